"""The demo scene: a sculpture garden too detailed to draw in full, a tour through it, and its store.

Objects stand in 4 × 4 blocks separated by avenues, so a camera flying along
an avenue sees long rows of objects on both sides and far ahead: hundreds of
objects and millions of full-detail triangles in view at once, several times
what a software rasteriser draws in a 50 ms frame. Every object is a closed
base shape (sphere, superellipsoid, surface of revolution, torus) displaced
by fractal noise — sums of sinusoids along random directions, seeded per
object — so its detail is real surface relief that simplification removes
gradually, and full-detail face counts vary from about 4.5k to 16k.

World axes: z is up, the ground is near z = 0, units are metres.

Meshes are made on demand (``DemoObject.mesh()``) rather than held: the full
scene is ~5M triangles, and ``build_demo`` works one object at a time, in
worker processes, from the small picklable recipe: each worker makes the mesh,
its LOD chain with geomorph maps, the error of each level and the payloads,
and only the payloads travel back; the parent writes them in object order
through one ``SceneWriter`` transaction. The result does not depend on the
number of workers, and the same ``(objects, seed)`` gives the same meshes and
tour wherever numpy's floating-point functions round alike.

The demo does not go through the ``SourceScene`` builder (``server.scene.builder``):
that one holds every mesh in the parent before it starts, names classes in the
order it meets them and records an origin and source metadata; the demo's
store keeps its fixed ``CLASS_NAMES`` and the meta it has always had. Both
share the worker pool (``server.scene.workers``) and the level encoding
(``server.scene.writer.encode_levels``).

Example::

    >>> scene = generate_demo(objects=12, seed=0)
    >>> positions, faces = scene.objects[0].mesh()   # (n, 3) float64, (m, 3) int64

Build the store from the command line::

    python -m server.scene.demo demo.db --objects 576 --seed 0
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from .lod import build_chain
from .store import SceneStore
from .workers import POOL_MIN_JOBS, default_workers, pool_map
from .writer import SceneWriter, encode_levels

__all__ = ["CLASS_NAMES", "DemoObject", "DemoScene", "generate_demo", "build_demo", "build_object"]

#: Object classes of the demo, in the order their ids take in the store.
CLASS_NAMES = ["ground", "rock", "column", "statue", "ring"]

CELL = 3.5  #: spacing of object sites inside a block, metres
BLOCK = 4  #: sites per block side
AVENUE = 7.0  #: width of the avenues between blocks, metres
PERIOD = BLOCK * CELL + AVENUE  #: block plus avenue, metres
GROUND_TILE = 36.0  #: approximate side of one ground tile, metres
SPEED = 6.0  #: tour speed in m/s (a brisk flight; slower when the loop is short)
CENTRE_PULL = 1.5  #: how far the tour's view leans from the path toward the scene centre (1.5 ≈ 56°)

# (class, weight, full-detail face range) — log-uniform inside the range.
_KINDS = [("rock", 0.35, (4500, 12000)), ("column", 0.25, (4500, 9000)), ("statue", 0.25, (7000, 16000)),
          ("ring", 0.15, (5000, 12000))]


@dataclass(frozen=True)
class DemoObject:
    """One object of the demo: its name and class, and the recipe its mesh is made from.

    ``params`` holds only plain numbers, so an object pickles in a few hundred
    bytes and a worker process can make its mesh.
    """

    name: str
    cls: str
    params: dict = field(repr=False)

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """Full-detail mesh: positions (n, 3) float64 in world space, faces (m, 3) int64, outward."""
        p = self.params
        rng = np.random.default_rng(p["seed"])
        if self.cls == "ground":
            return _ground(p, rng)
        local, faces = _SHAPES[self.cls](p, rng)
        # Rotation about z written out: a BLAS matmul would start BLAS's thread
        # pool in every build worker and oversubscribe the cores (slower builds),
        # and may round differently from one BLAS build to another.
        c, s = math.cos(p["yaw"]), math.sin(p["yaw"])
        world = np.empty_like(local)
        world[:, 0] = c * local[:, 0] - s * local[:, 1] + p["x"]
        world[:, 1] = s * local[:, 0] + c * local[:, 1] + p["y"]
        world[:, 2] = local[:, 2] + p["z"]
        return world, faces


@dataclass(frozen=True)
class DemoScene:
    """A generated scene: objects (ground tiles first), a closed tour and its start pose.

    tour  : list of {"t", "eye", "forward", "up"} dicts, t ascending, the last
            key repeating the first pose (``proto.messages.TourKey`` fields)
    start : {"eye", "forward", "up"} — the tour's first pose
    """

    name: str
    objects: list[DemoObject]
    tour: list[dict]
    start: dict
    class_names: list[str]
    seed: int


# --------------------------------------------------------------------------- noise


def _fbm(p: np.ndarray, rng: np.random.Generator, base: float, octaves: int, dirs: int = 7,
         gain: float = 0.5, ridged: bool = False) -> np.ndarray:
    """Fractal noise (n,) at points p (n, 3): ``octaves`` doublings of frequency from ``base``
    (radians per metre), each the sum of ``dirs`` sinusoids along random directions.

    Amplitude of octave o is gain**o; the sum is scaled to roughly [-1, 1].
    ``ridged`` folds each octave (1 − 2|sin|) for sharp creases, as on rock.
    """
    d = rng.normal(size=(octaves * dirs, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    freq = base * np.repeat(2.0 ** np.arange(octaves), dirs) * rng.uniform(0.8, 1.25, octaves * dirs)
    phase = rng.uniform(0.0, 2.0 * np.pi, octaves * dirs)
    amp = np.repeat(gain ** np.arange(octaves), dirs) / math.sqrt(dirs)
    # Elementwise rather than BLAS products: BLAS may round a row differently
    # depending on where it sits in the array, and ground tiles must agree
    # bit for bit on the vertices they share.
    k = d * freq[:, None]
    wave = np.sin(p[:, :1] * k[:, 0] + p[:, 1:2] * k[:, 1] + p[:, 2:3] * k[:, 2] + phase)  # (n, octaves·dirs)
    if ridged:
        wave = 1.0 - 2.0 * np.abs(wave)
    return (wave * amp).sum(axis=1) / (amp.sum() / math.sqrt(dirs) * 1.5)


def _octaves(base: float, spacing: float) -> int:
    """Octaves whose finest wavelength stays above ~3 vertex spacings, so the mesh resolves them."""
    finest = 2.0 * math.pi / (3.0 * spacing)
    return max(1, int(math.floor(math.log2(max(finest / base, 1.0)))) + 1)


# --------------------------------------------------------------------------- base meshes


def _cube_sphere(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit sphere from a cube with n × n quads per side: positions (6n²+2, 3), faces (12n², 3).

    Vertices are welded on the integer cube lattice, so seams are exact; the
    cube → sphere map is the area-balancing one, so triangles are even in size.
    """
    t = np.arange(n + 1)
    u, v = np.meshgrid(t, t, indexing="ij")
    quads = []
    lattice = []
    for axis in range(3):
        for side in (0, n):
            pts = np.zeros((n + 1, n + 1, 3), np.int64)
            a1, a2 = (axis + 1) % 3, (axis + 2) % 3
            pts[..., axis], pts[..., a1], pts[..., a2] = side, u, v
            base = len(lattice) * (n + 1) ** 2
            lattice.append(pts.reshape(-1, 3))
            idx = base + (u * (n + 1) + v)
            q = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)
            quads.append(q if side == n else q[:, ::-1])
    lat = np.concatenate(lattice)
    key = (lat[:, 0] * (n + 1) + lat[:, 1]) * (n + 1) + lat[:, 2]
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    quads = inverse[np.concatenate(quads)]
    faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    c = lat[first].astype(np.float64) * (2.0 / n) - 1.0  # cube [-1, 1]³
    x2, y2, z2 = c[:, 0] ** 2, c[:, 1] ** 2, c[:, 2] ** 2
    s = np.stack([c[:, 0] * np.sqrt(1 - y2 / 2 - z2 / 2 + y2 * z2 / 3),
                  c[:, 1] * np.sqrt(1 - z2 / 2 - x2 / 2 + z2 * x2 / 3),
                  c[:, 2] * np.sqrt(1 - x2 / 2 - y2 / 2 + x2 * y2 / 3)], -1)
    return s, _outward(s, faces, np.zeros(3))


def _outward(pos: np.ndarray, faces: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Flip faces (m, 3) whose normal points toward ``centre`` (valid for star-shaped bases)."""
    tri = pos[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    flip = np.einsum("ij,ij->i", n, tri.mean(1) - centre) < 0
    faces = faces.copy()
    faces[flip] = faces[flip][:, ::-1]
    return faces


def _grid(nu: int, nv: int, wrap_u: bool, wrap_v: bool) -> np.ndarray:
    """Faces (2·nu'·nv', 3) of a (nu × nv) vertex grid, vertex id = i·nv + j, optionally periodic."""
    iu = np.arange(nu if wrap_u else nu - 1)
    iv = np.arange(nv if wrap_v else nv - 1)
    i, j = np.meshgrid(iu, iv, indexing="ij")
    i1, j1 = (i + 1) % nu, (j + 1) % nv
    a, b, c, d = i * nv + j, i1 * nv + j, i1 * nv + j1, i * nv + j1
    return np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])


def _revolution(radius: np.ndarray, z: np.ndarray, n_theta: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closed surface of revolution about the z axis: profile radius (k,), z (k,) from bottom to top.

    Returns positions (k·n_theta + 2, 3), faces, and theta (k·n_theta,) of the ring vertices;
    the two poles (bottom, top centre) are the last two vertices, joined by fans.
    """
    k = radius.size
    theta = np.arange(n_theta) * (2.0 * np.pi / n_theta)
    th = np.tile(theta, k)
    r = np.repeat(radius, n_theta)
    ring = np.stack([r * np.cos(th), r * np.sin(th), np.repeat(z, n_theta)], -1)
    pos = np.concatenate([ring, [[0.0, 0.0, z[0]], [0.0, 0.0, z[-1]]]])
    side = _grid(k, n_theta, wrap_u=False, wrap_v=True)[:, ::-1]  # outward: up the profile, then round
    j = np.arange(n_theta)
    bottom = np.stack([np.full(n_theta, k * n_theta), (j + 1) % n_theta, j], -1)
    top = np.stack([np.full(n_theta, k * n_theta + 1), (k - 1) * n_theta + j, (k - 1) * n_theta + (j + 1) % n_theta], -1)
    return pos, np.concatenate([side, bottom, top]), th


# --------------------------------------------------------------------------- shapes (object space, z up, base at z≈0)


def _rock(p: dict, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Ridged-noise boulder: an ellipsoid whose radius carries five or six octaves of crags."""
    n = max(8, round(math.sqrt(p["faces"] / 12)))
    s, faces = _cube_sphere(n)
    radii = np.array([p["size"], p["size"] * rng.uniform(0.6, 0.95), p["size"] * rng.uniform(0.45, 0.8)]) / 2
    spacing = 2.0 * p["size"] / (2 * n)
    base = 2.0 * math.pi / p["size"]
    bump = 0.22 * _fbm(s * radii, rng, base, _octaves(base, spacing), ridged=True)
    pos = s * radii * (1.0 + bump)[:, None]
    pos[:, 2] += radii[2] * 0.75
    return pos, faces


def _statue(p: dict, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Twisted superellipsoid on its end: boxy or pinched, with bulges and weathered noise."""
    n = max(8, round(math.sqrt(p["faces"] / 12)))
    s, faces = _cube_sphere(n)
    e = rng.uniform(0.35, 1.6)  # < 1 boxy, > 1 pinched
    r = (np.abs(s) ** (2.0 / e)).sum(axis=1) ** (-e / 2.0)
    w, h = p["size"] / 2, p["height"] / 2
    pos = s * r[:, None] * np.array([w, w * rng.uniform(0.6, 1.0), h])
    zt = pos[:, 2] / h
    bulge = 1.0 + 0.18 * np.sin(rng.uniform(2.0, 5.0) * np.pi * zt + rng.uniform(0, 2 * np.pi))
    twist = rng.uniform(-1.2, 1.2) * zt
    c, sn = np.cos(twist), np.sin(twist)
    x, y = pos[:, 0] * bulge, pos[:, 1] * bulge
    pos[:, 0], pos[:, 1] = c * x - sn * y, sn * x + c * y
    spacing = 2.0 * p["height"] / (2 * n)
    base = 2.0 * math.pi / p["size"]
    pos += s * (0.05 * p["size"] * _fbm(pos, rng, base, _octaves(base, spacing)))[:, None]
    pos[:, 2] += h
    return pos, faces


def _column(p: dict, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Fluted column with base, entasis and capital, its stone pitted by fine noise."""
    flutes = int(rng.choice([12, 16, 20]))
    n_theta = flutes * 6
    k = max(8, round(p["faces"] / (2 * n_theta)))
    h, r0 = p["height"], p["size"] / 2
    t = np.linspace(0.0, 1.0, k)
    z = t * h
    radius = r0 * (1.0 - 0.12 * t)  # entasis
    radius = np.where(t < 0.06, r0 * 1.35, radius)  # base
    radius = np.where(t > 0.92, r0 * (1.2 + 2.5 * (t - 0.92)), radius)  # capital
    pos, faces, theta = _revolution(radius, z, n_theta)
    ring = pos[:-2]
    shaft = (ring[:, 2] > 0.07 * h) & (ring[:, 2] < 0.91 * h)
    radial = ring[:, :2] / np.maximum(np.linalg.norm(ring[:, :2], axis=1, keepdims=True), 1e-12)
    flute = np.where(shaft, -0.06 * r0 * np.cos(flutes * theta) ** 2, 0.0)
    base = 2.0 * math.pi / r0
    spacing = max(2 * math.pi * r0 / n_theta, h / k)
    pit = 0.03 * r0 * _fbm(ring, rng, base, _octaves(base, spacing), ridged=True)
    ring[:, :2] += radial * (flute + pit)[:, None]
    return pos, faces


def _ring(p: dict, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Upright torus sculpture with a tube of varying thickness and knotted noise."""
    big, tube = p["size"] / 2, p["size"] * rng.uniform(0.08, 0.14)
    nv = max(12, round(math.sqrt(p["faces"] / 2 * tube / big)))
    nu = max(24, round(p["faces"] / (2 * nv)))
    u = np.repeat(np.arange(nu) * (2 * np.pi / nu), nv)
    v = np.tile(np.arange(nv) * (2 * np.pi / nv), nu)
    centre = np.stack([big * np.cos(u), np.zeros_like(u), big * np.sin(u)], -1)
    normal = np.stack([np.cos(v) * np.cos(u), np.sin(v), np.cos(v) * np.sin(u)], -1)
    base = 2.0 * math.pi / p["size"]
    thick = tube * (1.0 + 0.35 * np.sin(rng.integers(2, 5) * u + rng.uniform(0, 2 * np.pi)))
    spacing = 2 * math.pi * tube / nv
    thick = thick * (1.0 + 0.25 * _fbm(centre + normal * tube, rng, base * 2, _octaves(base * 2, spacing)))
    pos = centre + normal * thick[:, None]
    pos[:, 2] += big + tube * 0.5
    return pos, _grid(nu, nv, wrap_u=True, wrap_v=True)[:, ::-1]


def _ground(p: dict, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Heightfield tile: gentle undulation plus paving-scale relief, world space, z up.

    The height is a function of world (x, y) with one noise for the whole
    ground (``p['ground_seed']``), so adjacent tiles meet exactly at full detail.
    """
    res, spacing = p["res"], p["size"] / p["res"]
    k = np.arange(res + 1)
    # World coordinates from global grid indices, so shared edges agree exactly.
    gx, gy = np.meshgrid((p["i"] * res + k) * spacing, (p["j"] * res + k) * spacing, indexing="ij")
    xy = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], -1)
    noise = np.random.default_rng(p["ground_seed"])
    z = 0.35 * _fbm(xy, noise, 2 * math.pi / 60.0, 3) + 0.04 * _fbm(xy, noise, 2 * math.pi / 2.0, 3, ridged=True)
    pos = np.concatenate([xy[:, :2], (z - 0.1)[:, None]], 1)
    return pos, _grid(res + 1, res + 1, wrap_u=False, wrap_v=False)


_SHAPES = {"rock": _rock, "statue": _statue, "column": _column, "ring": _ring}


def _sizes(cls: str, rng: np.random.Generator) -> dict:
    """Overall size (width) and height of an object of class ``cls``, metres."""
    if cls == "rock":
        return {"size": rng.uniform(1.3, 2.7), "height": 0.0}
    if cls == "column":
        return {"size": rng.uniform(0.6, 0.9), "height": rng.uniform(3.0, 5.5)}
    if cls == "statue":
        return {"size": rng.uniform(0.9, 1.6), "height": rng.uniform(1.8, 3.2)}
    return {"size": rng.uniform(2.0, 2.8), "height": 0.0}


# --------------------------------------------------------------------------- layout and tour


def _avenue(i: int) -> float:
    """Centre line of avenue i (along x or y), metres."""
    return i * PERIOD + AVENUE / 2


def _tour(blocks: int, rng: np.random.Generator) -> list[dict]:
    """A closed flight along the avenues with rounded turns, keys every 0.5 s.

    The loop circles the garden along the avenues one block in from its
    edge (around the only block in small scenes), with four rounded turns; eye height swings between ~1.8 and ~2.8 m; the
    view looks a few metres ahead along the path, leans toward the centre of
    the garden and slightly down.
    """
    lo, hi = (1, blocks - 1) if blocks >= 3 else (0, blocks)
    corners = [(lo, lo), (hi, lo), (hi, hi), (lo, hi)]
    pts = np.array([[_avenue(i), _avenue(j)] for i, j in corners])
    centre = np.full(2, (blocks * PERIOD + AVENUE) / 2)
    # Dense closed polyline, then a circular moving average rounds the corners.
    step = 0.25
    seg = np.roll(pts, -1, axis=0) - pts
    counts = np.maximum(1, np.round(np.linalg.norm(seg, axis=1) / step).astype(int))
    dense = np.concatenate([pts[i] + np.outer(np.arange(c) / c, seg[i]) for i, c in enumerate(counts)])
    w = int(round(5.0 / step))
    kernel = np.ones(2 * w + 1) / (2 * w + 1)
    padded = np.concatenate([dense[-w:], dense, dense[:w]])
    smooth = np.stack([np.convolve(padded[:, a], kernel, mode="valid") for a in range(2)], -1)
    closed = np.concatenate([smooth, smooth[:1]])
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))])
    length = float(s[-1])
    duration = float(np.clip(length / SPEED, 40.0, 60.0))
    keys_t = np.arange(0.0, duration, 0.5)
    phase0 = rng.uniform(0.0, 2 * np.pi)

    def at(dist: np.ndarray) -> np.ndarray:
        d = np.mod(dist, length)
        return np.stack([np.interp(d, s, closed[:, 0]), np.interp(d, s, closed[:, 1])], -1)

    dist = keys_t / duration * length
    xy = at(dist)
    ahead = at(dist + 6.0) - xy
    ahead /= np.linalg.norm(ahead, axis=1, keepdims=True)
    # Lean the view sideways toward the garden's centre: flying along an
    # avenue, the camera then sees the depth of the garden rather than the
    # row ahead. Only the part across the path is used, so the view never
    # turns back against the motion.
    to_centre = centre - xy
    to_centre /= np.maximum(np.linalg.norm(to_centre, axis=1, keepdims=True), 1e-9)
    across = to_centre - np.sum(to_centre * ahead, axis=1, keepdims=True) * ahead
    ahead = ahead + CENTRE_PULL * across
    ahead /= np.linalg.norm(ahead, axis=1, keepdims=True)
    height = 2.3 + 0.5 * np.sin(2 * np.pi * 2 * dist / length + phase0)
    keys = []
    for t, (x, y), (fx, fy), z in zip(keys_t, xy, ahead, height):
        keys.append({"t": float(t), "eye": [float(x), float(y), float(z)],
                     "forward": [float(fx), float(fy), -0.12], "up": [0.0, 0.0, 1.0]})
    keys.append({**keys[0], "t": duration})
    return keys


def generate_demo(objects: int = 576, seed: int = 0) -> DemoScene:
    """The demo scene: ``objects`` sculptures in 4 × 4 blocks plus ground tiles, and a tour.

    objects : number of sculptures (ground tiles come in addition: one per ~36 m square)
    seed    : everything random derives from it; object i's mesh from (seed, i) alone
    """
    if objects < 1:
        raise ValueError(f"objects must be ≥ 1, got {objects}")
    if seed < 0:
        raise ValueError(f"seed must be ≥ 0, got {seed}")
    rng = np.random.default_rng([seed, 0x5EED])
    blocks = max(1, math.ceil(math.sqrt(objects / BLOCK**2)))
    side = blocks * BLOCK
    extent = blocks * PERIOD + AVENUE
    tiles = max(1, math.ceil(extent / GROUND_TILE))
    ground_seed = int(rng.integers(1 << 62))
    out = [DemoObject(f"ground_{i}_{j}", "ground", {"seed": 0, "ground_seed": ground_seed, "res": 64,
                                                   "i": i, "j": j, "size": extent / tiles})
           for i in range(tiles) for j in range(tiles)]
    kinds = [k[0] for k in _KINDS]
    weights = np.array([k[1] for k in _KINDS])
    for n in range(objects):
        gi, gj = divmod(n, side)
        orng = np.random.default_rng([seed, 1, n])
        kind = int(orng.choice(len(kinds), p=weights / weights.sum()))
        lo_f, hi_f = _KINDS[kind][2]
        cls = kinds[kind]
        params = {
            "seed": [seed, 2, n],
            "faces": int(round(math.exp(orng.uniform(math.log(lo_f), math.log(hi_f))))),
            "x": AVENUE + (gi // BLOCK) * PERIOD + (gi % BLOCK + 0.5) * CELL + orng.uniform(-0.3, 0.3),
            "y": AVENUE + (gj // BLOCK) * PERIOD + (gj % BLOCK + 0.5) * CELL + orng.uniform(-0.3, 0.3),
            "z": -0.15,
            "yaw": orng.uniform(0.0, 2 * np.pi),
            **_sizes(cls, orng),
        }
        out.append(DemoObject(f"{cls}_{n:04d}", cls, params))
    tour = _tour(blocks, rng)
    start = {k: tour[0][k] for k in ("eye", "forward", "up")}
    return DemoScene(name="demo", objects=out, tour=tour, start=start, class_names=list(CLASS_NAMES), seed=seed)


# --------------------------------------------------------------------------- the demo's store


def build_object(
    obj: DemoObject,
) -> tuple[DemoObject, np.ndarray, np.ndarray, list[float], list[bytes], list[bytes | None]]:
    """One object's store rows: (object, box lo (3,), box hi (3,), errors per level,
    geometry payloads per level, morph payloads per level).

    Levels are coarsest → finest; every level is quantized in one box
    (``writer.object_box``) and stored in the chain's GPU order (``reorder=False``), so
    the morph maps (``proto.morph``, from the simplifier's edge collapses) index
    the stored vertices: entry k maps level k's vertices onto level k − 1's; entry 0 is None.
    """
    positions, faces = obj.mesh()
    chain = build_chain(positions, faces, morph="collapse")
    lo, hi, blobs, morphs = encode_levels(chain.levels, chain.morph, reorder=False)
    return obj, lo, hi, chain.errors, blobs, morphs


def build_demo(
    path: str | os.PathLike[str],
    *,
    objects: int = 576,
    seed: int = 0,
    progress: Callable[[int, int], None] | None = None,
    workers: int | None = None,
) -> dict:
    """Generate the demo scene and write it to a new store at ``path`` (atomically).

    objects  : sculptures (ground tiles are added: 16 for the default size)
    progress : called as progress(done, total) after each object is written
    workers  : processes; default one per CPU (at most 8), and none for small scenes

    Returns a summary: path, objects, representations, triangles (full detail),
    triangles_per_level (list, level 0 = coarsest, over objects having that
    level), bytes (file size), geometry_bytes, seconds.
    """
    started = time.perf_counter()
    scene = generate_demo(objects=objects, seed=seed)
    total = len(scene.objects)
    if workers is None:
        workers = 1 if objects < POOL_MIN_JOBS else default_workers()
    reps = geometry_bytes = 0
    with SceneWriter(path, name=scene.name, generator="walkstream demo", seed=seed,
                     class_names=scene.class_names) as writer:
        for done, (obj, lo, hi, errors, blobs, morphs) in enumerate(pool_map(build_object, scene.objects, workers, chunksize=4), 1):
            writer.add_encoded(obj.name, obj.cls, lo, hi, errors, blobs, morphs=morphs)
            reps += len(blobs)
            geometry_bytes += sum(len(b) for b in blobs)
            if progress is not None:
                progress(done, total)
        writer.set_tour(scene.tour)
        writer.set_start(scene.start)
    with SceneStore.open(path) as store:
        idx = store.index
        full = idx.rep_first + idx.rep_count - 1
        triangles = int(idx.rep_faces[full].sum())
        per_level = np.bincount(idx.rep_level, weights=idx.rep_faces).astype(np.int64).tolist()
    return {
        "path": str(path),
        "objects": total,
        "representations": reps,
        "triangles": triangles,
        "triangles_per_level": per_level,
        "bytes": Path(path).stat().st_size,
        "geometry_bytes": geometry_bytes,
        "seconds": round(time.perf_counter() - started, 2),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Build the walkstream demo scene store.")
    parser.add_argument("path", type=Path)
    parser.add_argument("--objects", type=int, default=576)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=None)
    args = parser.parse_args(argv)

    def report(done: int, total: int) -> None:
        if done == total or done % 50 == 0:
            print(f"\r{done}/{total} objects", end="\n" if done == total else "", file=sys.stderr, flush=True)

    summary = build_demo(args.path, objects=args.objects, seed=args.seed, progress=report, workers=args.workers)
    for key, value in summary.items():
        print(f"{key}: {value}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
