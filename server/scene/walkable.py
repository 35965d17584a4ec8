"""The walkable grid of a scene: where a person can stand, and how high the ground is there.

Theory of operation. The grid is a regular plan grid over the scene's bounds
(``cell_size``: the finest of ``MIN_CELL`` and the size that keeps it within
``MAX_CELLS``). Every triangle of the scene is sampled at the cell centres its
plan projection covers (a fragment: cell, height, object); walls and thin parts,
whose plan projection covers no centre, are added as the cells their outline
crosses with the triangle's height range. A cell's ground is the lowest
*candidate* — a sample of a terrain or ground surface, or of any face flatter
than ``MAX_SLOPE_DEG`` (a floor, a seating tier, a stage) — that has headroom:

- no geometry between ``STEP`` and ``CLEARANCE`` above it (a chair, a wall, a
  low ceiling): a kerb or a riser lower than ``STEP`` is climbed;
- not inside a solid, at the feet or in the headroom: counted from above, the
  column crosses each object's surface an even number of times above that
  height (an odd count means it lies inside a building, a wall box or a kerb,
  whatever the winding).

A scene without terrain or ground surfaces gets a virtual ground at the lowest
geometry of the nearest covered cell (the footprints' ground height), where no
geometry covers a cell. Then a cell is not walkable where the ground rises more
than ``STEP`` + cell·tan(``MAX_SLOPE_DEG``) to a neighbour (the higher cell is
dropped: a stage edge, a cliff) or more than ``RAMP``·tan(``MAX_SLOPE_DEG``) over
``RAMP`` metres (a steep ramp made of small cells), and regions smaller than
``MIN_REGION_SHARE`` of the largest (the tops of walls and roofs) are dropped.

Each object is read at its coarsest level within half a cell of full detail,
terrain at its quadtree's leaves; tree instances block the cell of their trunk.
Everything is arrays: no loop runs per object, triangle or cell.

The builder stores the grid (``SceneWriter.commit``); ``SceneStore.walkable``
reads it, and computes it with ``walkable_grid`` for a store built before.
"""

from __future__ import annotations

import math
from typing import Iterator, Protocol

import numpy as np
from scipy import ndimage

from proto.geometry import decode_geometry
from proto.points import decode_instances
from proto.walkable import WalkableGrid

from .index import MESH, TERRAIN, TREES

__all__ = ["walkable_grid", "cell_size", "MAX_CELLS", "MIN_CELL", "STEP", "CLEARANCE", "MAX_SLOPE_DEG", "RAMP",
           "GROUND_CLASSES"]

#: The grid has at most this many cells (about a million).
MAX_CELLS = 1 << 20
#: Cells are never finer than this (m): a person's stride is a few of them.
MIN_CELL = 0.1
#: Height a walker steps up without noticing (m): a kerb, a stair riser, a seating tier.
STEP = 0.3
#: Headroom a standing person needs above the ground (m).
CLEARANCE = 2.0
#: Ground steeper than this is not walkable, and faces steeper than this are not floors.
MAX_SLOPE_DEG = 35.0
#: Baseline (m) over which a ramp's slope is measured when cells are much finer.
RAMP = 2.0
#: Regions with fewer cells than this share of the largest region are dropped.
MIN_REGION_SHARE = 0.01
#: Object classes whose surfaces are the ground (as the builder's ``_is_ground``).
GROUND_CLASSES = ("terrain", "ground", "tin", "tinrelief")

_FLAT = math.cos(math.radians(MAX_SLOPE_DEG))
#: Faces whose normal is further than 60° from vertical are walls: their outline is rasterised too.
_STEEP = 0.5
#: Sample points sit this far (in cells) off the centre: a generic offset, so that no sample falls on the
#: axis-aligned and diagonal edges that boxes put at round coordinates.
_JITTER = np.array([0.0012345, 0.0006789])
#: Where the feet are (m above a candidate): ground covered by a solid there (a kerb, a tier, a floor slab) is
#: not stood on; the solid's top is.
_FOOT = 0.05
#: Fragments made per rasterisation pass (bounds the working memory).
_CHUNK = 1 << 22
#: Triangles decoded per batch of representations.
_BATCH_FACES = 1 << 21


class _Store(Protocol):
    @property
    def index(self): ...

    def geometries(self, reps) -> list[bytes]: ...


def cell_size(bounds: np.ndarray, max_cells: int = MAX_CELLS, min_cell: float = MIN_CELL) -> float:
    """The cell edge (m) for a scene's (2, 2+) [min, max] bounds: the finer of ``min_cell`` and the size that
    keeps ⌈w/cell⌉ · ⌈h/cell⌉ ≤ ``max_cells``."""
    ext = np.maximum(np.asarray(bounds, np.float64)[1, :2] - np.asarray(bounds, np.float64)[0, :2], min_cell)
    cell = max(min_cell, math.sqrt(float(ext[0] * ext[1]) / max_cells))
    while math.ceil(ext[0] / cell) * math.ceil(ext[1] / cell) > max_cells:
        cell *= 1.01
    return cell


class _Raster:
    """The grid's geometry: origin (2,), cell, nx, ny; sample points at jittered cell centres."""

    def __init__(self, origin: np.ndarray, cell: float, nx: int, ny: int) -> None:
        self.origin, self.cell, self.nx, self.ny = np.asarray(origin, np.float64), float(cell), int(nx), int(ny)

    def centres(self, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Samples of triangles ``tri`` (n, 3, 3) at the cell centres their plan projections cover:
        (flat cell index (k,) int64, height (k,) float64, triangle (k,) int64).

        A centre on an edge two triangles share belongs to exactly one of them: each edge function is
        evaluated with the edge's endpoints in one canonical order, so both triangles compute the same
        number, and the triangle on its positive side takes the tie.
        """
        xy = tri[:, :, :2]
        g0 = np.ceil((xy.min(axis=1) - self.origin) / self.cell - 0.5 - _JITTER).astype(np.int64)
        g1 = np.floor((xy.max(axis=1) - self.origin) / self.cell - 0.5 - _JITTER).astype(np.int64)
        g0 = np.maximum(g0, 0)
        g1 = np.minimum(g1, [self.nx - 1, self.ny - 1])
        w, h = g1[:, 0] - g0[:, 0] + 1, g1[:, 1] - g0[:, 1] + 1
        n = np.where((w > 0) & (h > 0), w * h, 0)
        out = ([], [], [])
        for first, last in _chunks(n, _CHUNK):
            count = n[first:last]
            t = np.repeat(np.arange(first, last), count)
            k = np.arange(t.size) - np.repeat(np.cumsum(count) - count, count)
            col, row = g0[t, 0] + k % w[t], g0[t, 1] + k // w[t]
            p = self.origin + (np.column_stack([col, row]) + 0.5 + _JITTER) * self.cell
            lam = np.empty((t.size, 3))
            inside = np.ones(t.size, bool)
            for e in range(3):  # edge e is opposite vertex e
                a, b, c = xy[t, (e + 1) % 3], xy[t, (e + 2) % 3], xy[t, e]
                swap = (a[:, 0] > b[:, 0]) | ((a[:, 0] == b[:, 0]) & (a[:, 1] > b[:, 1]))
                u = np.where(swap[:, None], b, a)
                v = np.where(swap[:, None], a, b)
                d = v - u
                ep = d[:, 0] * (p[:, 1] - u[:, 1]) - d[:, 1] * (p[:, 0] - u[:, 0])
                ec = d[:, 0] * (c[:, 1] - u[:, 1]) - d[:, 1] * (c[:, 0] - u[:, 0])
                s = np.sign(ec)
                inside &= (s * ep > 0) | ((ep == 0) & (s > 0))
                lam[:, e] = ep / np.where(ec != 0, ec, 1.0)
            z = (lam * tri[t, :, 2]).sum(axis=1)
            out[0].append((row * self.nx + col)[inside])
            out[1].append(z[inside])
            out[2].append(t[inside])
        return tuple(np.concatenate(a) if a else np.zeros(0, dt)  # type: ignore[return-value]
                     for a, dt in zip(out, (np.int64, np.float64, np.int64)))

    def outlines(self, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The cells the plan outlines of triangles ``tri`` (n, 3, 3) cross: (flat cell (k,), triangle (k,)),
        each pair once; edges are sampled every half cell."""
        a = tri[:, :, :2]
        b = np.roll(a, -1, axis=1)
        length = np.linalg.norm(b - a, axis=2).reshape(-1)  # (3n,)
        m = np.ceil(length / (0.5 * self.cell)).astype(np.int64) + 1
        edge = np.repeat(np.arange(length.size), m)
        s = (np.arange(edge.size) - np.repeat(np.cumsum(m) - m, m)) / np.repeat(np.maximum(m - 1, 1), m)
        pa, pb = a.reshape(-1, 2)[edge], b.reshape(-1, 2)[edge]
        ij = np.floor((pa + s[:, None] * (pb - pa) - self.origin) / self.cell).astype(np.int64)
        ok = (ij[:, 0] >= 0) & (ij[:, 0] < self.nx) & (ij[:, 1] >= 0) & (ij[:, 1] < self.ny)
        flat = ij[ok, 1] * self.nx + ij[ok, 0]
        t = edge[ok] // 3
        n = self.nx * self.ny
        pairs = np.unique(t * n + flat)
        return pairs % n, pairs // n


def _chunks(n: np.ndarray, limit: int) -> Iterator[tuple[int, int]]:
    """[first, last) ranges of ``n`` whose sums stay within ``limit`` (a single larger entry stands alone)."""
    ends = np.cumsum(n)
    first = 0
    while first < n.size:
        base = ends[first - 1] if first else 0
        last = max(first + 1, int(np.searchsorted(ends, base + limit, side="right")))
        yield first, last
        first = last


def _reps(index, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """The representation read of each mesh object (its coarsest within cell/2 of full detail) and each
    terrain leaf: (reps (m,), ground (m,) bool: the surface is ground)."""
    mesh = np.flatnonzero(index.object_kind == MESH)
    first, count = index.rep_first[mesh].astype(np.int64), index.rep_count[mesh].astype(np.int64)
    levels = np.arange(max(int(count.max()) if mesh.size else 0, 1))
    ok = (levels[None, :] < count[:, None]) & (
        index.rep_error[np.minimum(first[:, None] + levels[None, :], max(index.n_representations - 1, 0))] <= cell / 2)
    level = np.where(ok.any(axis=1), np.argmax(ok, axis=1), count - 1) if mesh.size else count
    names = np.array([c.lower() for c in index.class_names], object)
    ground = np.isin(names[index.object_class[mesh]], GROUND_CLASSES)
    terrain = np.flatnonzero(index.object_kind == TERRAIN)
    has_child = np.zeros(index.n_objects, bool)
    parent = index.object_parent[terrain]
    has_child[parent[parent >= 0]] = True
    leaves = terrain[~has_child[terrain]]
    reps = np.concatenate([first + level, index.rep_first[leaves]]).astype(np.int64)
    return reps, np.concatenate([ground, np.ones(leaves.size, bool)])


def _batches(index, reps: np.ndarray) -> Iterator[np.ndarray]:
    """Index ranges into ``reps`` of about ``_BATCH_FACES`` triangles each."""
    for first, last in _chunks(index.rep_faces[reps].astype(np.int64), _BATCH_FACES):
        yield np.arange(first, last)


class _Fragments:
    """What the rasterisation collects, as lists of arrays joined at the end."""

    def __init__(self) -> None:
        self.solid: list[tuple] = []  # (cell, object, z): surface crossings of non-ground objects
        self.walls: list[tuple] = []  # (cell, lo, hi): height ranges of walls and trunks over the cells they cross
        self.candidates: list[tuple] = []  # (cell, z): faces flat enough to stand on
        self.ground: list[tuple] = []  # (cell, z): terrain and ground surfaces (their top is a candidate)

    @staticmethod
    def join(parts: list[tuple], n: int) -> list[np.ndarray]:
        if not parts:
            return [np.zeros(0, np.float64) for _ in range(n)]
        return [np.concatenate([p[i] for p in parts]) for i in range(n)]


def _rasterise(store: _Store, raster: _Raster, reps: np.ndarray, ground: np.ndarray, frags: _Fragments) -> None:
    index = store.index
    for batch in _batches(index, reps):
        blobs = store.geometries(reps[batch].tolist())
        geoms = [decode_geometry(b) for b in blobs]
        tri = np.concatenate([g.positions.astype(np.float64)[g.indices.astype(np.int64)] for g in geoms])
        nf = np.array([g.faces for g in geoms], np.int64)
        obj = np.repeat(index.rep_object[reps[batch]], nf)
        is_ground = np.repeat(ground[batch], nf)
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        nz = np.abs(normal[:, 2]) / np.maximum(np.linalg.norm(normal, axis=1), 1e-300)
        cell, z, t = raster.centres(tri)
        solid = ~is_ground[t]
        flat = solid & (nz[t] >= _FLAT)
        frags.candidates.append((cell[flat], z[flat]))
        frags.ground.append((cell[~solid], z[~solid]))
        frags.solid.append((cell[solid], obj[t[solid]], z[solid]))
        steep = np.flatnonzero((nz < _STEEP) & ~is_ground)
        if steep.size:
            cell, t = raster.outlines(tri[steep])
            zs = tri[steep][:, :, 2]
            frags.walls.append((cell, zs.min(axis=1)[t], zs.max(axis=1)[t]))


def _trees(store: _Store, raster: _Raster, frags: _Fragments) -> None:
    """Tree instances block the cell of their trunk, from their base to the top of their model."""
    index = store.index
    groups = np.flatnonzero(index.object_kind == TREES)
    if not groups.size:
        return
    blobs = store.geometries(index.rep_first[groups].tolist())
    inst = [decode_instances(b) for b in blobs]
    model = np.concatenate([i.model for i in inst]).astype(np.int64)
    matrix = np.concatenate([i.matrix for i in inst]).astype(np.float64)
    base = matrix[:, :3, 3]
    top = base[:, 2] + index.model_hi[model, 2] * np.linalg.norm(matrix[:, :3, 2], axis=1)
    ij = np.floor((base[:, :2] - raster.origin) / raster.cell).astype(np.int64)
    ok = (ij[:, 0] >= 0) & (ij[:, 0] < raster.nx) & (ij[:, 1] >= 0) & (ij[:, 1] < raster.ny)
    frags.walls.append((ij[ok, 1] * raster.nx + ij[ok, 0], base[ok, 2], top[ok]))


def _virtual_ground(raster: _Raster, solid_cell: np.ndarray, solid_z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Candidates for cells no geometry covers, at the lowest geometry of the nearest covered cell."""
    n = raster.nx * raster.ny
    low = np.full(n, np.inf)
    np.minimum.at(low, solid_cell.astype(np.int64), solid_z)
    covered = np.isfinite(low).reshape(raster.ny, raster.nx)
    if not covered.any() or covered.all():
        return np.zeros(0, np.int64), np.zeros(0)
    _, (ri, ci) = ndimage.distance_transform_edt(~covered, return_indices=True)
    filled = low.reshape(raster.ny, raster.nx)[ri, ci]
    empty = np.flatnonzero(~covered.reshape(-1))
    return empty, filled.reshape(-1)[empty]


def _keys(cell: np.ndarray, z: np.ndarray, zref: float, span: float) -> np.ndarray:
    """Heights in their cells as one sortable float64 key: cell · span + (z − zref), z − zref in [0, span)."""
    return cell.astype(np.float64) * span + np.clip(z - zref, 0.0, span * (1 - 1e-9))


def _headroom(cell: np.ndarray, z: np.ndarray, frags: _Fragments, zref: float, span: float) -> np.ndarray:
    """(k,) bool: candidates (cell, z) with nothing between STEP and CLEARANCE above them, and not in a solid."""
    s_cell, s_obj, s_z = _Fragments.join(frags.solid, 3)
    w_cell, w_lo, w_hi = _Fragments.join(frags.walls, 3)
    # Obstacles: every crossing (a point) and every wall range, as intervals [lo, hi] per cell. One overlaps
    # the band (z + STEP, z + CLEARANCE] iff lo ≤ top and hi > bottom; counting those with lo ≤ top less those
    # with hi ≤ bottom counts exactly them (hi ≤ bottom implies lo ≤ top).
    ob_cell = np.concatenate([s_cell, w_cell]).astype(np.int64)
    lo = np.sort(_keys(ob_cell, np.concatenate([s_z, w_lo]), zref, span))
    hi = np.sort(_keys(ob_cell, np.concatenate([s_z, w_hi]), zref, span))
    top = np.searchsorted(lo, _keys(cell, z + CLEARANCE, zref, span), side="right")
    bottom = np.searchsorted(hi, _keys(cell, z + STEP, zref, span), side="right")
    free = top - bottom <= 0
    # Inside a solid: per (cell, object), crossings ranked from the top; between ranks 2i+1 and 2i the column
    # is inside, and below an odd count's lowest crossing too (an object without a bottom face).
    order = np.lexsort((-s_z, s_obj, s_cell))
    c, o, zz = s_cell[order].astype(np.int64), s_obj[order], s_z[order]
    start = np.ones(c.size, bool)
    start[1:] = (c[1:] != c[:-1]) | (o[1:] != o[:-1])
    first = np.maximum.accumulate(np.where(start, np.arange(c.size), 0))
    rank = np.arange(c.size) - first
    last = np.ones(c.size, bool)
    last[:-1] = start[1:]
    odd = np.flatnonzero(rank % 2 == 1)
    bare = np.flatnonzero(last & (rank % 2 == 0))
    in_lo = np.sort(np.concatenate([_keys(c[odd], zz[odd], zref, span), _keys(c[bare], np.full(bare.size, zref), zref, span)]))
    in_hi = np.sort(np.concatenate([_keys(c[odd], zz[odd - 1], zref, span), _keys(c[bare], zz[bare], zref, span)]))
    inside = np.zeros(cell.size, bool)
    for above in (_FOOT, 0.5 * (STEP + CLEARANCE)):  # the feet (not under a kerb or a floor), the body
        q = _keys(cell, z + above, zref, span)
        inside |= np.searchsorted(in_lo, q, side="left") - np.searchsorted(in_hi, q, side="right") > 0
    return free & ~inside


def _steep(ground: np.ndarray, cell: float) -> np.ndarray:
    """(ny, nx) bool: cells the ground climbs to too steeply from a neighbour (the higher of each pair)."""
    bad = np.zeros(ground.shape, bool)
    tan = math.tan(math.radians(MAX_SLOPE_DEG))
    tests = [(1, STEP + cell * tan)]
    k = int(round(RAMP / cell))
    if k >= 2:
        tests.append((k, RAMP * tan))
    with np.errstate(invalid="ignore"):
        for k, rise in tests:
            for axis in (0, 1):
                n = ground.shape[axis]
                if n <= k:
                    continue
                a = np.take(ground, np.arange(n - k), axis=axis)
                b = np.take(ground, np.arange(k, n), axis=axis)
                d = b - a
                over = np.abs(d) > rise
                hi_b, hi_a = over & (d > 0), over & (d < 0)
                idx_a, idx_b = [slice(None)] * 2, [slice(None)] * 2
                idx_a[axis], idx_b[axis] = slice(0, n - k), slice(k, n)
                bad[tuple(idx_b)] |= hi_b
                bad[tuple(idx_a)] |= hi_a
    return bad


def walkable_grid(store: _Store, cell: float | None = None) -> WalkableGrid:
    """The scene's walkable grid (see the module docstring), from an open store (``index``, ``geometries``).

    cell : the cell edge (m); default ``cell_size`` of the scene's bounds
    """
    index = store.index
    bounds = np.asarray(index.bounds, np.float64)
    cell = float(cell) if cell is not None else cell_size(bounds)
    if not (math.isfinite(cell) and cell > 0):
        raise ValueError(f"cell must be a positive size, got {cell!r}")
    ext = np.maximum(bounds[1, :2] - bounds[0, :2], cell)
    nx, ny = (int(v) for v in np.ceil(ext / cell - 1e-9).astype(np.int64))
    raster = _Raster(bounds[0, :2], cell, max(nx, 1), max(ny, 1))
    reps, ground = _reps(index, cell)
    frags = _Fragments()
    _rasterise(store, raster, reps, ground, frags)
    _trees(store, raster, frags)
    cand_cell, cand_z = _Fragments.join(frags.candidates, 2)
    g_cell, g_z = _Fragments.join(frags.ground, 2)
    if g_cell.size:  # a ground surface is a height field: its top in each cell (a closed tile's bottom is not)
        top = np.full(raster.nx * raster.ny, -np.inf)
        np.maximum.at(top, g_cell.astype(np.int64), g_z)
        on = np.flatnonzero(np.isfinite(top))
        cand_cell, cand_z = np.concatenate([cand_cell, on]), np.concatenate([cand_z, top[on]])
    has_ground = bool(ground.any())
    if not has_ground:
        s_cell, _, s_z = _Fragments.join(frags.solid, 3)
        v_cell, v_z = _virtual_ground(raster, s_cell, s_z)
        cand_cell, cand_z = np.concatenate([cand_cell, v_cell]), np.concatenate([cand_z, v_z])
    cand_cell = cand_cell.astype(np.int64)
    zref = float(bounds[0, 2]) - CLEARANCE - 1.0
    span = float(bounds[1, 2] - zref) + 2 * CLEARANCE + 2.0
    ok = _headroom(cand_cell, cand_z, frags, zref, span)
    cand_cell, cand_z = cand_cell[ok], cand_z[ok]
    order = np.lexsort((cand_z, cand_cell))
    cand_cell, cand_z = cand_cell[order], cand_z[order]
    lowest = np.ones(cand_cell.size, bool)
    lowest[1:] = cand_cell[1:] != cand_cell[:-1]
    heights = np.full(raster.nx * raster.ny, np.nan, np.float32)
    heights[cand_cell[lowest]] = np.clip(cand_z[lowest], bounds[0, 2], bounds[1, 2])
    heights = heights.reshape(raster.ny, raster.nx)
    heights[_steep(heights, cell)] = np.nan
    labels, n = ndimage.label(np.isfinite(heights))
    if n > 1:
        sizes = np.bincount(labels.reshape(-1), minlength=n + 1)
        sizes[0] = 0
        small = sizes < MIN_REGION_SHARE * sizes.max()
        heights[small[labels]] = np.nan
    return WalkableGrid(origin=(float(raster.origin[0]), float(raster.origin[1])), cell=cell, ground=heights)

