"""The scale benchmark: a city of ≥ 40k facade-detailed buildings on a street grid, ≥ 20M triangles.

Zach 2002 selects among tens of thousands of buildings at once; this scene
makes that load without data files. Buildings carry detail that LOD removes
first — window frames and sills as small boxes standing out of the wall,
ledges, parapets, chimneys, stepped tower tiers — on a plain body, so coarse
levels keep the massing.

Speed: a few dozen archetypes are built once with numpy (boxes and gable
prisms); each building is an archetype scaled, turned by a multiple of 90°
and moved into its lot, done for all buildings of an archetype in one batched
numpy operation. Every building of an archetype shares that archetype's face
array (read it, never write it in place), so memory is mostly positions.

Layout: blocks of 4 × 4 lots (20 m) between 20 m streets; lots are filled
from the centre outward, so any building count gives a round city. Downtown
(near the centre) favours towers; the outskirts houses.

World axes: z up, metres, ground at z = 0; streets run along x = k·PERIOD and
y = k·PERIOD.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from server.scene.generate.camera import looping_tour, yaw_pitch
from server.scene.source import Mesh, SourceObject, SourceScene

__all__ = ["megacity", "archetypes", "LOT", "STREET", "PERIOD"]

LOT = 20.0  #: lot side, metres
LOTS = 4  #: lots per block side
STREET = 20.0  #: street width
PERIOD = LOTS * LOT + STREET  #: block plus street
FLOOR = 3.2  #: storey height
TILE_BLOCKS = 4  #: ground tile side in blocks

# --------------------------------------------------------------------------- primitives

_BOX_CORNERS = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], np.float64)
_BOX_FACES = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                       [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], np.int64)


def _boxes(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closed axis-aligned boxes, outward faces: positions (8k, 3), faces (12k, 3)."""
    lo, hi = np.atleast_2d(lo), np.atleast_2d(hi)
    pos = lo[:, None, :] + _BOX_CORNERS[None] * (hi - lo)[:, None, :]
    faces = _BOX_FACES[None] + 8 * np.arange(lo.shape[0])[:, None, None]
    return pos.reshape(-1, 3), faces.reshape(-1, 3)


def _gable(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """A closed gable prism over box lo..hi, ridge along x at the top: 6 vertices, 8 faces."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    ym = (y0 + y1) / 2
    pos = np.array([[x0, y0, z0], [x0, y1, z0], [x0, ym, z1], [x1, y0, z0], [x1, y1, z0], [x1, ym, z1]])
    faces = np.array([[0, 2, 1], [3, 4, 5], [0, 3, 5], [0, 5, 2], [1, 2, 5], [1, 5, 4], [0, 1, 4], [0, 4, 3]])
    return pos, faces


def _merge(parts: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    offsets = np.cumsum([0] + [p.shape[0] for p, _ in parts[:-1]])
    return np.concatenate([p for p, _ in parts]), np.concatenate([f + o for (_, f), o in zip(parts, offsets)])


def _windows(x0, x1, y0, y1, z0, floors, spacing) -> tuple[np.ndarray, np.ndarray]:
    """Window frames (1.3 × 1.6 m, standing 0.12 m proud) and sills on all four facades of a storey stack."""
    lo, hi = [], []
    for axis, (a0, a1), (b0, b1) in ((0, (x0, x1), (y0, y1)), (1, (y0, y1), (x0, x1))):
        n = max(1, int((a1 - a0 - 1.0) // spacing))
        along = a0 + (a1 - a0) / 2 + (np.arange(n) - (n - 1) / 2) * spacing
        zs = z0 + FLOOR * np.arange(floors) + 0.9
        u, z = np.meshgrid(along, zs, indexing="ij")
        u, z = u.ravel(), z.ravel()
        for side, sgn in ((b0, -1.0), (b1, 1.0)):
            for du, dz, out, h in ((0.65, 0.0, 0.12, 1.6), (0.8, -0.1, 0.22, 0.1)):  # frame, then sill
                w0 = np.column_stack([u - du, np.full_like(u, side - 0.1 * sgn), z + dz])
                w1 = np.column_stack([u + du, np.full_like(u, side + out * sgn), z + dz + h])
                if axis == 1:  # facade along y: swap the plan axes
                    w0, w1 = w0[:, [1, 0, 2]], w1[:, [1, 0, 2]]
                lo.append(np.minimum(w0, w1))
                hi.append(np.maximum(w0, w1))
    return _boxes(np.concatenate(lo), np.concatenate(hi))


def _tier(w, d, z0, floors, spacing, ledge_every) -> list[tuple[np.ndarray, np.ndarray]]:
    """A storey stack: body, windows and ledges; footprint w × d centred on the origin, from z0."""
    x0, x1, y0, y1 = -w / 2, w / 2, -d / 2, d / 2
    top = z0 + floors * FLOOR
    parts = [_boxes(np.array([x0, y0, z0]), np.array([x1, y1, top])), _windows(x0, x1, y0, y1, z0, floors, spacing)]
    lz = z0 + FLOOR * np.arange(ledge_every, floors, ledge_every)
    if lz.size:
        o = 0.3
        parts.append(_boxes(np.column_stack([np.full_like(lz, x0 - o), np.full_like(lz, y0 - o), lz - 0.15]),
                            np.column_stack([np.full_like(lz, x1 + o), np.full_like(lz, y1 + o), lz + 0.15])))
    return parts


def _parapet(w, d, z) -> tuple[np.ndarray, np.ndarray]:
    t, h = 0.3, 1.0
    x0, x1, y0, y1 = -w / 2, w / 2, -d / 2, d / 2
    lo = np.array([[x0, y0, z], [x0, y1 - t, z], [x0, y0 + t, z], [x1 - t, y0 + t, z]])
    hi = np.array([[x1, y0 + t, z + h], [x1, y1, z + h], [x0 + t, y1 - t, z + h], [x1, y1 - t, z + h]])
    return _boxes(lo, hi)


def _archetype(kind: str, w: float, d: float, floors: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One building model, footprint centred on the origin, base at z = 0."""
    if kind == "house":  # gabled roof, chimney
        parts = _tier(w, d, 0.0, floors, 3.3, 1)
        top = floors * FLOOR
        parts.append(_gable((-w / 2 - 0.4, -d / 2 - 0.4, top), (w / 2 + 0.4, d / 2 + 0.4, top + 0.45 * d)))
        cx = rng.uniform(-w / 3, w / 3)
        parts.append(_boxes(np.array([cx - 0.4, d / 5 - 0.4, top]), np.array([cx + 0.4, d / 5 + 0.4, top + 0.5 * d + 0.8])))
    elif kind == "block":  # flat roof with parapet and roof plant
        parts = _tier(w, d, 0.0, floors, 4.0, 3)
        top = floors * FLOOR
        parts.append(_parapet(w, d, top))
        parts.append(_boxes(np.array([-w / 6, -d / 6, top]), np.array([w / 6, d / 6, top + 2.2])))
    else:  # stepped tower: tiers shrinking upward, an antenna
        parts, z = [], 0.0
        steps = [(1.0, 0.5), (0.75, 0.3), (0.5, 0.2)]
        for scale, share in steps:
            n = max(2, int(round(floors * share)))
            parts += _tier(w * scale, d * scale, z, n, 4.6, 5)
            z += n * FLOOR
            parts.append(_parapet(w * scale, d * scale, z))
        parts.append(_boxes(np.array([-0.3, -0.3, z]), np.array([0.3, 0.3, z + 0.15 * z])))
    return _merge(parts)


def archetypes(seed: int = 0) -> list[dict]:
    """The building models: dicts {"name", "kind", "positions", "faces", "height"}; 36 of them."""
    rng = np.random.default_rng([seed, 0xA4C])
    out = []
    specs = [("house", w, d, f) for w, d in ((10, 8), (12, 9), (14, 10), (9, 9), (13, 12)) for f in (2, 3)]
    specs += [("block", w, d, f) for w, d in ((16, 12), (17, 15), (14, 14), (17, 10)) for f in (4, 6, 9)]
    specs += [("tower", w, d, f) for w, d in ((17, 17), (16, 13), (15, 15), (17, 14)) for f in (14, 22, 34)]
    for kind, w, d, f in specs:
        pos, faces = _archetype(kind, float(w), float(d), f, rng)
        out.append({"name": f"{kind}_{w}x{d}_{f}", "kind": kind, "positions": pos, "faces": faces,
                    "height": float(pos[:, 2].max())})
    return out


# --------------------------------------------------------------------------- layout


def _lots(buildings: int) -> tuple[np.ndarray, int]:
    """Lot centres (buildings, 2), centre outward, and blocks per side."""
    blocks = max(1, math.ceil(math.sqrt(buildings / (LOTS * LOTS * 0.75))))
    b, l = np.arange(blocks), np.arange(LOTS)
    along = (b[:, None] * PERIOD + STREET / 2 + (l[None, :] + 0.5) * LOT).ravel()
    x, y = np.meshgrid(along, along, indexing="ij")
    xy = np.column_stack([x.ravel(), y.ravel()])
    centre = blocks * PERIOD / 2
    r = np.hypot(xy[:, 0] - centre, xy[:, 1] - centre)
    order = np.lexsort((xy[:, 1], xy[:, 0], np.round(r, 6)))
    return xy[order[:buildings]], blocks


def _ground(blocks: int) -> list[SourceObject]:
    """Flat ground tiles (TILE_BLOCKS blocks square, 16 × 16 quads each), cls "ground"."""
    extent = blocks * PERIOD
    tiles = max(1, math.ceil(blocks / TILE_BLOCKS))
    size, res = extent / tiles, 16
    k = np.arange(res + 1)
    i, j = np.meshgrid(k, k, indexing="ij")
    a = (i[:-1, :-1] * (res + 1) + j[:-1, :-1]).ravel()
    faces = np.concatenate([np.column_stack([a, a + res + 1, a + res + 2]), np.column_stack([a, a + res + 2, a + 1])])
    out = []
    for ti in range(tiles):
        for tj in range(tiles):
            pos = np.column_stack([(ti * res + i.ravel()) * size / res, (tj * res + j.ravel()) * size / res,
                                   np.zeros(i.size)])
            out.append(SourceObject(f"ground_{ti:02d}_{tj:02d}", "ground", [Mesh(pos, faces)]))
    return out


def _tour(blocks: int) -> tuple[list[dict], dict[str, float]]:
    """Drive east along a central street, turn north, climb to a high overview, glide back down."""
    m = blocks // 2
    c = m * PERIOD  # a street line through the centre
    span = min(3, max(1, m)) * PERIOD
    extent = blocks * PERIOD
    high = max(150.0, 0.35 * extent)
    drive = span / 14.0  # seconds per leg at 14 m/s
    ctl = [  # t, eye, look-at target
        (0.0, (c - span, c, 2.0), (c - span + 40, c, 1.5)),
        (drive, (c - 8, c, 2.0), (c + 32, c, 1.5)),
        (drive + 2.0, (c + 2, c + 10, 2.0), (c + 2, c + 50, 1.5)),  # left turn at the centre crossing
        (2 * drive + 2.0, (c + 2, c + span, 2.5), (c + 2, c + span + 40, 2.0)),
        (2 * drive + 16.0, (c + 0.4 * span, c + span + 0.4 * high, 0.5 * high), (c, c, 0.0)),
        (2 * drive + 28.0, (c - 0.3 * high, c + 0.9 * high, high), (c, c, 0.0)),  # overview
        (2 * drive + 40.0, (c - 0.9 * high, c + 0.2 * high, 0.8 * high), (c, c, 0.0)),
        (2 * drive + 54.0, (c - span - 30, c, 30.0), (c - span + 40, c, 1.5)),
    ]
    step = 0.1
    t = [round(round(k[0] / step) * step, 9) for k in ctl]
    t.append(t[-1] + 8.0)
    eyes = np.array([k[1] for k in ctl] + [ctl[0][1]])
    look = np.array([k[2] for k in ctl] + [ctl[0][2]]) - eyes
    yaw, pitch = yaw_pitch(look)
    yaw = np.unwrap(yaw)
    yaw[-1] = yaw[0] + 2 * math.pi * round((yaw[-1] - yaw[0]) / (2 * math.pi))
    return looping_tour(t, eyes, yaw, pitch, step=step), {"street": t[1], "overview": t[5]}


def megacity(buildings: int = 40000, seed: int = 0,
             progress: Callable[[int, int], None] | None = None) -> tuple[SourceScene, list[dict], dict[str, float]]:
    """A city of ``buildings`` buildings plus ground tiles, a looping tour and named tour times.

    buildings : how many (≥ 1); 40 000 gives about 25M triangles, 300 suits tests
    seed      : archetype details, choice, turn and scale of every building
    progress  : called as progress(done, buildings) as archetype batches are placed
    Returns (scene, tour, {"street": t, "overview": t}); objects are cls
    "building" (named building_NNNNN, attributes archetype/height) then cls "ground".
    """
    if buildings < 1:
        raise ValueError(f"buildings must be ≥ 1, got {buildings}")
    rng = np.random.default_rng([seed, 0xC17])
    arch = archetypes(seed)
    kinds = np.array([a["kind"] for a in arch])
    xy, blocks = _lots(buildings)
    centre = blocks * PERIOD / 2
    r = np.hypot(xy[:, 0] - centre, xy[:, 1] - centre) / max(centre, 1.0)
    # Downtown towers, a ring of blocks, houses beyond.
    p_tower = 0.5 * np.exp(-(r / 0.15) ** 2)
    p_block = (1 - p_tower) * (0.04 + 0.6 * np.exp(-(r / 0.3) ** 2))
    u = rng.uniform(size=buildings)
    kind = np.where(u < p_tower, "tower", np.where(u < p_tower + p_block, "block", "house"))
    choice = np.empty(buildings, np.int64)
    for k in ("house", "block", "tower"):
        ids = np.flatnonzero(kinds == k)
        sel = kind == k
        choice[sel] = rng.choice(ids, size=int(sel.sum()))
    quarter = rng.integers(0, 4, buildings)
    scale_xy = rng.uniform(0.9, 1.0, buildings)
    scale_z = rng.uniform(0.9, 1.15, buildings)
    meshes: list[Mesh | None] = [None] * buildings
    done = 0
    for a_id, a in enumerate(arch):
        ids = np.flatnonzero(choice == a_id)
        if ids.size == 0:
            continue
        p = a["positions"]
        ang = quarter[ids] * (math.pi / 2)
        c, s = np.round(np.cos(ang)), np.round(np.sin(ang))
        sx = scale_xy[ids]
        pos = np.empty((ids.size, p.shape[0], 3))
        pos[..., 0] = sx[:, None] * (c[:, None] * p[:, 0] - s[:, None] * p[:, 1]) + xy[ids, 0, None]
        pos[..., 1] = sx[:, None] * (s[:, None] * p[:, 0] + c[:, None] * p[:, 1]) + xy[ids, 1, None]
        pos[..., 2] = scale_z[ids, None] * p[:, 2]
        for k, i in enumerate(ids):
            meshes[i] = Mesh(pos[k], a["faces"])
        done += ids.size
        if progress is not None:
            progress(done, buildings)
    objects = [SourceObject(f"building_{i:05d}", "building", [meshes[i]],
                            {"archetype": arch[choice[i]]["name"], "height": arch[choice[i]]["height"] * scale_z[i]})
               for i in range(buildings)]
    objects += _ground(blocks)
    tour, viewpoints = _tour(blocks)
    return SourceScene(objects=objects, sources=[f"generate:megacity(buildings={buildings}, seed={seed})"]), tour, viewpoints
