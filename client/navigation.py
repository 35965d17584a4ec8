"""Interactive navigation: controllers that turn keys and mouse into the camera's pose.

Tours (the scene's or a kiosk's) are ``proto.tour.Tour``, shared with the server's prediction.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from proto.tour import Tour, field as _field, perpendicular as _perpendicular, unit as _unit

__all__ = ["Driving", "FlyController", "WalkController", "Navigator", "KEYS", "WORLD_UP"]

_EPS = 1e-9


# --------------------------------------------------------------------------- interactive navigation
#
# Controllers turn key and mouse input into a pose for client time ``t``. They
# know nothing of glfw (``client.window`` maps its events onto ``key`` and
# ``look``), so tests drive them directly. Motion is integrated between calls of
# ``pose_at``, and both translation and turning are capped: the caps are what
# the client announces in ``Hello.max_speed`` / ``Hello.max_turn``, and the
# server's conservative camera (and its teleport detection) relies on the
# camera never moving faster than announced.

#: The world's up axis: scenes are z-up (``server.scene`` tours and start poses use up = +z).
WORLD_UP = np.array([0.0, 0.0, 1.0])

#: Key names the controllers understand: move (w a s d), down/up (q e), faster (shift), turn (arrows).
KEYS = ("w", "a", "s", "d", "q", "e", "shift", "left", "right", "up", "down")


def _rotate(v: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues: ``v`` (3,) rotated by ``angle`` radians about unit ``axis`` (3,), right-handed."""
    c, s = np.cos(angle), np.sin(angle)
    return v * c + np.cross(axis, v) * s + axis * float(np.dot(axis, v)) * (1.0 - c)


def _pose(start: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A ``Pose``, a mapping or an (eye, forward, up) triple → float64 eye, unit forward, unit up ⟂ forward."""
    if isinstance(start, (tuple, list)) and len(start) == 3 and np.ndim(start[0]) == 1:
        eye, f, u = start
    else:
        eye, f, u = (_field(start, k) for k in ("eye", "forward", "up"))
    eye = np.array(eye, np.float64).reshape(3)
    f, bad = _unit(np.array(f, np.float64).reshape(1, 3))
    if bad.any():
        raise ValueError("start pose with a zero forward vector")
    u = Tour._orthogonal_up(f, np.array(u, np.float64).reshape(1, 3))
    return eye, f[0], u[0]


class _Controller:
    """Shared input state and integration; subclasses say how turning and moving act on the pose.

    start : the pose to start at (``Pose``, mapping or (eye, forward, up))
    speed : m/s with no modifier; Shift multiplies it by ``fast``
    max_turn : °/s, the cap on turning (mouse and arrow keys alike); arrows turn at this rate
    sensitivity : degrees of turn per pixel of mouse drag
    """

    mode = ""

    def __init__(self, start: Any, *, speed: float, fast: float = 4.0, max_turn: float = 90.0,
                 sensitivity: float = 0.15) -> None:
        for name, v in (("speed", speed), ("fast", fast), ("max_turn", max_turn), ("sensitivity", sensitivity)):
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive finite number, got {v!r}")
        if fast < 1:
            raise ValueError(f"fast must be at least 1, got {fast!r}")
        self.speed, self.fast, self.sensitivity = float(speed), float(fast), float(sensitivity)
        self.max_turn = float(max_turn)
        """°/s: no turn is ever faster (announce it as ``Hello.max_turn``)."""
        self.held: set[str] = set()
        """Key names currently held down."""
        self._look = np.zeros(2)  # pending (yaw right, pitch up) in degrees, applied at most max_turn °/s
        self._t: float | None = None
        self._place(*_pose(start))

    @property
    def max_speed(self) -> float:
        """m/s: no motion is ever faster (announce it as ``Hello.max_speed``)."""
        return self.speed * self.fast

    # ----------------------------------------------------------------- input (no glfw)

    def key(self, name: str, pressed: bool) -> bool:
        """A key went down (``pressed``) or up; returns whether this controller uses it."""
        name = name.lower()
        if name not in KEYS:
            return False
        if pressed:
            self.held.add(name)
        else:
            self.held.discard(name)
        return True

    def look(self, dx: float, dy: float) -> None:
        """A mouse drag of (dx, dy) pixels, screen axes (y down): right turns right, down looks down."""
        self._look += (float(dx) * self.sensitivity, -float(dy) * self.sensitivity)
        self._look = np.clip(self._look, -180.0, 180.0)  # a frantic drag does not queue up seconds of turning

    def clear_input(self) -> None:
        """Forget held keys and pending turns (the window lost focus: no key stays stuck)."""
        self.held.clear()
        self._look[:] = 0.0

    # ----------------------------------------------------------------- pose

    def pose_at(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Advance to client time ``t`` (s) and return (eye, forward, up), float64 (3,) each.

        The first call only sets the clock; a ``t`` earlier than the last one
        changes nothing (time does not run back).
        """
        t = float(t)
        dt = 0.0 if self._t is None else max(0.0, t - self._t)
        self._t = t if self._t is None else max(self._t, t)
        if dt > 0.0:
            self._turn(dt)
            self._move(dt)
        return self.pose

    @property
    def pose(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The current (eye, forward, up), copies."""
        return self.eye.copy(), self.forward.copy(), self.up.copy()

    @property
    def t(self) -> float | None:
        """The client time the pose is for (the latest ``pose_at``), None before the first."""
        return self._t

    def _turn(self, dt: float) -> None:
        h = self.held
        rate = self.max_turn * np.array([("right" in h) - ("left" in h), ("up" in h) - ("down" in h)], np.float64)
        want = self._look + rate * dt
        size = float(np.hypot(*want))
        k = min(1.0, self.max_turn * dt / size) if size > 0 else 1.0
        step = want * k
        self._look = self._look * (1.0 - k)  # the drag not yet turned waits; held arrows are a rate, never queued
        if np.any(step):
            self._apply_turn(np.radians(step[0]), np.radians(step[1]))

    def _move(self, dt: float) -> None:
        h = self.held
        direction = self._direction(("w" in h) - ("s" in h), ("d" in h) - ("a" in h), ("e" in h) - ("q" in h))
        n = float(np.linalg.norm(direction))
        if n > _EPS:  # diagonal moves are no faster than straight ones
            speed = self.speed * (self.fast if "shift" in h else 1.0)
            self.eye = self.eye + direction / n * speed * dt

    # ----------------------------------------------------------------- per mode

    def _place(self, eye: np.ndarray, forward: np.ndarray, up: np.ndarray) -> None:
        raise NotImplementedError

    def _apply_turn(self, yaw: float, pitch: float) -> None:
        raise NotImplementedError

    def _direction(self, ahead: int, right: int, rise: int) -> np.ndarray:
        raise NotImplementedError


class FlyController(_Controller):
    """Free flight: the camera's own frame turns (yaw about its up, pitch about its right),
    W/S move along the view direction, A/D sideways and Q/E along the camera's up.

    Nothing keeps the horizon level, as in any six-degree-of-freedom flight;
    switching to walking (``Navigator.toggle``) levels it.
    """

    mode = "fly"

    def __init__(self, start: Any, *, speed: float = 8.0, fast: float = 4.0, max_turn: float = 90.0,
                 sensitivity: float = 0.15) -> None:
        super().__init__(start, speed=speed, fast=fast, max_turn=max_turn, sensitivity=sensitivity)

    def _place(self, eye: np.ndarray, forward: np.ndarray, up: np.ndarray) -> None:
        self.eye, self.forward, self.up = eye.copy(), forward.copy(), up.copy()

    def _apply_turn(self, yaw: float, pitch: float) -> None:
        f, u = self.forward, self.up
        f = _rotate(f, u, -yaw)  # yaw right: clockwise seen from the camera's up
        right = np.cross(f, u)
        f, u = _rotate(f, right, pitch), _rotate(u, right, pitch)
        f = f / np.linalg.norm(f)  # re-orthonormalise: rounding must not build up over a long flight
        u = u - np.dot(u, f) * f
        self.forward, self.up = f, u / np.linalg.norm(u)

    def _direction(self, ahead: int, right: int, rise: int) -> np.ndarray:
        return ahead * self.forward + right * np.cross(self.forward, self.up) + rise * self.up


class WalkController(_Controller):
    """Walking: the eye stays at the start pose's height, moves only horizontally,
    turns about the world up (+z) and pitches within ±``max_pitch`` degrees; Q/E do nothing.

    The view keeps the world's up, so the horizon stays level.
    """

    mode = "walk"

    def __init__(self, start: Any, *, speed: float = 2.0, fast: float = 4.0, max_turn: float = 90.0,
                 sensitivity: float = 0.15, max_pitch: float = 80.0) -> None:
        if not 0 < max_pitch < 90:
            raise ValueError(f"max_pitch must lie in (0, 90) degrees, got {max_pitch!r}")
        self.max_pitch = float(max_pitch)
        super().__init__(start, speed=speed, fast=fast, max_turn=max_turn, sensitivity=sensitivity)

    def _place(self, eye: np.ndarray, forward: np.ndarray, up: np.ndarray) -> None:
        self.eye = eye.copy()
        self.height = float(eye[2])
        """The fixed eye height (world z, m)."""
        flat = forward[:2] if np.hypot(*forward[:2]) > 1e-6 else up[:2] * -np.sign(forward[2])
        self.yaw = float(np.arctan2(flat[1], flat[0])) if np.hypot(*flat) > 1e-6 else np.pi / 2
        """Heading, radians counter-clockwise from +x."""
        limit = np.radians(self.max_pitch)
        self.pitch = float(np.clip(np.arcsin(np.clip(forward[2], -1, 1)), -limit, limit))
        """Radians above the horizon, within ±max_pitch."""

    @property
    def forward(self) -> np.ndarray:  # type: ignore[override]
        cp = np.cos(self.pitch)
        return np.array([cp * np.cos(self.yaw), cp * np.sin(self.yaw), np.sin(self.pitch)])

    @property
    def up(self) -> np.ndarray:  # type: ignore[override]
        sp = np.sin(self.pitch)
        return np.array([-sp * np.cos(self.yaw), -sp * np.sin(self.yaw), np.cos(self.pitch)])

    def _apply_turn(self, yaw: float, pitch: float) -> None:
        self.yaw = float(np.mod(self.yaw - yaw + np.pi, 2 * np.pi) - np.pi)
        limit = np.radians(self.max_pitch)
        self.pitch = float(np.clip(self.pitch + pitch, -limit, limit))

    def _direction(self, ahead: int, right: int, rise: int) -> np.ndarray:
        heading = np.array([np.cos(self.yaw), np.sin(self.yaw), 0.0])
        side = np.array([np.sin(self.yaw), -np.cos(self.yaw), 0.0])  # heading × world up
        return ahead * heading + right * side

    def _move(self, dt: float) -> None:
        super()._move(dt)
        self.eye[2] = self.height


class Driving:
    """What a navigator passes on to the controller it drives (``self.controller``): input and poses."""

    controller: _Controller

    def key(self, name: str, pressed: bool) -> bool:
        return self.controller.key(name, pressed)

    def look(self, dx: float, dy: float) -> None:
        self.controller.look(dx, dy)

    def clear_input(self) -> None:
        self.controller.clear_input()

    def pose_at(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.controller.pose_at(t)

    @property
    def pose(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.controller.pose

    @property
    def t(self) -> float | None:
        return self.controller.t


class Navigator(Driving):
    """The window's camera: a fly or a walk controller, switched by ``toggle`` (Tab) where the camera is.

    Speeds are m/s (Shift multiplies by ``fast``); ``max_speed`` and ``max_turn``
    cover both modes, so one ``Hello`` announces limits that hold whichever mode
    the user switches to. ``start`` may come later, through ``place``.
    """

    MODES = ("fly", "walk")

    def __init__(self, start: Any = None, *, mode: str = "fly", fly_speed: float = 8.0, walk_speed: float = 2.0,
                 fast: float = 4.0, max_turn: float = 90.0, sensitivity: float = 0.15) -> None:
        if mode not in self.MODES:
            raise ValueError(f"mode must be one of {', '.join(self.MODES)}, got {mode!r}")
        self._options = dict(fast=fast, max_turn=max_turn, sensitivity=sensitivity)
        self._speeds = {"fly": float(fly_speed), "walk": float(walk_speed)}
        origin = start if start is not None else ((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
        self.controller: FlyController | WalkController = self._make(mode, origin)

    def _make(self, mode: str, start: Any) -> FlyController | WalkController:
        cls = FlyController if mode == "fly" else WalkController
        return cls(start, speed=self._speeds[mode], **self._options)

    @property
    def mode(self) -> str:
        return self.controller.mode

    @property
    def max_speed(self) -> float:
        """m/s, the faster mode's cap."""
        return max(self._speeds.values()) * self._options["fast"]

    @property
    def max_turn(self) -> float:
        """°/s."""
        return float(self._options["max_turn"])

    def place(self, start: Any) -> None:
        """Put the camera at a pose (the welcome's start), keeping the mode, the clock and held keys."""
        self._switch(self.mode, start)

    def toggle(self) -> str:
        """Switch fly ↔ walk at the current pose (walking keeps the current eye height); returns the new mode."""
        self._switch("walk" if self.mode == "fly" else "fly", self.controller.pose)
        return self.mode

    def _switch(self, mode: str, start: Any) -> None:
        old = self.controller
        new = self._make(mode, start)
        new.held, new._t = set(old.held), old._t  # a key held through the switch keeps moving
        self.controller = new

