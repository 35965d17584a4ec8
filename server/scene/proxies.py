"""HLOD proxies that look like what they stand for: candidates measured against the subtree, kept or not.

An inner node of the HLOD tree stands for every object under it. Merging the
children's meshes and decimating them (``hlod``'s unguarded path) collapses the
walls of closed buildings first and leaves roof slabs over empty space; here a
node's proxy is chosen among candidates, each measured (``fidelity``) against
the **subtree's objects at their coarsest kept levels**, merged — each of those
is itself within the bounds of its own full detail, and the full detail of a
whole city would not fit in memory at once. The candidates, in ladder order:

- ``box`` — the objects' LoD1 boxes (``blocks.oriented_box`` of each object's
  finest level), merged: CityGML's LoD1 for a block of buildings;
- ``decimate`` — the node's parts (its kept children's proxies, the objects'
  coarsest levels, which the shape ladder made wall-keeping) merged and
  decimated; tried only while the parts are few faces, since quadric
  decimation of a city block is slow;
- ``footprint`` — the reference as a 2.5-D footprint set with per-footprint
  heights (``footprints.footprint_proxy``), the finest that fits the faces.

A candidate counts when it has at most ``limit`` faces (``limit``: the cost
saving against the parts it replaces in a cut, a draw call counted as
``DRAW_FACES`` faces). Candidates are measured in ladder order — area ratio of
exposed surface (the walls row houses share are buried, in the reference as in
a proxy), silhouette IoU on coverage fractions (the objects are a few pixels
each in a node's masks), then the proxy's geometric
error both ways (the subtree's full-detail points to the proxy, points on the
proxy to the subtree) and FLIP at its switching distance —
and the first that passes is the proxy; a later one than the first measured is
*regenerated*. When none passes, the node keeps no proxy: it is not kept, and
a cut goes from its parent (or from the roots) straight to its children.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import fast_simplification
import numpy as np

from .fidelity import Bounds, Fidelity, area_ratio, flip_error, reference, silhouette_iou
from .footprints import footprint_proxy
from .lod import clean_mesh, geometric_error

__all__ = ["ProxyJob", "ProxyResult", "node_proxy", "proxy_limit", "merge", "simplify", "LADDER", "SAMPLES"]

#: Candidate methods, in ladder order: the footprint set last, as it is the slowest to make and,
#: on a grid, needs the most faces for a given outline.
LADDER = ("box", "decimate", "footprint")

#: Coverage points per mask pixel side for a node's silhouettes.
SAMPLES = 4

#: Fine vertices measured per node for its geometric error (the estimate's subsample).
ERROR_SAMPLES = 1000

#: Parts above this many faces are not decimated (a candidate that fails on buildings anyway).
DECIMATE_MAX_FACES = 20000

#: A draw call's cost in faces (F&S's per-object term C0 over the per-face C1, on the renderer this
#: is made for): a proxy drawn once instead of its parts saves their draws as well as faces.
DRAW_FACES = 16


def proxy_limit(part_faces: int, parts: int, min_saving: float, cap: int) -> int:
    """Most faces of a proxy that costs at most 1 − ``min_saving`` of its ``parts`` (draws and faces)."""
    cost = part_faces + DRAW_FACES * parts
    return max(0, min(cap, int(np.floor((1.0 - min_saving) * cost)) - DRAW_FACES))


@dataclass
class ProxyJob:
    """What one node's proxy is chosen from; meshes are (positions (n, 3) float, faces (m, 3) int).

    objects : the subtree's objects' coarsest levels (the reference)
    boxes   : their LoD1 boxes (None where an object has none)
    parts   : what the node replaces in a cut (kept children's proxies, objects' coarsest levels);
              empty when they are too many faces to decimate
    points  : (p, 3) the subtree's full-detail points, for the geometric error
    limit   : most faces a proxy may have
    """

    objects: list
    boxes: list
    parts: list
    points: np.ndarray
    limit: int


@dataclass
class ProxyResult:
    """The kept proxy (None: the node is not kept), its error, measures and how it was chosen."""

    positions: np.ndarray | None
    faces: np.ndarray | None
    error: float
    fidelity: Fidelity | None
    regenerated: bool
    best: Fidelity | None  # the best measures among the candidates, when none passed
    closed: bool = False  # whether the area bound applied (every object closed)


def merge(meshes: list) -> tuple[np.ndarray, np.ndarray]:
    """One mesh of many: positions (Σn, 3) float64, faces (Σm, 3) int64."""
    if not meshes:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    offsets = np.cumsum([0] + [p.shape[0] for p, _ in meshes[:-1]])
    pos = np.concatenate([np.asarray(p, np.float64) for p, _ in meshes])
    fac = np.concatenate([np.asarray(f, np.int64) + o for (_, f), o in zip(meshes, offsets)])
    return pos, fac


def _cluster_vertices(pos: np.ndarray, fac: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertex clustering (Rossignac & Borrel): weld vertices per grid cell, drop collapsed and repeated faces."""
    key = np.floor((pos - pos.min(axis=0)) / cell).astype(np.int64)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    centre = np.zeros((counts.size, 3))
    np.add.at(centre, inverse, pos)
    f = inverse[fac]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    _, first = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
    return clean_mesh(centre / counts[:, None], f[np.sort(first)])


def simplify(pos: np.ndarray, fac: np.ndarray, limit: int, stalled: bool = False) -> tuple[np.ndarray, np.ndarray, bool]:
    """Decimate to at most ``limit`` faces.

    Quadric decimation stalls on many small disjoint parts (each stops near a
    tetrahedron), so when it cannot reach ``limit`` the result is vertex-clustered
    on a coarsening grid, which merges neighbouring parts, and decimated again.
    The simplifier aims a little under ``limit`` as it may overshoot by a few faces.
    A stalled decimation is slow (it runs all its passes), so when the parts are
    known to be stalled already (``stalled``: a child needed clustering) the
    first attempt is skipped. Returns positions, faces, and whether it stalled.
    """
    if limit < 1:
        return pos[:0], fac[:0], False
    target = max(1, int(limit * 0.95))
    if stalled:
        p, f = pos, fac
    else:
        p, f = clean_mesh(*fast_simplification.simplify(pos, fac, target_count=target))
        if f.shape[0] <= limit:
            return p, f, False
    diag = float(np.linalg.norm(pos.max(axis=0) - pos.min(axis=0)))
    cell = diag / (8.0 * math.sqrt(limit))  # from fine to coarse: the first grid that fits keeps the most shape
    retried = False
    while True:
        cp, cf = _cluster_vertices(p, f, cell)
        if cf.shape[0] <= limit:
            return cp, cf, True
        if not retried and cf.shape[0] <= 1.5 * limit:  # once: a stalled decimation is slow
            retried = True
            sp, sf = clean_mesh(*fast_simplification.simplify(cp, cf, target_count=target))
            if sf.shape[0] <= limit:
                return sp, sf, True
        cell *= 1.3


def _candidate(method: str, job: ProxyJob, ref_mesh: tuple[np.ndarray, np.ndarray]):
    if method == "box":
        if any(b is None for b in job.boxes) or 12 * len(job.boxes) > job.limit:
            return None
        return merge(job.boxes)
    if method == "footprint":
        p, f = footprint_proxy(*ref_mesh, job.limit)
        return (p, f) if f.shape[0] else None
    if not job.parts:
        return None
    pos, fac = merge(job.parts)
    target = min(job.limit, (fac.shape[0] * 3) // 5)  # decimation that removes faces, whatever draws save
    p, f, _ = simplify(pos, fac, target)
    return (p, f) if 0 < f.shape[0] <= target else None


def _surface_samples(positions: np.ndarray, faces: np.ndarray, n: int) -> np.ndarray:
    """(n, 3) points spread over the surface by area (systematically: deterministic, every face its share)."""
    tri = positions[faces]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    cum = np.cumsum(area)
    t = np.minimum(np.searchsorted(cum, (np.arange(n) + 0.5) / n * cum[-1], side="right"), faces.shape[0] - 1)
    u = (0.5 + np.arange(n) / 1.32471795724474602596) % 1.0  # R2 low-discrepancy points inside each face
    v = (0.5 + np.arange(n) / 1.32471795724474602596 ** 2) % 1.0
    r1 = np.sqrt(u)[:, None]
    return tri[t, 0] * (1 - r1) + tri[t, 1] * (r1 * (1 - v[:, None])) + tri[t, 2] * (r1 * v[:, None])


def _hausdorff(points: np.ndarray, ref_mesh: tuple[np.ndarray, np.ndarray], p: np.ndarray, f: np.ndarray) -> float:
    """The proxy's geometric error both ways: from the subtree's full-detail points to the proxy, and
    from points on the proxy to the subtree's coarsest levels — a proxy that spans the street
    between two buildings, or a slab over empty space, is far from everything it stands for."""
    out = geometric_error(points, p, f, samples=ERROR_SAMPLES)
    back = geometric_error(_surface_samples(p, f, ERROR_SAMPLES), *ref_mesh, samples=ERROR_SAMPLES)
    return max(out, back)


def node_proxy(job: ProxyJob, bounds: Bounds) -> ProxyResult:
    """The node's proxy: the first candidate in ladder order within ``limit`` and ``bounds``."""
    ref_mesh = merge(job.objects)
    if ref_mesh[1].shape[0] == 0:
        return ProxyResult(None, None, float("nan"), None, False, None)
    ref = reference(*ref_mesh, samples=SAMPLES)
    points = job.points if len(job.points) else ref_mesh[0]
    best, measured = None, 0
    for method in LADDER:
        cand = _candidate(method, job, ref_mesh)
        if cand is None:
            continue
        p, f = cand
        measured += 1
        area = area_ratio(ref, p, f)
        fid = Fidelity(area, silhouette_iou(ref, p, f), float("nan"), method)
        if bounds.passes(fid, ref.closed):
            err = _hausdorff(points, ref_mesh, p, f)
            fid = Fidelity(area, fid.iou, flip_error(ref, p, f, err), method)
            if bounds.passes(fid, ref.closed):
                return ProxyResult(p, f, err, fid, measured > 1, None, ref.closed)
        if best is None or fid.iou > best.iou:
            best = fid
    return ProxyResult(None, None, float("nan"), None, False, best, ref.closed)
