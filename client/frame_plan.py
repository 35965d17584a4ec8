"""What one frame draws, decided without GL: arrays in, a ``FramePlan`` out.

The renderer's ``draw`` is this plan followed by the GL submit. The plan
checks the caller's arrays, looks the reps up in the slot table
(``client.slots``), leaves out what is not resident or lies outside the view
frustum, groups the draws by rendering algorithm (one multi-draw each, the
caller's order kept within a group), builds one DrawElementsIndirectCommand
and one per-draw row (``DRAW``) per draw, and counts the work the cost model
is fitted to. Being pure, it is what the tests check the culling, grouping and
counts on, without a GL context.

Culling is by bounding sphere against the Gribb–Hartmann planes of the
view-projection: the server's selection includes a margin around the view for
where the camera is going, and on a software rasterizer every submitted vertex
is processed on the CPU, seen or not.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from proto.messages import ALGORITHMS

from .slots import SlotTable

__all__ = ["DRAW", "FLAG_MORPH", "FramePlan", "in_frustum", "plan_frame"]

#: Per-draw row (instanced attribute, divisor 1): weight, continuous level, tint (RGBA8 packed little-endian), flags,
#: and the representation's texture: its size class (``client.textures``; −1: none) and layer in that class's array.
DRAW = np.dtype([("weight", "<f4"), ("level", "<f4"), ("tint", "<u4"), ("flags", "<u4"), ("tex_class", "<i4"),
                 ("tex_layer", "<f4")])
#: ``DRAW["flags"]`` bit: the draw blends toward its morph target.
FLAG_MORPH = 1


@dataclass(frozen=True)
class FramePlan:
    """The draws of one frame, grouped by rendering algorithm, and what they amount to.

    slots    : (n,) int32 — the slots drawn, algorithm 0's first, the caller's order within each group
    rows     : (n,) ``DRAW`` — row i belongs to draw i (its command's baseInstance is i)
    commands : (n, 5) uint32 — count, 1, firstIndex, baseVertex, baseInstance
    draws, triangles, vertices : (R,) int64 per rendering algorithm (index into ``ALGORITHMS``); a
               morphing draw counts the finer level's triangles and vertices
    morphs   : draws blended toward their morph target (weight < 1 and a target set)
    unmorphed : draws asked to morph (weight < 1) whose rep has no target: drawn as they are
    missing  : reps asked for that are not resident (skipped)
    culled   : resident reps outside the view frustum (skipped, counted in nothing else)
    seen     : (s,) bool over the reps asked for: resident and inside the view frustum, hence drawn
    """

    slots: np.ndarray
    rows: np.ndarray
    commands: np.ndarray
    draws: np.ndarray
    triangles: np.ndarray
    vertices: np.ndarray
    morphs: int = 0
    unmorphed: int = 0
    missing: int = 0
    culled: int = 0
    seen: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.slots.size)


def _aligned(values: object, s: int, dtype: type, what: str) -> np.ndarray | None:
    if values is None:
        return None
    a = np.asarray(values)
    if a.shape != (s,):
        raise ValueError(f"{what} must be aligned with reps ({s},), got {a.shape}")
    if dtype is np.int64 and s and a.dtype.kind not in "iu":
        if a.dtype.kind != "f" or not np.array_equal(a, np.round(a)):
            raise ValueError(f"{what} must be integers")
    return a.astype(dtype, copy=False)


def _frustum_planes(view_projection: np.ndarray) -> np.ndarray:
    """(6, 4) float64 unit-normal planes (left, right, bottom, top, near, far) of a view-projection."""
    vp = view_projection
    planes = np.stack([vp[3] + vp[0], vp[3] - vp[0], vp[3] + vp[1], vp[3] - vp[1], vp[3] + vp[2], vp[3] - vp[2]])
    planes /= np.linalg.norm(planes[:, :3], axis=1, keepdims=True)
    return planes


def in_frustum(table: SlotTable, slots: np.ndarray, view_projection: np.ndarray, eye: np.ndarray) -> np.ndarray:
    """(n,) bool: whether each resident slot's bounding sphere reaches into the view frustum.

    One (6, 4) @ (4, n) product gives each centre's signed distance to each plane plus its radius. Planes as
    rows, so the test reduces over contiguous rows: a reduction along the short axis of an (n, 6) array is
    several times slower, and this is most of preparing a frame of many reps.
    """
    planes = _frustum_planes(view_projection)
    m = np.hstack([planes[:, :3], np.ones((6, 1))]).astype(np.float32)
    d = m @ table.sphere[slots].T
    d += (planes[:, 3] - planes[:, :3] @ eye)[:, None]
    return np.logical_and.reduce(d >= 0.0, axis=0)


def plan_frame(
    reps: np.ndarray,
    table: SlotTable,
    view_projection: np.ndarray,
    eye: np.ndarray,
    *,
    weights: np.ndarray | None = None,
    algorithms: np.ndarray | None = None,
    levels: np.ndarray | None = None,
    cull: bool = True,
) -> FramePlan:
    """Plan drawing ``reps`` (s,) int from ``eye`` (3,) float64.

    table : the resident representations (read, never changed)
    view_projection : (4, 4) float64, projection @ view rotation — camera-relative
        (``proto.camera``; applied to [world − eye, 1])
    weights : (s,) float, the morph weight of each rep (None: all 1); ≥ 1 draws the
        rep as it is, < 1 blends it toward its morph target (below 0 counts as 0)
        if it has one, else draws it as it is and counts it in ``unmorphed``
    algorithms : (s,) int in 0..R−1, index into ``ALGORITHMS`` (None: all flat)
    levels : (s,) float, the continuous level shown by false colour (None: 0)
    cull : leave out reps whose bounding sphere lies outside the view frustum
    Raises ValueError on misaligned or non-finite arguments or algorithms out of range.
    """
    reps = np.asarray(reps).ravel()
    reps = reps.astype(np.int64, copy=False) if reps.dtype.kind in "iu" else reps.astype(np.int64)
    s = reps.size
    w = _aligned(weights, s, np.float64, "weights")
    alg = _aligned(algorithms, s, np.int64, "algorithms")
    lev = _aligned(levels, s, np.float32, "levels")
    if w is not None and not np.isfinite(w).all():
        raise ValueError("morph weights must be finite")
    if alg is not None and s and (alg.min() < 0 or alg.max() >= len(ALGORITHMS)):
        raise ValueError(f"algorithms must lie in 0..{len(ALGORITHMS) - 1}")
    if lev is not None and not np.isfinite(lev).all():
        raise ValueError("levels must be finite")

    slots = table.lookup(reps)
    here = slots >= 0
    seen_mask = here.copy()
    n = int(np.count_nonzero(here))
    missing = s - n
    if n < s:
        slots = slots[here]
        w = None if w is None else w[here]
        alg = None if alg is None else alg[here]
        lev = None if lev is None else lev[here]
    culled = 0
    if cull and n:
        seen = in_frustum(table, slots, view_projection, eye)
        culled = n - int(np.count_nonzero(seen))
        if culled:
            seen_mask[np.flatnonzero(here)[~seen]] = False
            slots = slots[seen]
            w = None if w is None else w[seen]
            alg = None if alg is None else alg[seen]
            lev = None if lev is None else lev[seen]
            n -= culled
    r = len(ALGORITHMS)
    if alg is not None and n:  # group by algorithm, keeping the caller's order within each
        masks = [alg == k for k in range(r)]
        order = np.concatenate([np.flatnonzero(m) for m in masks])  # R passes beat a sort
        slots, alg = slots[order], alg[order]
        w = None if w is None else w[order]
        lev = None if lev is None else lev[order]
        per_alg = np.array([np.count_nonzero(m) for m in masks])
    else:
        per_alg = np.array([n] + [0] * (r - 1))

    rows = np.empty(n, DRAW)
    morphs = unmorphed = 0
    if w is None:
        rows["weight"] = 1.0
        rows["flags"] = 0
    else:
        static = w >= 1.0
        has_target = table.target[slots]
        morphing = ~static & has_target
        morphs = int(np.count_nonzero(morphing))
        unmorphed = int(np.count_nonzero(~static & ~has_target))
        rows["weight"] = np.where(morphing, np.maximum(w, 0.0), 1.0)
        rows["flags"] = morphing * np.uint32(FLAG_MORPH)
    rows["level"] = 0.0 if lev is None else lev
    rows["tint"] = table.tint[slots]
    rows["tex_class"] = table.tex_class[slots]
    rows["tex_layer"] = table.tex_layer[slots]
    commands = table.command[slots]
    commands[:, 4] = np.arange(n, dtype=np.uint32)

    faces, vertices = table.faces[slots], table.vertices[slots]
    if alg is None or not n:
        tri_alg = np.zeros(r, np.int64)
        vert_alg = np.zeros(r, np.int64)
        tri_alg[0], vert_alg[0] = faces.sum(), vertices.sum()
    else:
        tri_alg = np.bincount(alg, weights=faces, minlength=r).astype(np.int64)
        vert_alg = np.bincount(alg, weights=vertices, minlength=r).astype(np.int64)
    return FramePlan(slots, rows, commands, per_alg, tri_alg, vert_alg, morphs=morphs, unmorphed=unmorphed,
                     missing=missing, culled=culled, seen=seen_mask)
