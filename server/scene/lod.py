"""LOD chains by quadric decimation, their geomorph maps, and the geometric error of each level.

A chain is a list of meshes ordered coarsest → finest (the store's level
convention: level 0 is the coarsest, the last level is full detail). Each level
is simplified from the next finer one with ``fast_simplification`` (Garland &
Heckbert quadrics), so errors compound the way they do for any successive
simplifier.

**Model no more than the object needs.** A coarser level is added only while
it saves at least ``min_saving`` (40 %) of the faces of the level before it: a
level that saves less costs a representation (storage, a selection variable, a
morph) for little gain in rendering cost. The chain stops at a floor of a few
faces, when the simplifier cannot save enough (pinned open borders), or at
``max_levels``. Each step asks for ``ratio`` (half) of the faces, so a chain
has a few levels, each at most 60 % of the next finer one.

**Geomorph maps.** ``Chain.morph[k]`` maps every vertex of level k to a vertex
of level k − 1. Zach (2002) maps each finer vertex to the *nearest* coarser
vertex and names the artefacts of that rule as future work; here the map comes
from the simplifier's own edge collapses (``morph="collapse"``): each fine
vertex goes to the vertex it was collapsed into. Moving every vertex of level
k to its target ("weight 0") then turns level k into exactly level k − 1's
surface: each fine triangle either degenerates or lands on a coarse triangle,
and every coarse triangle is hit (``morph_faces_match``). The nearest rule is
kept for comparison and for chains that come from the source
(``chain_from_levels``), where no collapse history exists.

**Stored order.** Levels are kept in GPU order (``proto.geometry.order_for_gpu``:
vertex-cache order, vertices in first-use order), the order in which they are
stored, so the maps index stored vertices; encode them with
``encode_geometry(..., reorder=False)``.

The error of a level is the one-sided Hausdorff distance from the full-detail
surface to that level, estimated on a deterministic subsample of full-detail
vertices; on that subsample the maximum is exact. The point–mesh distances come
from libigl's AABB tree (``igl.point_mesh_squared_distance``): the error
estimate is most of the chain stage's work, and the tree gives the same
distances as a brute-force closest-point search in a fraction of its time.

Example::

    >>> import trimesh
    >>> m = trimesh.creation.icosphere(4)
    >>> chain = build_chain(m.vertices, m.faces)
    >>> chain.faces                               # doctest: +SKIP
    [40, 80, 160, 320, 640, 1280, 2560, 5120]
    >>> morph_faces_match(chain, len(chain) - 1)
    True
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator, Sequence

import fast_simplification
import igl
import numpy as np
from scipy.spatial import cKDTree

from proto.geometry import order_for_gpu

__all__ = [
    "Chain", "build_chain", "chain_from_levels", "clean_mesh", "geometric_error", "chain_errors",
    "nearest_vertex_map", "morph_positions", "morph_faces_match", "morph_surface_error", "MORPH_KINDS",
]

#: Vertex correspondences ``build_chain`` can make: from edge collapses, by the nearest rule, or none.
MORPH_KINDS = ("collapse", "nearest", "none")

Level = tuple[np.ndarray, np.ndarray]


@dataclass
class Chain:
    """An object's LOD chain, coarsest → finest, with its geomorph maps and errors.

    levels : [(positions (n_k, 3) float64, faces (m_k, 3) int64), ...], in GPU
             (stored) order; the last level is full detail
    morph  : per level, ``None`` for level 0 (and for every level if
             ``morph_kind == "none"``), else an (n_k,) int64 array: vertex v of
             level k morphs to vertex ``morph[k][v]`` of level k − 1
    errors : geometric error of each level against full detail (object-space
             units), non-increasing toward full detail, 0 at the finest
    morph_kind : "collapse" (topology-consistent, from the simplifier's edge
             collapses), "nearest" (Zach's rule) or "none"

    For code written against the former list-of-levels API, a chain is also a
    read-only sequence of its levels (``len``, indexing, iteration, ``+``).
    """

    levels: list[Level]
    morph: list[np.ndarray | None]
    errors: list[float]
    morph_kind: str = "collapse"

    @property
    def faces(self) -> list[int]:
        """Triangles per level, coarsest first."""
        return [int(f.shape[0]) for _, f in self.levels]

    @property
    def vertices(self) -> list[int]:
        """Vertices per level, coarsest first."""
        return [int(p.shape[0]) for p, _ in self.levels]

    def __len__(self) -> int:
        return len(self.levels)

    def __getitem__(self, k):  # int or slice, like the former list
        return self.levels[k]

    def __iter__(self) -> Iterator[Level]:
        return iter(self.levels)

    def __add__(self, other: Sequence[Level]) -> list[Level]:
        return list(self.levels) + list(other)

    def __radd__(self, other: Sequence[Level]) -> list[Level]:
        return list(other) + list(self.levels)


def _clean(positions: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``clean_mesh`` plus the vertex map: (positions, faces, new_of_old (n,) int64, −1 where dropped)."""
    positions = np.asarray(positions, np.float64)
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    distinct = (a != b) & (b != c) & (a != c)
    tri = positions[faces]
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    faces = faces[distinct & (area2 > 0.0)]
    used = np.zeros(positions.shape[0], bool)
    used[faces.ravel()] = True
    remap = np.where(used, np.cumsum(used) - 1, -1)
    return positions[used], remap[faces], remap


def clean_mesh(positions: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop degenerate faces and unreferenced vertices, as the simplifier can leave both.

    positions : (n, 3) float
    faces     : (m, 3) int
    Returns (n', 3) float64 positions and (m', 3) int64 faces; the kept
    vertices keep their relative order.
    """
    p, f, _ = _clean(positions, faces)
    return p, f


def _prepare(positions: np.ndarray, faces: np.ndarray) -> Level:
    """Cleaned and in GPU order: the form every stored level has."""
    p, f = clean_mesh(positions, faces)
    if f.shape[0] == 0:
        raise ValueError("the mesh has no non-degenerate faces")
    p, f, _ = order_for_gpu(p, f)
    return p, f


def _representatives(n: int, collapses: np.ndarray) -> np.ndarray:
    """Final vertex of each of n vertices after the collapses ``[keep, gone]``, in order."""
    parent = np.arange(n, dtype=np.int64)
    collapses = np.asarray(collapses, np.int64).reshape(-1, 2)
    parent[collapses[:, 1]] = collapses[:, 0]
    rep = parent
    while True:  # pointer jumping: a few rounds (log of the longest collapse chain)
        nxt = rep[rep]
        if np.array_equal(nxt, rep):
            return rep
        rep = nxt


def _image(faces: np.ndarray, vmap: np.ndarray) -> np.ndarray:
    """Faces mapped through vmap, without the ones that degenerate (two equal corners)."""
    g = vmap[faces]
    keep = (g[:, 0] != g[:, 1]) & (g[:, 1] != g[:, 2]) & (g[:, 0] != g[:, 2])
    return g[keep]


def _canonical(faces: np.ndarray) -> np.ndarray:
    """Faces rotated to start at their least index (winding kept), rows sorted."""
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    r = np.argmin(faces, axis=1)
    rows = np.arange(faces.shape[0])[:, None]
    rot = faces[rows, (r[:, None] + np.arange(3)) % 3]
    return rot[np.lexsort(rot.T[::-1])] if rot.size else rot


def _simplify_step(positions: np.ndarray, faces: np.ndarray, target: int,
                   preserve_border: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One coarser level and the collapse map onto it.

    positions, faces : a cleaned level in GPU order
    Returns (coarse positions, coarse faces) in GPU order and the (n,) int64
    map of the fine vertices onto the coarse ones. The coarse faces are the
    image of the fine faces under the map, which is what the simplifier
    produced (checked), less faces of zero area.
    """
    n = positions.shape[0]
    sp, sf, collapses = fast_simplification.simplify(
        positions, faces, target_count=target, return_collapses=True, preserve_border=preserve_border)
    sf = np.asarray(sf, np.int64).reshape(-1, 3)
    # The simplifier keeps the vertices that survive the collapses and still
    # carry a face, in their original order; so a fine vertex's coarse id is
    # the rank of its representative among those.
    rep = _representatives(n, collapses)
    mapped = rep[faces]
    keep = (mapped[:, 0] != mapped[:, 1]) & (mapped[:, 1] != mapped[:, 2]) & (mapped[:, 0] != mapped[:, 2])
    carriers = np.unique(mapped[keep])
    vmap = np.searchsorted(carriers, rep)
    image = np.searchsorted(carriers, mapped[keep])
    if carriers.size == sp.shape[0] and np.array_equal(image, sf):
        # A survivor whose faces all collapsed away (a border corner, say) is
        # dropped; any target keeps its fine faces degenerate, so take the
        # coarse vertex nearest that survivor. (Nearest to the survivor, not to each
        # fine vertex: vertices that share a representative must share a target, or
        # a fine face that the collapses flattened would open up again at weight 0.)
        isolated = carriers[np.minimum(vmap, carriers.size - 1)] != rep
        if isolated.any():
            _, vmap[isolated] = cKDTree(sp).query(positions[rep[isolated]])
    else:
        # Not the expected numbering: let fast_simplification replay the collapses.
        _, _, vmap = fast_simplification.replay_simplification(
            positions.astype(np.float32), faces.astype(np.int64), collapses)
        vmap = np.asarray(vmap, np.int64)
        image = _image(faces, vmap) if vmap.min() >= 0 and vmap.max() < sp.shape[0] else None
        if image is None or not np.array_equal(_canonical(image), _canonical(sf)):
            raise RuntimeError("fast_simplification's collapse history does not reproduce its output")
    cp, cf, remap = _clean(sp, image)
    fine_to_coarse = remap[vmap]
    lost = fine_to_coarse < 0
    if lost.any():
        # Vertices used only by zero-area faces were dropped with them; their
        # fine vertices go to the nearest remaining coarse vertex.
        _, near = cKDTree(cp).query(sp[vmap[lost]])
        fine_to_coarse[lost] = near
    cp, cf, new_of_old = order_for_gpu(cp, cf)
    return cp, cf, new_of_old[fine_to_coarse]


def nearest_vertex_map(fine_positions: np.ndarray, coarse_positions: np.ndarray) -> np.ndarray:
    """Zach's vertex correspondence: each fine vertex → the nearest coarse vertex.

    fine_positions   : (n, 3) float
    coarse_positions : (n', 3) float, n' > 0
    Returns (n,) int64 indices into coarse_positions (ties go to the lower id, as cKDTree breaks them).
    """
    fine = np.asarray(fine_positions, np.float64).reshape(-1, 3)
    coarse = np.asarray(coarse_positions, np.float64).reshape(-1, 3)
    if coarse.shape[0] == 0:
        raise ValueError("nearest_vertex_map needs at least one coarse vertex")
    _, idx = cKDTree(coarse).query(fine)
    return np.asarray(idx, np.int64).reshape(-1)


def morph_positions(fine_positions: np.ndarray, coarse_positions: np.ndarray, morph: np.ndarray,
                    weight: float | np.ndarray) -> np.ndarray:
    """The geomorph blend of a fine level toward its coarser neighbour.

    fine_positions   : (n, 3) float — level k
    coarse_positions : (n', 3) float — level k − 1
    morph            : (n,) int — ``Chain.morph[k]``
    weight           : 1 = the fine level as it is, 0 = every vertex at its coarse
                       target (the coarse surface); a scalar or an (n,) array
    Returns (n, 3) float64: weight · fine + (1 − weight) · coarse[morph].
    """
    fine = np.asarray(fine_positions, np.float64)
    target = np.asarray(coarse_positions, np.float64)[np.asarray(morph, np.int64)]
    w = np.asarray(weight, np.float64)
    if w.ndim == 1:
        w = w[:, None]
    return target + w * (fine - target)


def _validate_maps(levels: list[Level], morph: list[np.ndarray | None]) -> None:
    for k, m in enumerate(morph):
        if m is None:
            continue
        if k == 0:
            raise ValueError("level 0 has no coarser level to morph to")
        if m.shape != (levels[k][0].shape[0],) or m.min() < 0 or m.max() >= levels[k - 1][0].shape[0]:
            raise ValueError(f"morph map of level {k} is not a map onto level {k - 1}'s vertices")


def build_chain(
    positions: np.ndarray,
    faces: np.ndarray,
    *,
    min_saving: float = 0.4,
    floor_faces: int = 12,
    max_levels: int = 8,
    morph: str = "collapse",
    preserve_border: bool = True,
    ratio: float = 0.5,
    levels: int | None = None,
    samples: int = 2000,
) -> Chain:
    """Successively simplified levels of one mesh, coarsest → finest, with morph maps and errors.

    positions : (n, 3) float — the full-detail mesh
    faces     : (m, 3) int
    min_saving : a coarser level is made only if it has at most (1 − min_saving)
        of the faces of the level before it
    floor_faces : no level has fewer faces than this (the chain stops instead)
    max_levels : at most this many levels, full detail included
    morph     : "collapse" (maps from the simplifier's edge collapses; exact
        geomorphs), "nearest" (each vertex to the nearest coarser vertex) or "none"
    preserve_border : keep open boundaries at full resolution. Without it the
        quadric simplifier erodes them (a 33 m ground tile lost 0.7 m at its
        edge after one step); with it, tiles that share a boundary meet without
        cracks at any pair of levels. Closed meshes are unaffected. Pinned
        borders can stop a chain early, when a step cannot save ``min_saving``.
    ratio     : the face count each step asks the simplifier for, relative to
        the level before (≤ 1 − min_saving)
    levels    : former name of ``max_levels`` (kept for old callers)
    samples   : full-detail vertices measured per level for the errors (``chain_errors``)

    Returns a ``Chain``; its last level is the cleaned input in GPU order.
    """
    if levels is not None:
        max_levels = levels
    if max_levels < 1:
        raise ValueError(f"max_levels must be ≥ 1, got {max_levels}")
    if not 0.0 < min_saving < 1.0:
        raise ValueError(f"min_saving must lie in (0, 1), got {min_saving}")
    if not 0.0 < ratio <= 1.0 - min_saving:
        raise ValueError(f"ratio must lie in (0, 1 − min_saving], got {ratio}")
    if floor_faces < 1:
        raise ValueError(f"floor_faces must be ≥ 1, got {floor_faces}")
    if morph not in MORPH_KINDS:
        raise ValueError(f"morph must be one of {MORPH_KINDS}, got {morph!r}")
    fine_first = [_prepare(positions, faces)]
    maps: list[np.ndarray] = []  # maps[j]: vertices of fine_first[j] → fine_first[j + 1]
    while len(fine_first) < max_levels:
        pos, fac = fine_first[-1]
        m = fac.shape[0]
        limit = int(np.floor((1.0 - min_saving) * m))  # most faces a coarser level may have
        if limit < floor_faces:
            break
        target = min(limit, max(floor_faces, int(round(ratio * m))))
        cp, cf, vmap = _simplify_step(pos, fac, target, preserve_border)
        if not floor_faces <= cf.shape[0] <= limit:
            break
        fine_first.append((cp, cf))
        maps.append(vmap)
    chain_levels = fine_first[::-1]
    if morph == "collapse":
        morphs: list[np.ndarray | None] = [None] + maps[::-1]
    elif morph == "nearest":
        morphs = [None] + [nearest_vertex_map(chain_levels[k][0], chain_levels[k - 1][0])
                           for k in range(1, len(chain_levels))]
    else:
        morphs = [None] * len(chain_levels)
    return Chain(chain_levels, morphs, chain_errors(chain_levels, samples=samples), morph)


def chain_from_levels(
    levels: Sequence[Level],
    errors: Sequence[float] | None = None,
    morph: str = "nearest",
    samples: int = 2000,
) -> Chain:
    """A chain from levels the source gives (e.g. CityJSON LoD 1.2 / 1.3 / 2.2 of one building).

    levels : [(positions (n_k, 3) float, faces (m_k, 3) int), ...] coarsest → finest;
             each is cleaned and put in GPU order
    errors : per level, or None to measure them against the last level (``chain_errors``)
    morph  : "nearest" or "none" — no collapse history exists for such levels
    """
    if len(levels) == 0:
        raise ValueError("a chain needs at least one level")
    if morph not in ("nearest", "none"):
        raise ValueError(f"morph must be 'nearest' or 'none' for given levels, got {morph!r}")
    prepared = [_prepare(p, f) for p, f in levels]
    if errors is None:
        errors = chain_errors(prepared, samples=samples)
    elif len(errors) != len(prepared):
        raise ValueError(f"{len(prepared)} levels but {len(errors)} errors")
    if morph == "nearest":
        morphs: list[np.ndarray | None] = [None] + [nearest_vertex_map(prepared[k][0], prepared[k - 1][0])
                                                    for k in range(1, len(prepared))]
    else:
        morphs = [None] * len(prepared)
    return Chain(prepared, morphs, [float(e) for e in errors], morph)


def morph_faces_match(chain: Chain, k: int) -> bool:
    """Whether weight 0 turns level k exactly into level k − 1 (combinatorially).

    True when every face of level k, its corners replaced by their targets,
    either degenerates (two corners share a target) or is a face of level k − 1
    with the same winding, and every face of level k − 1 is hit. Faces of zero
    area in level k − 1's positions are allowed to be missing from level k − 1
    (``clean_mesh`` drops them).
    """
    if not 1 <= k < len(chain.levels):
        raise ValueError(f"level {k} has no coarser level in a chain of {len(chain.levels)}")
    m = chain.morph[k]
    if m is None:
        return False
    (cp, cf), (_, ff) = chain.levels[k - 1], chain.levels[k]
    image = _canonical(_image(ff, np.asarray(m, np.int64)))
    coarse = np.unique(_canonical(cf), axis=0)
    hit = np.unique(image, axis=0) if image.size else image.reshape(0, 3)
    # Every image face is a coarse face or has zero area.
    view = lambda a: np.ascontiguousarray(a).view([("", a.dtype)] * 3).ravel()  # noqa: E731
    known = np.isin(view(hit), view(coarse))
    if not known.all():
        tri = cp[hit[~known]]
        area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        if (area2 > 0.0).any():
            return False
    return bool(np.isin(view(coarse), view(hit)).all())


def _surface_points(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Centroids and edge midpoints of the non-degenerate faces: where a bad morph shows."""
    tri = positions[faces]
    return np.concatenate([tri.mean(axis=1), (tri + np.roll(tri, 1, axis=1)).reshape(-1, 3) / 2.0])


def morph_surface_error(chain: Chain, k: int, samples: int = 20000, seed: int = 0) -> float:
    """How far level k at weight 0 is from level k − 1's surface (object-space units).

    The symmetric distance between the morphed-down level k (each vertex at its
    target) and level k − 1, estimated on triangle centroids and edge midpoints
    of both (vertices would not do: all morphed vertices are coarse vertices).
    Zero for collapse maps; typically positive for the nearest rule, whose
    triangles cut across the coarse surface or leave parts of it uncovered.
    """
    if not 1 <= k < len(chain.levels):
        raise ValueError(f"level {k} has no coarser level in a chain of {len(chain.levels)}")
    m = chain.morph[k]
    if m is None:
        raise ValueError(f"level {k} has no morph map")
    (cp, cf), (_, ff) = chain.levels[k - 1], chain.levels[k]
    image = _image(ff, np.asarray(m, np.int64))
    if image.shape[0] == 0:
        return float("inf")
    forward = geometric_error(_surface_points(cp, image), cp, cf, samples, seed)
    backward = geometric_error(_surface_points(cp, cf), cp, image, samples, seed)
    return max(forward, backward)


def geometric_error(
    fine_positions: np.ndarray,
    coarse_positions: np.ndarray,
    coarse_faces: np.ndarray,
    samples: int = 2000,
    seed: int = 0,
) -> float:
    """Estimated one-sided Hausdorff distance from the fine vertices to the coarse surface.

    fine_positions   : (n, 3) float — vertices of the full-detail mesh
    coarse_positions : (n', 3) float
    coarse_faces     : (m', 3) int
    samples : at most this many fine vertices are measured (all when fewer)
    seed    : picks the subsample, so the estimate is deterministic

    Returns the largest distance found, in the positions' units (object space);
    on the sampled points it is exact (libigl's AABB-tree point–mesh distance).
    """
    fine = np.asarray(fine_positions, np.float64).reshape(-1, 3)
    pos = np.ascontiguousarray(coarse_positions, np.float64).reshape(-1, 3)
    fac = np.ascontiguousarray(coarse_faces, np.int64).reshape(-1, 3)
    if fine.shape[0] == 0 or fac.shape[0] == 0:
        raise ValueError("geometric_error needs a non-empty fine point set and coarse mesh")
    if fine.shape[0] > samples:
        pick = np.random.default_rng(seed).choice(fine.shape[0], samples, replace=False)
        fine = fine[np.sort(pick)]
    squared, _, _ = igl.point_mesh_squared_distance(np.ascontiguousarray(fine), pos, fac)
    return float(np.sqrt(max(float(np.max(squared)), 0.0)))


def chain_errors(chain: list[tuple[np.ndarray, np.ndarray]], samples: int = 2000, seed: int = 0) -> list[float]:
    """Geometric error of every level of a chain against its last (full-detail) level.

    The estimates are made non-increasing toward full detail (a running maximum
    from the finest level down), because selection relies on diminishing
    returns: a coarser level is never reported as more accurate than a finer one.
    The full-detail level's error is exactly 0.
    """
    fine = chain[-1][0]
    raw = [geometric_error(fine, p, f, samples, seed) for p, f in chain[:-1]] + [0.0]
    return [float(e) for e in np.maximum.accumulate(np.asarray(raw)[::-1])[::-1]]
