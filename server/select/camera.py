"""View-frustum culling and projected screen size of bounding boxes, over all objects at once.

Funkhouser & Séquin measure an object's Size as the pixels its bounding box
covers on screen; culling and size come out of the same eight projected corners
per box. Everything here is arrays in, arrays out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from proto.camera import NEAR, normalize

__all__ = [
    "View",
    "frustum_planes",
    "cull_boxes",
    "cull_hierarchy",
    "screen_size",
    "screen_centre",
    "centre_offset",
    "screen_speed",
    "widened",
]

# The eight corners of a box as 0/1 choices of (hi - lo) along x, y, z.
_CORNERS = np.array([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], dtype=np.float64)

# Gribb & Hartmann: the six planes are row 3 plus or minus rows 0, 1, 2 of the clip matrix.
_PLANE_ROW = np.array([0, 0, 1, 1, 2, 2])
_PLANE_SIGN = np.array([1.0, -1.0, 1.0, -1.0, 1.0, -1.0])[:, None]


@dataclass(frozen=True)
class View:
    """A camera as the selection sees it: pose, field of view and viewport in pixels."""

    eye: np.ndarray  # (3,) float64
    forward: np.ndarray  # (3,) float64
    up: np.ndarray  # (3,) float64
    fov_y: float  # degrees
    width: int
    height: int
    far: float

    @classmethod
    def of_pose(cls, eye, forward, up, fov_y: float, viewport: tuple[int, int], bounds: np.ndarray) -> "View":
        eye = np.asarray(eye, np.float64)
        return cls(
            eye=eye,
            forward=normalize(forward),
            up=np.asarray(up, np.float64),
            fov_y=float(fov_y),
            width=int(viewport[0]),
            height=int(viewport[1]),
            far=_far_plane(eye, bounds),
        )

    @property
    def aspect(self) -> float:
        return self.width / self.height

    def matrix(self) -> np.ndarray:
        """(4, 4) float64 world → clip (read-only: computed once per view, a selection asks for it often)."""
        m = self.__dict__.get("_clip")
        if m is None:
            m = _clip_matrix(self.eye, self.forward, self.up, self.fov_y, self.aspect, self.far)
            m.flags.writeable = False
            self.__dict__["_clip"] = m  # a frozen dataclass: its fields never change, so neither does this
        return m

    def planes(self) -> np.ndarray:
        """(6, 4) ``frustum_planes(self.matrix())``, computed once per view (read-only)."""
        p = self.__dict__.get("_planes")
        if p is None:
            p = frustum_planes(self.matrix())
            p.flags.writeable = False
            self.__dict__["_planes"] = p
        return p


def _clip_matrix(eye, forward, up, fov_y: float, aspect: float, far: float) -> np.ndarray:
    """``projection_matrix(fov_y, aspect, NEAR, far) @ view_matrix(eye, forward, up)`` in scalar arithmetic.

    The same formulas as ``proto.camera`` (equal up to rounding; the tests compare them): numpy's
    per-call overhead on 3-vectors and 4×4 products costs more than the arithmetic, several times a selection.
    """
    fx, fy, fz = (float(c) for c in forward)
    ux, uy, uz = (float(c) for c in up)
    ex, ey, ez = (float(c) for c in eye)
    n = max(math.sqrt(fx * fx + fy * fy + fz * fz), 1e-300)
    fx, fy, fz = fx / n, fy / n, fz / n
    sx, sy, sz = fy * uz - fz * uy, fz * ux - fx * uz, fx * uy - fy * ux  # s = f × up
    n = max(math.sqrt(sx * sx + sy * sy + sz * sz), 1e-300)
    sx, sy, sz = sx / n, sy / n, sz / n
    vx, vy, vz = sy * fz - sz * fy, sz * fx - sx * fz, sx * fy - sy * fx  # u = s × f
    ts = -(sx * ex + sy * ey + sz * ez)
    tu = -(vx * ex + vy * ey + vz * ez)
    tf = fx * ex + fy * ey + fz * ez  # the third row is −f: its translation is +f·eye
    t = 1.0 / math.tan(math.radians(fov_y) / 2.0)
    a = t / aspect
    p22 = (far + NEAR) / (NEAR - far)
    p23 = 2.0 * far * NEAR / (NEAR - far)
    return np.array([
        [a * sx, a * sy, a * sz, a * ts],
        [t * vx, t * vy, t * vz, t * tu],
        [-p22 * fx, -p22 * fy, -p22 * fz, p22 * tf + p23],
        [fx, fy, fz, -tf],
    ])


def _far_plane(eye: np.ndarray, bounds: np.ndarray) -> float:
    """``proto.camera.far_plane`` (the same corners, norms and margin) without its meshgrid: it runs for
    every predicted camera of every selection."""
    b = np.asarray(bounds, np.float64)
    corners = np.where(_CORNERS > 0, b[1], b[0])
    d = corners - np.asarray(eye, np.float64)
    return float(np.sqrt((d * d).sum(axis=1)).max() * 1.05 + 1.0)


def widened(view: View, margin_deg: float) -> View:
    """The same camera with ``margin_deg`` more vertical field of view and the viewport grown to match.

    Pixels per radian stay the same, so an object's screen size is unchanged
    inside the original view and meaningful in the margin (where an object
    will be once the camera turns a little).
    """
    if margin_deg <= 0:
        return view
    fov = min(view.fov_y + margin_deg, 170.0)
    grow = np.tan(np.radians(fov) / 2) / np.tan(np.radians(view.fov_y) / 2)
    return View(
        eye=view.eye,
        forward=view.forward,
        up=view.up,
        fov_y=fov,
        width=max(1, int(round(view.width * grow))),
        height=max(1, int(round(view.height * grow))),
        far=view.far,
    )


def frustum_planes(clip: np.ndarray) -> np.ndarray:
    """(6, 4) inward plane equations (a, b, c, d), normalised, from a world → clip matrix (Gribb & Hartmann)."""
    m = np.asarray(clip, np.float64)
    planes = m[3] + _PLANE_SIGN * m[_PLANE_ROW]  # m3 ± m0, m3 ± m1, m3 ± m2 (× ±1 is exact)
    n = planes[:, :3]
    return planes / np.sqrt((n * n).sum(axis=1))[:, None]


def cull_boxes(lo: np.ndarray, hi: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """(n,) bool: boxes (n, 3) that are not entirely outside any plane (conservative p-vertex test)."""
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)
    visible = np.ones(lo.shape[0], dtype=bool)
    for a, b, c, d in planes:
        px = np.where(a >= 0, hi[:, 0], lo[:, 0])
        py = np.where(b >= 0, hi[:, 1], lo[:, 1])
        pz = np.where(c >= 0, hi[:, 2], lo[:, 2])
        visible &= a * px + b * py + c * pz + d >= 0
    return visible


def screen_size(lo: np.ndarray, hi: np.ndarray, clip: np.ndarray, width: int, height: int) -> np.ndarray:
    """(n,) float64 pixels covered by the screen rectangle of each box, clipped to the viewport.

    A box that reaches behind the eye plane covers an unbounded region; it is
    given the whole viewport, which is right for the walls one walks past.
    """
    lo = np.asarray(lo, np.float64)
    ext = np.asarray(hi, np.float64) - lo
    m = np.asarray(clip, np.float64)
    base = lo @ m[:, :3].T + m[:, 3]  # (n, 4) clip coordinates of the lo corner
    axes = ext[:, :, None] * m[:, :3].T[None, :, :]  # (n, 3, 4) clip delta along each box edge
    corners = base[:, None, :] + _CORNERS @ axes  # (n, 8, 4); a matmul, much faster than the same einsum
    w = corners[..., 3]
    behind = (w <= 1e-6).any(axis=1)
    safe_w = np.where(w > 1e-6, w, 1.0)
    x = np.clip(corners[..., 0] / safe_w, -1.0, 1.0)
    y = np.clip(corners[..., 1] / safe_w, -1.0, 1.0)
    area = (x.max(axis=1) - x.min(axis=1)) * (y.max(axis=1) - y.min(axis=1)) * 0.25 * width * height
    return np.where(behind, float(width * height), area)


def cull_hierarchy(parent: np.ndarray, lo: np.ndarray, hi: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """(N,) bool: a node is visible iff its own box passes the frustum and every ancestor's does.

    A representation hierarchy (Zach's increments, Mason & Blake) is only entered
    through visible parents, so a culled node culls its whole subtree. ``parent``
    is (N,) int with −1 at roots. Pointer jumping: after round r each node has
    folded in its 2^r nearest ancestors, so a tree of depth d takes ⌈log2 d⌉ + 1
    array rounds and no per-node Python loop.
    """
    parent = np.asarray(parent, np.int64)
    ok = cull_boxes(lo, hi, planes)
    jump = parent.copy()
    for _ in range(64):  # 2^64 ancestors: more than any tree holds
        has = jump >= 0
        if not has.any():
            break
        safe = np.where(has, jump, 0)
        ok = ok & np.where(has, ok[safe], True)
        jump = np.where(has, jump[safe], -1)
    return ok


def _centre_ndc(lo: np.ndarray, hi: np.ndarray, clip: np.ndarray, limit: float) -> np.ndarray:
    """(N, 2) normalised device x, y of each box centre, clamped to [−limit, limit].

    A centre behind the eye (w ≤ 0) has no true projection; it is put on the
    border of the clamp square in the direction it lies (straight behind: a
    corner), i.e. as far off-centre as anything can be.
    """
    c = (np.asarray(lo, np.float64) + np.asarray(hi, np.float64)) * 0.5
    m = np.asarray(clip, np.float64)
    h = c @ m[:, :3].T + m[:, 3]  # (N, 4) clip coordinates
    xy, w = h[:, :2], h[:, 3]
    front = w > 1e-9
    ndc = np.clip(xy / np.where(front, w, 1.0)[:, None], -limit, limit)
    reach = np.abs(xy).max(axis=1)
    edge = np.where(reach[:, None] > 1e-12, xy / np.maximum(reach, 1e-300)[:, None] * limit, limit)
    return np.where(front[:, None], ndc, edge)


def _to_pixels(ndc: np.ndarray, width: int, height: int) -> np.ndarray:
    """NDC → window pixels (OpenGL convention: origin bottom-left, y up)."""
    return (ndc + 1.0) * 0.5 * np.array([width, height], np.float64)


def screen_centre(lo: np.ndarray, hi: np.ndarray, clip: np.ndarray, width: int, height: int) -> np.ndarray:
    """(N, 2) float64 pixel position of each box centre's projection, clamped to the viewport.

    Window convention: (0, 0) bottom-left, (width, height) top-right. Centres
    behind the eye land on the viewport's border (see ``_centre_ndc``).
    """
    return _to_pixels(_centre_ndc(lo, hi, clip, 1.0), width, height)


def centre_offset(lo: np.ndarray, hi: np.ndarray, clip: np.ndarray, width: int, height: int) -> np.ndarray:
    """(N,) float64 in [0, 1]: distance of each box centre's projection from the screen centre.

    0 at the middle of the screen, 1 at a corner (distance over the half
    diagonal); the input of F&S's Focus factor.
    """
    px = screen_centre(lo, hi, clip, width, height)
    half = np.array([width, height], np.float64) * 0.5
    return np.clip(np.linalg.norm(px - half, axis=1) / np.linalg.norm(half), 0.0, 1.0)


#: How far outside the screen (in NDC units) apparent motion is still measured.
SPEED_LIMIT_NDC = 4.0


def screen_speed(
    lo: np.ndarray,
    hi: np.ndarray,
    clip_now: np.ndarray,
    clip_before: np.ndarray,
    dt: float,
    width: int,
    height: int,
) -> np.ndarray:
    """(N,) float64 pixels per second each box centre moves on screen between two views.

    The input of F&S's Motion factor: objects sweeping across the screen are
    blurred and seen briefly. Positions are compared unclamped up to
    ``SPEED_LIMIT_NDC`` so an object leaving the screen still counts as moving;
    ``dt`` is the time between the two views in seconds (> 0).
    """
    if not dt > 0:
        raise ValueError(f"dt must be positive, got {dt}")
    now = _to_pixels(_centre_ndc(lo, hi, clip_now, SPEED_LIMIT_NDC), width, height)
    before = _to_pixels(_centre_ndc(lo, hi, clip_before, SPEED_LIMIT_NDC), width, height)
    return np.linalg.norm(now - before, axis=1) / float(dt)
