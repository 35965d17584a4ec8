"""Linear path prediction of the camera, and Zach's conservative camera (Zach 2002, 3.3 and 4.3).

A selection made at t is drawn during [t + 2τ, t + 3τ) (three stages with
morphing), so it must know where the client will look then. Zach predicts the
eye, the view direction and the up vector *linearly*: low-order polynomials
oscillate too much far outside the sampled interval. The samples come from a
real network, so the line is fitted, not drawn through the last two points:
weighted least squares over a short window (recent samples weigh more, so a
turn is followed quickly) with Huber reweighting (one bad sample does not
throw the line), and the extrapolation never goes faster than the navigation
allows (θ, ω).

Where prediction can be wrong, the conservative camera of ``conservative_camera``
holds everything the user can reach, so every potentially visible object is
drawn at some level.

Beyond the paper, the predictor knows the navigation when the client states it
(``navigation``): a tour plan gives exact future poses wherever it covers the
time asked for (``set_plan``), and a walking camera's extrapolated eye stays on
walkable ground and within bounds (``navigable``).

Pure: times are the client's clock as the samples carry it; nothing here reads
a clock or does I/O.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np

from proto.messages import TourPlan

from . import kernels
from .navigation import Navigable, Plan, check_plan, plan_after
from .snapshot import dump_fields, load_fields

__all__ = ["MotionLimits", "Pose", "Predictor", "conservative_camera", "tour_speed"]

#: Residuals past HUBER × the median residual (per eye / forward / up) are downweighted.
HUBER = 2.5
#: Reweighting rounds after the first least-squares fit.
ROUNDS = 3
#: Shrinkage of fitted rates by their noise: rate · (1 − SHRINK · var / |rate|²)⁺ (0: never shrink).
SHRINK = 4.0
#: The smallest residual scale (m for the eye, unit-vector units for directions): exact data stays exact.
_SCALE_FLOOR = np.array([1e-4, 1e-6, 1e-6])
#: A jump shorter than this is never a teleport (no speed limit given): jitter at tiny time steps.
TELEPORT_SLACK = 1.0
#: Seconds of camera samples between fits while no prediction asks for one (θ and ω follow the fits).
REFIT_EVERY = 0.25
#: A view-direction change smaller than this is never a teleport, however fast.
TELEPORT_MIN_TURN_DEG = 60.0
_EPS = 1e-12


def tour_speed(tour) -> float:
    """The fastest a scene's own tour moves (m/s), from its keys ({"t", "eye", …} mappings); 0 if it cannot say.

    A flyover of a mountain (St. Helens' tour: about 1 km/s) is not a string of teleports: a session
    whose client gave no speed limit takes its teleport speed from this.
    """
    if not tour or len(tour) < 2:
        return 0.0
    t = np.array([float(k["t"]) for k in tour], np.float64)
    eye = np.array([k["eye"] for k in tour], np.float64).reshape(-1, 3)
    order = np.argsort(t, kind="stable")
    t, eye = t[order], eye[order]
    dt = np.diff(t)
    ok = dt > 1e-6
    if not ok.any():
        return 0.0
    return float((np.linalg.norm(np.diff(eye, axis=0), axis=1)[ok] / dt[ok]).max())


@dataclass(frozen=True)
class MotionLimits:
    """Navigation limits: max translational speed θ (m/s) and max angular speed ω (rad/s); None = use the maxima observed."""

    speed: float | None = None
    turn: float | None = None

    def __post_init__(self) -> None:
        for name in ("speed", "turn"):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(v) and v > 0):
                raise ValueError(f"MotionLimits.{name} must be a positive finite number or None, got {v!r}")


@dataclass(frozen=True, eq=False)
class Pose:
    """A camera pose: eye (3,), forward (3,) unit, up (3,) unit and orthogonal to forward; float64."""

    eye: np.ndarray
    forward: np.ndarray
    up: np.ndarray


def _norm(v: np.ndarray) -> float:
    """``np.linalg.norm`` of a float64 vector — the same number (it is √(v·v)) without its general machinery."""
    return math.sqrt(float(v.dot(v)))


def _unit(v: np.ndarray) -> tuple[np.ndarray, float]:
    n = _norm(v)
    return (v / n if n > _EPS else v), n


def _perpendicular(f: np.ndarray) -> np.ndarray:
    axis = np.zeros(3)
    axis[int(np.argmin(np.abs(f)))] = 1.0
    return _unit(np.cross(f, axis))[0]


def _orthogonal_up(f: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Unit ``u`` made perpendicular to unit ``f`` (Gram-Schmidt); a degenerate up gets any perpendicular."""
    u, n = _unit(u - np.dot(u, f) * f)
    return u if n > 1e-9 else _perpendicular(f)


def _vector(v, name: str) -> np.ndarray:
    a = np.asarray(v, np.float64)
    if a.shape != (3,):
        raise ValueError(f"{name} must be 3 numbers, got shape {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name} must be finite, got {a.tolist()}")
    return a


def _sample(eye, forward, up) -> np.ndarray:
    """(9,) eye, unit forward, unit up orthogonal to forward; ValueError on bad input.

    ``_unit`` and ``_orthogonal_up`` in scalar arithmetic, the three vectors checked in one array: it runs for
    every pose of every session, and numpy's per-call overhead on 3-vectors is most of what they cost.
    """
    try:
        a = np.array((eye, forward, up), np.float64)
    except (TypeError, ValueError):  # ragged or not numbers: the per-vector checks name which
        a = None
    if a is None or a.shape != (3, 3) or not np.isfinite(a).all():
        a = np.stack([_vector(eye, "eye"), _vector(forward, "forward"), _vector(up, "up")])
    (ex, ey, ez), (fx, fy, fz), (ux, uy, uz) = a.tolist()
    n = math.sqrt(fx * fx + fy * fy + fz * fz)
    if n <= 1e-9:
        raise ValueError("forward must not be zero")
    fx, fy, fz = fx / n, fy / n, fz / n
    d = ux * fx + uy * fy + uz * fz
    ux, uy, uz = ux - d * fx, uy - d * fy, uz - d * fz
    m = math.sqrt(ux * ux + uy * uy + uz * uz)
    if m <= 1e-9:  # a degenerate up gets any perpendicular
        ux, uy, uz = _perpendicular(np.array((fx, fy, fz))).tolist()
    else:
        ux, uy, uz = ux / m, uy / m, uz / m
    return np.array((ex, ey, ez, fx, fy, fz, ux, uy, uz))


def _line(powers: np.ndarray, x: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least-squares line x ≈ a + b·s per column: powers (3, n) = 1, s, s²; x, w (n, 9) → a, b (9,).

    Too little spread in s (one sample, or all weight on one) gives b = 0 and the weighted mean.
    """
    s0, s1, ss = powers @ w  # (3, 9) moments of the weights
    wx = w * x
    sy, sxy = powers[:2] @ wx
    det = s0 * ss - s1 * s1
    ok = det > 1e-10 * s0 * s0  # weighted variance of s above (10 µs)²
    safe = np.where(ok, det, 1.0)
    b = np.where(ok, (s0 * sxy - s1 * sy) / safe, 0.0)
    a = np.where(ok, (ss * sy - s1 * sxy) / safe, sy / np.maximum(s0, 1e-300))
    return a, b


def _significance(s: np.ndarray, res: np.ndarray, w: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(9,) factor in [0, 1] that shrinks each group's fitted rate towards zero by its noise (James-Stein).

    A rate no larger than the scatter of the samples explains is jitter, not
    motion; extrapolating it over 1.5 s would amplify the noise. The variance
    of the slope is the sandwich estimate Σw²(s − s̄)²r² / (Σw(s − s̄)²)² per
    component, summed over the group's three; the factor is
    (1 − SHRINK · variance / |b|²)⁺, 1 for exact data.
    """
    s_bar = (w * s[:, None]).sum(0) / w.sum(0)
    d = s[:, None] - s_bar
    sxx = (w * d * d).sum(0)
    var = (w * w * d * d * res * res).sum(0) / np.maximum(sxx * sxx, 1e-300)
    var_g = var.reshape(3, 3).sum(1)
    b2 = (b * b).reshape(3, 3).sum(1)
    keep = np.clip(1.0 - SHRINK * var_g / np.maximum(b2, 1e-300), 0.0, 1.0)
    return np.repeat(np.where(b2 > 0, keep, 1.0), 3)


def _tangent(v0: np.ndarray, rate: np.ndarray, limit: float) -> tuple[np.ndarray, float]:
    """The rate of a unit-vector line made tangent to it and clamped to ``limit`` rad/s; and the rate before clamping.

    A unit vector's velocity is perpendicular to it; the radial part of a fitted
    rate only shrinks the extrapolated vector towards zero.
    """
    n2 = float(np.dot(v0, v0))
    if n2 <= 1e-18:
        return np.zeros(3), 0.0
    rate = rate - np.dot(rate, v0) / n2 * v0
    angular = _norm(rate) / math.sqrt(n2)
    if angular > limit:
        rate = rate * (limit / angular)
    return rate, angular


class Predictor:
    """Camera path prediction from a client's timestamped samples (client clock, seconds).

    Samples older than ``window`` before the newest leave the fit; recency weights
    halve every ``half_life`` seconds; ``gap`` seconds without samples and a
    teleport (``teleport_speed`` m/s, or 3·θ + 5 m when a speed limit is given;
    a turn of more than 60° at more than ``teleport_turn_deg`` °/s) start the
    history afresh, since velocity across them is unknown. θ and ω default to the
    fastest motion seen, never below ``min_speed`` m/s and ``min_turn_deg`` °/s.
    """

    def __init__(
        self,
        limits: MotionLimits = MotionLimits(),
        *,
        window: float = 1.0,
        gap: float = 0.5,
        half_life: float = 0.3,
        teleport_speed: float = 200.0,
        teleport_turn_deg: float = 120.0,
        min_speed: float = 1.0,
        min_turn_deg: float = 10.0,
    ) -> None:
        for name, v in (("window", window), ("gap", gap), ("half_life", half_life), ("teleport_speed", teleport_speed),
                        ("teleport_turn_deg", teleport_turn_deg), ("min_speed", min_speed), ("min_turn_deg", min_turn_deg)):
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive finite number, got {v!r}")
        self.limits = limits
        self.window, self.gap, self.half_life = float(window), float(gap), float(half_life)
        self.teleport_speed, self.teleport_turn = float(teleport_speed), math.radians(teleport_turn_deg)
        self.min_speed, self.min_turn = float(min_speed), math.radians(min_turn_deg)
        self.resets = 0
        self._t = np.empty(0)
        self._x = np.empty((0, 9))
        self._floor = -math.inf  # samples from before the last reset are stale
        self._a = self._b = np.zeros(9)
        self._speed_seen = 0.0
        self._turn_seen = 0.0
        self._stale = False  # samples arrived since the last fit: refit when a prediction is asked for
        self._fit_t = -math.inf  # the newest sample's time at the last fit
        self.plan: Plan | None = None  # the tour plan the client announced (``set_plan``)
        self.navigable: Navigable | None = None  # where the camera can go (the owner's, like the limits)
        self.revision = 0  # counts plan changes: a prediction cached before one is stale

    # ------------------------------------------------------------------ state

    @property
    def latest(self) -> float | None:
        """Time of the newest sample kept, None before the first."""
        return float(self._t[-1]) if len(self._t) else None

    @property
    def theta(self) -> float:
        """θ, m/s: the speed limit if given, else the fastest fitted speed seen (at least ``min_speed``)."""
        if self.limits.speed is not None:
            return float(self.limits.speed)
        self._fit()
        return max(self.min_speed, self._speed_seen)

    @property
    def omega(self) -> float:
        """ω, rad/s: the turn limit if given, else the fastest fitted turn of forward seen (at least ``min_turn_deg``)."""
        if self.limits.turn is not None:
            return float(self.limits.turn)
        self._fit()
        return max(self.min_turn, self._turn_seen)

    # ------------------------------------------------------------------ input

    def add(self, t: float, eye, forward, up) -> bool:
        """Take one sample; returns True if it reset the prediction (teleport or gap).

        A sample at a time already held replaces it (the last received wins); an
        older one is inserted in time order, or ignored when it is older than the
        window or than the last reset. Only a sample that becomes the newest is
        checked for gap and teleport.
        """
        t = float(t)
        if not math.isfinite(t):
            raise ValueError(f"t must be finite, got {t!r}")
        x = _sample(eye, forward, up)
        if not len(self._t):
            self._start(t, x)
            return False
        latest = self._t[-1]
        if t < self._floor or t < latest - self.window:
            return False
        if t > latest + self.gap:
            return self._reset(t, x)
        n = len(self._t)
        i = n if t > latest else int(np.searchsorted(self._t, t))  # where t goes (the samples are in time order)
        if t >= latest and i > 0:  # the newest sample before it
            if self._teleport(t - self._t[i - 1], self._x[i - 1], x):
                return self._reset(t, x)
        if i < n and self._t[i] == t:
            self._x[i] = x
        elif i == n:  # the usual case, a newer pose: appended, without np.insert's general machinery
            self._t = np.concatenate((self._t, (t,)))
            self._x = np.concatenate((self._x, x[None, :]))
        else:
            self._t = np.insert(self._t, i, t)
            self._x = np.insert(self._x, i, x, axis=0)
        # The window: a suffix of the samples in time order, and at least the newest two.
        first = min(int(np.searchsorted(self._t, self._t[-1] - self.window)), max(len(self._t) - 2, 0))
        if first:
            self._t, self._x = self._t[first:], self._x[first:]
        # Poses come many times per τ and predictions are asked for once per τ: fit lazily, but at least
        # every REFIT_EVERY seconds of samples so the fastest motion seen (θ, ω) is still tracked.
        self._stale = True
        if t >= self._fit_t + REFIT_EVERY:
            self._fit()
        return False

    def set_plan(self, message: TourPlan, scene_bounds: np.ndarray) -> None:
        """Take a client's tour plan (``navigation.plan_after``); ``ProtocolError`` (predictor unchanged) for
        a plan ``navigation.check_plan`` refuses, judged against the newest sample."""
        check_plan(message, scene_bounds, self.latest)
        self.plan = plan_after(self.plan, message, self.latest)
        self.revision += 1

    # ------------------------------------------------------------------ snapshot

    #: The fields a snapshot holds: the recent poses, their fit and the motion seen; the limits stay the owner's.
    STATE = ("window", "gap", "half_life", "teleport_speed", "teleport_turn", "min_speed", "min_turn", "resets",
             "_t", "_x", "_floor", "_a", "_b", "_speed_seen", "_turn_seen")

    def to_state(self) -> dict:
        """The history, its fit and the tour plan as plain data (``from_state`` reads it back)."""
        self._fit()  # the fit is lazy: bring it up to the poses held
        return {**dump_fields(self, self.STATE), "plan": None if self.plan is None else self.plan.to_state()}

    def from_state(self, state) -> None:
        """Take in ``to_state``'s data; ValueError (predictor unchanged) if it does not fit. A snapshot from
        before plans were holds none."""
        trial = copy.copy(self)
        load_fields(trial, state, self.STATE, "predictor", variable=("_t", "_x"))
        if trial._t.shape[0] != trial._x.shape[0] or (trial._t.size and np.any(np.diff(trial._t) < 0)):
            raise ValueError("predictor: times and poses do not match")
        trial.plan = Plan.from_state(state.get("plan"))
        trial.revision = self.revision + 1
        self.__dict__.update(trial.__dict__)

    def _fit(self) -> None:
        if self._stale:
            self._stale = False
            self._fit_t = float(self._t[-1])
            self._refit()

    def _start(self, t: float, x: np.ndarray) -> None:
        self._t, self._x = np.array([t]), x[None, :].copy()
        self._floor = t
        self._a, self._b = x.copy(), np.zeros(9)
        self._stale = False
        self._fit_t = t

    def _reset(self, t: float, x: np.ndarray) -> bool:
        self._start(t, x)
        self.resets += 1
        return True

    def _teleport(self, dt: float, x0: np.ndarray, x1: np.ndarray) -> bool:
        """Whether going from x0 to x1 in dt seconds is faster than any navigation: a jump, not a motion."""
        jump = _norm(x1[:3] - x0[:3])
        if self.limits.speed is not None:
            far = jump > 3.0 * self.limits.speed * dt + 5.0
        else:
            far = jump > self.teleport_speed * dt + TELEPORT_SLACK
        turn = math.acos(min(1.0, max(-1.0, float(np.dot(x0[3:6], x1[3:6])))))
        fast = turn > math.radians(TELEPORT_MIN_TURN_DEG) and turn > self.teleport_turn * dt
        return far or fast

    def _refit(self) -> None:
        """Recency-weighted line through the window, Huber-reweighted per eye / forward / up."""
        s = self._t - self._t[-1]
        x = self._x
        n = len(s)
        ready = kernels.compiled()
        if ready is not None:  # the same fit in one compiled pass (``kernels.motion``)
            self._a, self._b = ready.motion.refit(self._t, x, self.half_life, ROUNDS, HUBER, SHRINK, _SCALE_FLOOR)
            self._seen(s, self._b)
            return
        recency = 0.5 ** (-s / self.half_life)
        powers = np.stack([np.ones_like(s), s, s * s])
        w = np.repeat(recency[:, None], 9, axis=1)
        a, b = _line(powers, x, w)
        for _ in range(ROUNDS if n > 2 else 0):
            res = np.linalg.norm((x - a - b * s[:, None]).reshape(n, 3, 3), axis=2)  # (n, 3): eye, forward, up
            scale = np.maximum(HUBER * np.sort(res, axis=0)[(n - 1) // 2], _SCALE_FLOOR)  # lower median
            w = np.repeat(recency[:, None] * np.minimum(1.0, scale / np.maximum(res, 1e-300)), 3, axis=1)
            a, b = _line(powers, x, w)
        if n > 2 and SHRINK > 0:
            b = b * _significance(s, x - a - b * s[:, None], w, b)
        self._a, self._b = a, b
        self._seen(s, b)

    def _seen(self, s: np.ndarray, b: np.ndarray) -> None:
        """The fastest motion seen (θ, ω without limits), from fits over at least a quarter of the window."""
        if len(s) >= 3 and -s[0] >= 0.25 * self.window:
            self._speed_seen = max(self._speed_seen, _norm(b[:3]))
            self._turn_seen = max(self._turn_seen, _tangent(self._a[3:6], b[3:6], math.inf)[1])

    # ------------------------------------------------------------------ output

    def pose(self, t: float) -> Pose:
        """The predicted pose at client time ``t``: the plan's where it covers t, else the fitted line evaluated
        at t, no faster than θ and ω (and confined to where the camera can go)."""
        return self.poses([t])[0]

    def poses(self, times) -> list[Pose]:
        """``pose`` at each of ``times``; the rates (clamped to θ and ω) are worked out once for all of them."""
        times = [float(t) for t in times]
        for t in times:
            if not math.isfinite(t):
                raise ValueError(f"t must be finite, got {t!r}")
        covered = self.plan.covers(np.array(times)) if self.plan is not None else np.zeros(len(times), bool)
        rest = [t for t, c in zip(times, covered) if not c]
        linear = iter(self._linear(rest) if rest else ())
        planned = iter(())
        if covered.any():
            eye, f, u = self.plan.poses(np.array(times)[covered])
            planned = iter([Pose(eye=e, forward=a, up=b) for e, a, b in zip(eye, f, u)])
        return [next(planned) if c else next(linear) for c in covered]

    def _linear(self, times: list[float]) -> list[Pose]:
        """The fitted line's poses at ``times`` (see ``poses``)."""
        if not len(self._t):
            raise ValueError("no camera sample yet")
        self._fit()
        a, b = self._a, self._b
        theta, omega = self.theta, self.omega
        velocity = b[:3]
        speed = _norm(velocity)
        if speed > theta:
            velocity = velocity * (theta / speed)
        f_rate, _ = _tangent(a[3:6], b[3:6], omega)
        u_rate, _ = _tangent(a[6:9], b[6:9], omega)
        latest = float(self._t[-1])
        out = []
        for t in times:
            h = t - latest
            eye = a[:3] + velocity * h
            forward, n = _unit(a[3:6] + f_rate * h)
            if n <= 1e-9:
                forward = self._x[-1, 3:6].copy()
            up = a[6:9] + u_rate * h
            if _norm(up - np.dot(up, forward) * forward) <= 1e-9:
                up = self._x[-1, 6:9]
            out.append(Pose(eye=eye, forward=forward, up=_orthogonal_up(forward, up)))
        if self.navigable is not None and out:
            eyes = self.navigable.confine(a[:3], np.array([p.eye for p in out]))
            out = [Pose(eye=e, forward=p.forward, up=p.up) for e, p in zip(eyes, out)]
        return out

    def samples(self, t0: float, t1: float, k: int = 3) -> list[tuple[float, Pose]]:
        """``k`` predicted poses sampling [t0, t1) at interval midpoints: Zach's sampled future cameras t_k."""
        if k < 1:
            raise ValueError(f"k must be at least 1, got {k}")
        step = (float(t1) - float(t0)) / k
        times = [float(t0) + (i + 0.5) * step for i in range(k)]
        return list(zip(times, self.poses(times)))


def conservative_camera(
    pose: Pose,
    fov_y_deg: float,
    aspect: float,
    tau: float,
    theta: float,
    omega: float,
    stages: int = 3,
    max_fov_deg: float = 170.0,
    *,
    strict: bool = False,
) -> tuple[Pose, float]:
    """Zach's conservative camera: field of view fov + 2·stages·τ·ω, eye moved back along the view direction by
    stages·τ·θ / sin(fov/2 + stages·τ·ω) (stages=3 with morphing, 2 without). Returns (pose, fov_y_deg).

    It holds every view the user can reach in stages·τ: the eye within
    r = stages·τ·θ, the view turned by up to a = stages·τ·ω. For a non-square
    viewport both half-angles widen by a (the horizontal one from fov_y and
    aspect); the returned fov_y is the larger of the widened vertical angle and
    the one that, at the *same* aspect, gives the widened horizontal angle, so
    a caller keeps its aspect. The eye goes back by r / sin(smaller widened
    half-angle): the sphere of radius r round the eye then lies inside every
    side plane. Each half-angle is capped at ``max_fov_deg`` / 2.

    The paper's widening by a is exact for a turn within one plane of the
    pyramid's axis (pure yaw or pitch); a turn that moves a *corner* of a
    pyramid straight out can leave it by a few degrees. ``strict=True`` widens
    each half-angle by the exact corner bound asin(sin a · √(1 + tx² + ty²) / √(1 + t²))
    (tx, ty: tangents of the half-angles, t the one widened) and then holds
    every turn by up to a about any axis.
    """
    fov_y_deg, aspect, tau, theta, omega = map(float, (fov_y_deg, aspect, tau, theta, omega))
    if not 0.0 < fov_y_deg < 180.0:
        raise ValueError(f"fov_y_deg must lie in (0, 180), got {fov_y_deg}")
    if not 0.0 < max_fov_deg < 180.0:
        raise ValueError(f"max_fov_deg must lie in (0, 180), got {max_fov_deg}")
    if not (math.isfinite(aspect) and aspect > 0):
        raise ValueError(f"aspect must be positive, got {aspect}")
    for name, v in (("tau", tau), ("theta", theta), ("omega", omega)):
        if not (math.isfinite(v) and v >= 0):
            raise ValueError(f"{name} must be finite and non-negative, got {v}")
    if stages < 1:
        raise ValueError(f"stages must be at least 1, got {stages}")
    turn = stages * tau * omega
    reach = stages * tau * theta
    half_y = math.radians(fov_y_deg) / 2
    ty = math.tan(half_y)
    tx = aspect * ty
    half_x = math.atan(tx)
    if strict:
        corner = math.sqrt(1 + tx * tx + ty * ty)
        s = math.sin(min(turn, math.pi / 2))
        grow_x = math.asin(min(1.0, s * corner / math.sqrt(1 + tx * tx))) if turn < math.pi / 2 else math.pi / 2
        grow_y = math.asin(min(1.0, s * corner / math.sqrt(1 + ty * ty))) if turn < math.pi / 2 else math.pi / 2
    else:
        grow_x = grow_y = turn
    cap = math.radians(max_fov_deg) / 2
    wide_y = min(half_y + grow_y, cap)
    wide_x = min(half_x + grow_x, cap)
    half = min(max(wide_y, math.atan(math.tan(wide_x) / aspect)), cap)
    forward = _unit(np.asarray(pose.forward, np.float64))[0]
    back = reach / math.sin(min(wide_x, wide_y))
    eye = np.asarray(pose.eye, np.float64) - back * forward
    return Pose(eye=eye, forward=forward, up=np.array(pose.up, np.float64)), math.degrees(2 * half)
