"""How much a coarse level still looks like its object: area ratio, silhouette IoU and FLIP.

Three measures of a level against the object's finest level, made at build
time for every coarse level and HLOD proxy:

- **area ratio** — the level's exposed surface area over the finest level's
  (``surface.exposed_area``: the surface outside every other shell, so a
  window frame sunk into a wall counts its face, not its buried back). Quadric
  decimation of a closed, box-like building collapses its walls first; what is
  left are roof slabs with a fraction of the area. Meaningful for closed meshes.
- **silhouette IoU** — intersection over union of the two rendered coverage
  masks, from the six axis directions (orthographic, in the finest level's box,
  ``MASK`` × ``MASK`` pixels). Under orthographic projection the masks from
  +a and −a are mirror images, so three renders give all six; the reported
  value is the least of them (the worst direction). An object fills its masks
  and they are binary; an HLOD proxy stands for many objects, each a few of its
  pixels, where a binary mask's half-pixel rounding would dominate the measure,
  so its masks hold each pixel's covered fraction (``samples`` × ``samples``
  points a pixel, as an antialiased render shows it) and the IoU is their
  weighted form, Σ min / Σ max (which is the plain IoU for binary masks).
- **FLIP** (Andersson et al. 2020, ``flip_evaluator``) of a shaded render of the
  level against one of the finest level, at the level's *switching distance*:
  where its geometric error projects to ``PIXEL_ERROR`` pixels on a
  ``SCREEN_HEIGHT``-pixel screen with a ``FOV``-degree vertical field of view.
  There the object covers about ``diagonal / error · PIXEL_ERROR`` pixels, so
  the render is that big (clamped to ``FLIP_MIN``..``FLIP_MAX``).

**Why a raster here and not the client's renderer.** The import contracts keep
``moderngl`` (and the client) out of the server, and the build runs in worker
processes with no GL context. The measures need coverage and flat-shaded
depth-tested images of small meshes, which a z-buffer rasteriser in a numba
kernel gives exactly, in one pass over the triangles, with the client's
conventions (z up, counter-clockwise outward faces, Lambert shading under one
directional light).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numba
import numpy as np

from .surface import exposed_area, is_closed, surface_area

__all__ = ["Bounds", "Fidelity", "Reference", "reference", "measure", "surface_area", "is_closed",
           "silhouettes", "silhouette_iou", "area_ratio", "shaded", "MASK"]

MASK = 64  #: silhouette mask side, pixels
PIXEL_ERROR = 1.0  #: projected geometric error at the switching distance, pixels
SCREEN_HEIGHT = 1080  #: pixels
FOV = 60.0  #: vertical field of view, degrees
FLIP_MIN, FLIP_MAX = 8, 32  #: side of the FLIP renders, pixels (FLIP costs per pixel: small renders keep builds fast)
_VIEW = np.array([0.62, -0.55, 0.56])  #: toward the camera for the FLIP render (from above, three-quarter)
_LIGHT = np.array([0.3, -0.5, 0.81])
_BACKGROUND = np.array([0.62, 0.72, 0.85])


@dataclass(frozen=True)
class Bounds:
    """What a kept level must reach: silhouette IoU ≥ ``iou``, area ratio ≥ ``area`` (closed meshes,
    either way: min(r, 1/r)), FLIP ≤ ``flip`` at the switching distance."""

    iou: float = 0.9
    area: float = 0.8
    flip: float = 0.25

    def passes(self, f: "Fidelity", closed: bool) -> bool:
        if not f.iou >= self.iou:
            return False
        if closed and not min(f.area_ratio, 1.0 / max(f.area_ratio, 1e-12)) >= self.area:
            return False
        return not f.flip > self.flip  # NaN (no render: full detail) passes


@dataclass(frozen=True)
class Fidelity:
    """One level's measures against its finest level; ``method`` names how it was made."""

    area_ratio: float
    iou: float
    flip: float
    method: str = "source"

    def as_tuple(self) -> tuple[str, float, float, float]:
        return self.method, float(self.area_ratio), float(self.iou), float(self.flip)


@dataclass
class Reference:
    """The finest level's side of every comparison, computed once per object."""

    positions: np.ndarray
    faces: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    area: float  # exposed surface area
    closed: bool
    masks: np.ndarray  # (3, MASK, MASK) covered fraction of each pixel (0 or 1 when samples == 1)
    samples: int = 1  # coverage points per pixel side
    renders: dict = field(default_factory=dict)  # FLIP render side → the finest level's shaded render

    def shaded(self, size: int) -> np.ndarray:
        """The finest level's FLIP render at ``size`` pixels, made once per size."""
        if size not in self.renders:
            self.renders[size] = shaded(self.positions, self.faces, self.lo, self.hi, size)
        return self.renders[size]


# --------------------------------------------------------------------------- kernels


@numba.njit(cache=True, nogil=True)
def _raster(tri: np.ndarray, shade: np.ndarray, h: int, w: int, image: np.ndarray, depth: np.ndarray) -> None:
    """Z-buffered triangles (t, 3, 3: pixel x, pixel y, depth — larger is nearer) into image (h, w)."""
    for t in range(tri.shape[0]):
        x0, y0, z0 = tri[t, 0, 0], tri[t, 0, 1], tri[t, 0, 2]
        x1, y1, z1 = tri[t, 1, 0], tri[t, 1, 1], tri[t, 1, 2]
        x2, y2, z2 = tri[t, 2, 0], tri[t, 2, 1], tri[t, 2, 2]
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if area == 0.0:
            continue
        i0 = max(int(math.floor(min(x0, x1, x2))), 0)
        i1 = min(int(math.ceil(max(x0, x1, x2))), w - 1)
        j0 = max(int(math.floor(min(y0, y1, y2))), 0)
        j1 = min(int(math.ceil(max(y0, y1, y2))), h - 1)
        inv = 1.0 / area
        for j in range(j0, j1 + 1):
            py = j + 0.5
            for i in range(i0, i1 + 1):
                px = i + 0.5
                a = ((x1 - px) * (y2 - py) - (x2 - px) * (y1 - py)) * inv
                b = ((x2 - px) * (y0 - py) - (x0 - px) * (y2 - py)) * inv
                c = 1.0 - a - b
                if a < 0.0 or b < 0.0 or c < 0.0:
                    continue
                z = a * z0 + b * z1 + c * z2
                if z > depth[j, i]:
                    depth[j, i] = z
                    image[j, i] = shade[t]


@numba.njit(cache=True, nogil=True)
def _cover(uv: np.ndarray, faces: np.ndarray, res: int, out: np.ndarray) -> None:
    """Coverage of the triangles (vertices ``uv`` in pixel units, n × 3) along x, y and z into out (3, res, res).

    The same inside test as ``_raster``: a pixel is covered when its centre lies in a triangle of
    non-zero area (closed edges). Coverage needs no depth, so one pass per axis over the faces.
    """
    for axis in range(3):
        ka = 1 if axis == 0 else 0
        kb = 1 if axis == 2 else 2
        for t in range(faces.shape[0]):
            v0, v1, v2 = faces[t, 0], faces[t, 1], faces[t, 2]
            x0, y0 = uv[v0, ka], uv[v0, kb]
            x1, y1 = uv[v1, ka], uv[v1, kb]
            x2, y2 = uv[v2, ka], uv[v2, kb]
            area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
            if area == 0.0:
                continue
            i0 = max(int(math.floor(min(x0, x1, x2))), 0)
            i1 = min(int(math.ceil(max(x0, x1, x2))), res - 1)
            j0 = max(int(math.floor(min(y0, y1, y2))), 0)
            j1 = min(int(math.ceil(max(y0, y1, y2))), res - 1)
            inv = 1.0 / area
            for j in range(j0, j1 + 1):
                py = j + 0.5
                for i in range(i0, i1 + 1):
                    if out[axis, j, i]:
                        continue
                    px = i + 0.5
                    a = ((x1 - px) * (y2 - py) - (x2 - px) * (y1 - py)) * inv
                    b = ((x2 - px) * (y0 - py) - (x0 - px) * (y2 - py)) * inv
                    c = 1.0 - a - b
                    if a < 0.0 or b < 0.0 or c < 0.0:
                        continue
                    out[axis, j, i] = True


def _draw(tri: np.ndarray, shade: np.ndarray, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    image = np.full((h, w), -1.0)
    depth = np.full((h, w), -np.inf)
    _raster(np.ascontiguousarray(tri, np.float64), np.ascontiguousarray(shade, np.float64), h, w, image, depth)
    return image, depth


# --------------------------------------------------------------------------- measures


def silhouettes(positions: np.ndarray, faces: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                res: int = MASK, samples: int = 1) -> np.ndarray:
    """Coverage masks along x, y and z, each filling the box lo..hi's face.

    samples == 1: (3, res, res) bool; else (3, res, res) float32, each pixel's covered share
    of its samples × samples points.
    """
    side = res * samples
    ext = np.maximum(np.asarray(hi) - np.asarray(lo), 1e-9)
    uv = np.ascontiguousarray((np.asarray(positions, np.float64) - lo) / ext * side)
    out = np.zeros((3, side, side), bool)
    _cover(uv, np.ascontiguousarray(faces, np.int64), side, out)
    if samples == 1:
        return out
    return out.reshape(3, res, samples, res, samples).mean(axis=(2, 4), dtype=np.float32)


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    """Least IoU over the three mask pairs: Σ min / Σ max (for bool masks, |a ∩ b| / |a ∪ b|)."""
    if a.dtype == bool and b.dtype == bool:
        union = np.logical_or(a, b).sum(axis=(1, 2))
        inter = np.logical_and(a, b).sum(axis=(1, 2))
    else:
        union = np.maximum(a, b).sum(axis=(1, 2), dtype=np.float64)
        inter = np.minimum(a, b).sum(axis=(1, 2), dtype=np.float64)
    return float(np.min(np.where(union > 0, inter / np.maximum(union, 1e-12), 1.0)))


def _view_basis() -> np.ndarray:
    d = _VIEW / np.linalg.norm(_VIEW)
    right = np.cross([0.0, 0.0, 1.0], d)
    right /= np.linalg.norm(right)
    up = np.cross(d, right)
    return np.stack([right, up, d])


@numba.njit(cache=True, nogil=True)
def _shade(p: np.ndarray, f: np.ndarray, basis: np.ndarray, centre: np.ndarray, radius: float, size: int,
           light: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-space triangles (m, 3, 3) seen along basis[2] and their Lambert shades (m,)."""
    m = f.shape[0]
    tri = np.empty((m, 3, 3))
    shade = np.empty(m)
    for t in range(m):
        for c in range(3):
            v = p[f[t, c]] - centre
            tri[t, c, 0] = (v @ basis[0] / radius + 1.0) * size / 2
            tri[t, c, 1] = (1.0 - v @ basis[1] / radius) * size / 2
            tri[t, c, 2] = v @ basis[2]
        a, b, d = p[f[t, 0]], p[f[t, 1]], p[f[t, 2]]
        ux, uy, uz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
        vx, vy, vz = d[0] - a[0], d[1] - a[1], d[2] - a[2]
        nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
        norm = max(math.sqrt(nx * nx + ny * ny + nz * nz), 1e-30)
        shade[t] = 0.15 + 0.75 * abs((nx * light[0] + ny * light[1] + nz * light[2]) / norm)
    return tri, shade


def shaded(positions: np.ndarray, faces: np.ndarray, lo: np.ndarray, hi: np.ndarray, size: int) -> np.ndarray:
    """(size, size, 3) float32 render in [0, 1]: Lambert-shaded grey over a sky colour, from ``_VIEW``."""
    p = np.ascontiguousarray(positions, np.float64)
    f = np.ascontiguousarray(faces, np.int64)
    centre = (np.asarray(lo, np.float64) + np.asarray(hi, np.float64)) / 2
    radius = max(float(np.linalg.norm(np.asarray(hi) - np.asarray(lo))) / 2, 1e-9)
    tri, shade = _shade(p, f, _view_basis(), centre, radius, int(size), _LIGHT / np.linalg.norm(_LIGHT))
    image, _ = _draw(tri, shade, size, size)
    rgb = np.where(image[..., None] >= 0, image[..., None] * np.array([0.93, 0.9, 0.85]), _BACKGROUND)
    return np.clip(rgb, 0.0, 1.0).astype(np.float32)


def switching_size(lo: np.ndarray, hi: np.ndarray, error: float) -> int:
    """Pixels the object spans where ``error`` projects to ``PIXEL_ERROR`` pixels (clamped)."""
    diag = float(np.linalg.norm(np.asarray(hi) - np.asarray(lo)))
    if not error > 0:
        return FLIP_MAX
    return int(np.clip(round(diag / error * PIXEL_ERROR), FLIP_MIN, FLIP_MAX))


def switching_distance(error: float) -> float:
    """Distance (object units) at which ``error`` projects to ``PIXEL_ERROR`` pixels."""
    focal = SCREEN_HEIGHT / (2 * math.tan(math.radians(FOV) / 2))
    return float(error) * focal / PIXEL_ERROR


_FLIP_POOL: list = []


def _flip_threads():
    """flip_evaluator's own OpenMP pool, limited to one thread per call.

    Builds run one worker per core; FLIP's threads on top of them oversubscribe
    the machine, and its tiny images then wait on their threads for most of a call.
    Only flip_evaluator's vendored OpenMP library is limited, nothing else in the process.
    """
    if not _FLIP_POOL:
        import flip_evaluator  # noqa: F401  (loads its OpenMP library)
        from threadpoolctl import ThreadpoolController

        libs = ThreadpoolController().select(user_api="openmp")
        mine = [lib for lib in libs.lib_controllers if "flip_evaluator" in lib.filepath]
        _FLIP_POOL.append(libs if not mine else ThreadpoolController().select(filepath=mine[0].filepath))
    return _FLIP_POOL[0].limit(limits=1)


def flip_error(ref: Reference, positions: np.ndarray, faces: np.ndarray, error: float) -> float:
    """Mean FLIP of the level against the finest level, rendered at the level's switching distance."""
    import flip_evaluator

    if not error > 0:
        return float("nan")
    size = switching_size(ref.lo, ref.hi, error)
    a = ref.shaded(size)
    b = shaded(positions, faces, ref.lo, ref.hi, size)
    with _flip_threads():
        _, mean, _ = flip_evaluator.evaluate(a, b, "LDR", applyMagma=False)
    return float(mean)


def reference(positions: np.ndarray, faces: np.ndarray, *, samples: int = 1) -> Reference:
    """The finest level's side of the measures; samples: coverage points per mask pixel side
    (1: binary masks, for one object)."""
    p = np.asarray(positions, np.float64)
    f = np.asarray(faces, np.int64)
    lo, hi = p.min(axis=0), p.max(axis=0)
    pad = 0.02 * np.maximum(hi - lo, 1e-6)
    lo, hi = lo - pad, hi + pad
    return Reference(p, f, lo, hi, exposed_area(p, f), is_closed(f), silhouettes(p, f, lo, hi, samples=samples),
                     samples)


def silhouette_iou(ref: Reference, positions: np.ndarray, faces: np.ndarray) -> float:
    """Least silhouette IoU over the six axis directions of the level against ``ref``."""
    return _iou(ref.masks, silhouettes(positions, faces, ref.lo, ref.hi, samples=ref.samples))


def area_ratio(ref: Reference, positions: np.ndarray, faces: np.ndarray) -> float:
    """The level's exposed surface area over the finest level's."""
    return exposed_area(positions, faces) / max(ref.area, 1e-30)


def measure(ref: Reference, positions: np.ndarray, faces: np.ndarray, error: float,
            method: str = "source", with_flip: bool = True) -> Fidelity:
    """The level's area ratio, least silhouette IoU over the six directions and FLIP vs ``ref``."""
    iou = silhouette_iou(ref, positions, faces)
    flip = flip_error(ref, positions, faces, error) if with_flip else float("nan")
    return Fidelity(area_ratio(ref, positions, faces), iou, flip, method)
