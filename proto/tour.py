"""Camera tours: the pose a camera following a tour is at for any time ``t``.

A tour is a list of keyed poses (``proto.messages.TourKey``). Between keys the
eye moves in a straight line and the view direction and up vector are blended
by normalised linear interpolation (nlerp), which is cheap, vectorises, and is
close enough to slerp for keys a fraction of a second to a few seconds apart.
Tours loop, so a kiosk can run for as long as it likes; a one-key tour is a
fixed camera (what the client uses when a ``Welcome`` carries no tour).

It lives in the contract because both sides interpolate the same way: the
client draws along a tour, and the server predicts a camera that announced its
tour (``proto.messages.TourPlan``) from exactly these poses.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from .messages import TourKey

__all__ = ["Tour", "field", "unit", "perpendicular"]

_EPS = 1e-9


def field(key: TourKey | Mapping[str, Any], name: str) -> Any:
    return key[name] if isinstance(key, Mapping) else getattr(key, name)


def unit(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) → unit vectors (n, 3) and a mask (n,) of rows too short to normalise."""
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    bad = n[:, 0] < _EPS
    return v / np.maximum(n, _EPS), bad


def perpendicular(f: np.ndarray) -> np.ndarray:
    """(n, 3) unit vectors → (n, 3) unit vectors perpendicular to them (any one)."""
    axis = np.zeros_like(f)
    axis[np.arange(len(f)), np.argmin(np.abs(f), axis=1)] = 1.0
    p, _ = unit(np.cross(f, axis))
    return p


class Tour:
    """A looping piecewise-linear camera path.

    keys : sequence of ``TourKey`` or mappings with ``t``, ``eye``, ``forward``, ``up``;
        sorted by ``t`` here. Tour time runs over [t_first, t_last) and then
        wraps around to t_first, so a closed tour should repeat its first pose
        as its last key; times before ``t_first`` hold the first pose.
    """

    def __init__(self, keys: Sequence[TourKey | Mapping[str, Any]]) -> None:
        if len(keys) == 0:
            raise ValueError("a tour needs at least one key")
        t = np.array([float(field(k, "t")) for k in keys], np.float64)
        order = np.argsort(t, kind="stable")
        self.t: np.ndarray = t[order]
        """(k,) float64 key times, ascending."""
        self.eye: np.ndarray = np.array([field(keys[i], "eye") for i in order], np.float64).reshape(-1, 3)
        """(k, 3) float64 eye positions."""
        f, bad = unit(np.array([field(keys[i], "forward") for i in order], np.float64).reshape(-1, 3))
        if bad.any():
            raise ValueError("tour key with a zero forward vector")
        self.forward: np.ndarray = f
        """(k, 3) float64 unit view directions."""
        self.up: np.ndarray = self._orthogonal_up(f, np.array([field(keys[i], "up") for i in order], np.float64))
        """(k, 3) float64 unit up vectors, perpendicular to ``forward``."""

    @property
    def duration(self) -> float:
        """Seconds of one loop (0 for a one-key tour or keys all at one time)."""
        return float(self.t[-1] - self.t[0])

    @staticmethod
    def _orthogonal_up(f: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Gram-Schmidt ``u`` (n, 3) against unit ``f`` (n, 3); a degenerate up gets any perpendicular."""
        u = u.reshape(-1, 3) - np.sum(u.reshape(-1, 3) * f, axis=1, keepdims=True) * f
        u, bad = unit(u)
        if bad.any():
            u[bad] = perpendicular(f[bad])
        return u

    def pose_at(self, t: float | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Eye, forward, up at tour time(s) ``t``.

        t : float or (n,) float seconds
        returns three float64 arrays, each (3,) for a scalar ``t`` or (n, 3);
        ``forward`` and ``up`` are unit length and perpendicular.
        """
        scalar = np.ndim(t) == 0
        tt = np.atleast_1d(np.asarray(t, np.float64))
        if len(self.t) == 1 or self.duration <= 0.0:
            n = len(tt)
            eye, f, u = (np.repeat(a[:1], n, axis=0) for a in (self.eye, self.forward, self.up))
        else:
            local = self.t[0] + np.mod(np.maximum(tt - self.t[0], 0.0), self.duration)
            i = np.clip(np.searchsorted(self.t, local, side="right") - 1, 0, len(self.t) - 2)
            span = self.t[i + 1] - self.t[i]
            w = np.where(span > 0, (local - self.t[i]) / np.where(span > 0, span, 1.0), 0.0)[:, None]
            eye = (1 - w) * self.eye[i] + w * self.eye[i + 1]
            f, bad = unit((1 - w) * self.forward[i] + w * self.forward[i + 1])
            f[bad] = self.forward[i][bad]  # opposite keys: hold the earlier direction
            u = self._orthogonal_up(f, (1 - w) * self.up[i] + w * self.up[i + 1])
        if scalar:
            return eye[0], f[0], u[0]
        return eye, f, u
