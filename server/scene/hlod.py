"""An HLOD tree over many objects: clusters of nearby objects share one merged, simplified proxy.

With tens of thousands of buildings (Zach 2002) the per-object LOD chains are
not enough: far away, even every building's coarsest level is too many draw
calls and triangles. So objects are clustered spatially into a tree, and each
inner node carries a proxy — its children's proxies merged and decimated —
that stands in for the whole subtree. Hierarchical selection starts at the
root (one node covering the whole scene) and refines toward the objects.

Clustering is a k-d split on the objects' box centres: a node's objects are
cut at rank-proportional positions along their longest extent, so siblings
are compact and nearly equal in size. Inner nodes are numbered in BFS order
(parents before children, root 0), which keeps every node's children
contiguous; proxies are built bottom-up (reverse BFS), each from its children.

Example::

    >>> tree = build_hlod(lo, hi, proxies, fanout=8, leaf_size=8)   # doctest: +SKIP
    >>> tree.children(0), tree.leaves_under(0).size == len(proxies)  # doctest: +SKIP
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import fast_simplification
import numpy as np

from server.scene import blocks
from server.scene.fidelity import Bounds, measure, reference
from server.scene.footprints import footprint_proxy
from server.scene.lod import clean_mesh, geometric_error
from server.scene.source import Mesh
from server.scene.workers import process_pool

__all__ = ["HLODTree", "build_hlod"]

#: Fine vertices measured per node for its geometric error (the estimate's subsample).
ERROR_SAMPLES = 1000


@dataclass
class HLODTree:
    """Inner nodes 0..N-1 in BFS order (root 0) over n objects, as a structure of arrays.

    parent        : (N,) int32, -1 for the root; parent[i] < i
    depth         : (N,) int16, 0 at the root
    lo, hi        : (N, 3) float64 — box of the node's objects and of its proxy
    error         : (N,) float64 — geometric error of the proxy (metres), non-decreasing toward the root
    proxies       : N meshes, the merged simplified stand-ins of the subtrees
    object_parent : (n,) int32 — the (lowest) inner node each object hangs under
    fidelity      : per node, the proxy's measures (``Fidelity``) or None when unmeasured
    regenerated, dropped : proxies rebuilt by the next method / left below the bounds
    """

    parent: np.ndarray
    depth: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    error: np.ndarray
    proxies: list[Mesh]
    object_parent: np.ndarray
    fidelity: list = field(default_factory=list)
    regenerated: int = 0
    dropped: int = 0
    _child_start: np.ndarray = field(init=False, repr=False)
    _object_order: np.ndarray = field(init=False, repr=False)
    _object_start: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        n_nodes = self.parent.shape[0]
        # BFS order makes each node's children one contiguous, sorted run of ids.
        counts = np.bincount(self.parent[1:], minlength=n_nodes)
        self._child_start = np.concatenate([[1], 1 + np.cumsum(counts)]).astype(np.int64)
        self._object_order = np.argsort(self.object_parent, kind="stable").astype(np.int64)
        ocounts = np.bincount(self.object_parent, minlength=n_nodes)
        self._object_start = np.concatenate([[0], np.cumsum(ocounts)]).astype(np.int64)

    @property
    def n_nodes(self) -> int:
        return int(self.parent.shape[0])

    @property
    def n_objects(self) -> int:
        return int(self.object_parent.shape[0])

    @property
    def height(self) -> int:
        """Levels of inner nodes (1 when the root is the only one)."""
        return int(self.depth.max()) + 1

    def children(self, node: int) -> np.ndarray:
        """Inner-node children of ``node`` (int64, ascending; empty for a lowest node)."""
        return np.arange(self._child_start[node], self._child_start[node + 1], dtype=np.int64)

    def objects(self, node: int) -> np.ndarray:
        """Objects hanging directly under ``node`` (int64, ascending; empty above the lowest level)."""
        return self._object_order[self._object_start[node] : self._object_start[node + 1]]

    def leaves_under(self, node: int) -> np.ndarray:
        """Every object in the subtree of ``node`` (int64, ascending)."""
        # BFS numbering: a subtree's nodes at each depth form one contiguous id range.
        first = last = node
        parts = []
        while first <= last:
            parts.append(self._object_order[self._object_start[first] : self._object_start[last + 1]])
            first, last = self._child_start[first], self._child_start[last + 1] - 1
        return np.sort(np.concatenate(parts))


# --------------------------------------------------------------------------- clustering


def _split(idx: np.ndarray, centres: np.ndarray, k: int) -> list[np.ndarray]:
    """Cut ``idx`` into k nearly equal, spatially compact parts by binary splits along the longest axis."""
    if k == 1:
        return [idx]
    c = centres[idx]
    axis = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
    k1 = k // 2
    n1 = int(round(idx.size * k1 / k))
    # Stable sort (not argpartition) so ties are cut the same way on every machine.
    order = np.argsort(c[:, axis], kind="stable")
    return _split(idx[order[:n1]], centres, k1) + _split(idx[order[n1:]], centres, k - k1)


def _cluster(centres: np.ndarray, fanout: int, leaf_size: int):
    """Tree shape: parent (N,), depth (N,) in BFS order, and object_parent (n,)."""
    parent, depth = [-1], [0]
    object_parent = np.empty(centres.shape[0], np.int32)
    queue = [np.arange(centres.shape[0])]  # queue[i]: the objects of node i
    i = 0
    while i < len(queue):
        idx = queue[i]
        if idx.size <= leaf_size:
            object_parent[idx] = i
        else:
            leaves = math.ceil(idx.size / leaf_size)
            h = 0
            while fanout**h < leaves:
                h += 1
            cap = leaf_size * fanout ** (h - 1)  # objects one child subtree can hold
            for part in _split(idx, centres, math.ceil(idx.size / cap)):
                parent.append(i)
                depth.append(depth[i] + 1)
                queue.append(part)
        i += 1
    return np.asarray(parent, np.int32), np.asarray(depth, np.int16), object_parent


# --------------------------------------------------------------------------- proxies


def _merge(meshes: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    offsets = np.cumsum([0] + [p.shape[0] for p, _ in meshes[:-1]])
    pos = np.concatenate([p for p, _ in meshes])
    fac = np.concatenate([f + o for (_, f), o in zip(meshes, offsets)])
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


def _simplify(pos: np.ndarray, fac: np.ndarray, limit: int, stalled: bool = False) -> tuple[np.ndarray, np.ndarray, bool]:
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


def build_hlod(
    lo: np.ndarray,
    hi: np.ndarray,
    proxies: Sequence[Mesh],
    *,
    fanout: int = 8,
    leaf_size: int = 8,
    max_proxy_faces: int = 4096,
    object_error: np.ndarray | None = None,
    progress: Callable[[int, int], None] | None = None,
    workers: int = 1,
    points: Sequence[np.ndarray] | None = None,
    bounds: Bounds | None = None,
) -> HLODTree:
    """Cluster n objects into an HLOD tree and build every inner node's merged proxy.

    lo, hi          : (n, 3) object boxes
    proxies         : n meshes, each object's stand-in inside its parent's merge
                      (the builder passes each object's coarsest level)
    fanout          : most inner-node children of an inner node (≥ 2)
    leaf_size       : most objects under a lowest inner node (≥ 1)
    max_proxy_faces : cap on a node proxy's faces; a proxy also has at most half
                      the faces of its children's merged proxies
    object_error    : (n,) geometric error of each object's proxy, added into its
                      parent's error (zeros when omitted)
    progress        : called as progress(done, total) after each inner node
    workers         : processes building proxies (1: in this process); the result
                      does not depend on it
    points          : n arrays of each object's full-detail vertices (a subsample); a node's
                      error is then measured from its subtree's points to its proxy
    bounds          : build proxies as 2.5-D footprint sets guarded by these bounds
                      (``_node_proxy``); None: merge and decimate, unmeasured

    Without ``points``, a node's error is the estimated Hausdorff distance from the merged
    children's vertices to its proxy plus the largest child error; with them it is measured
    from the subtree's full-detail points, and made no less than its children's.
    """
    lo = np.asarray(lo, np.float64).reshape(-1, 3)
    hi = np.asarray(hi, np.float64).reshape(-1, 3)
    n = lo.shape[0]
    if n == 0 or hi.shape[0] != n or len(proxies) != n:
        raise ValueError(f"need n ≥ 1 objects with matching boxes and proxies, got {n}, {hi.shape[0]}, {len(proxies)}")
    if fanout < 2 or leaf_size < 1 or max_proxy_faces < 1:
        raise ValueError(f"need fanout ≥ 2, leaf_size ≥ 1, max_proxy_faces ≥ 1; got {fanout}, {leaf_size}, {max_proxy_faces}")
    obj_err = np.zeros(n) if object_error is None else np.asarray(object_error, np.float64).reshape(n)
    parent, depth, object_parent = _cluster((lo + hi) / 2.0, fanout, leaf_size)
    n_nodes = parent.shape[0]
    tree = HLODTree(parent, depth, np.empty((n_nodes, 3)), np.empty((n_nodes, 3)), np.zeros(n_nodes),
                    [None] * n_nodes, object_parent)  # type: ignore[list-item]
    tree.fidelity = [None] * n_nodes
    stalled = np.zeros(n_nodes, bool)  # the node's proxy needed vertex clustering
    pool = process_pool(workers) if workers > 1 else None
    done = 0
    try:
        # Bottom-up one depth at a time: the nodes of a depth are independent.
        for d in range(int(depth.max()), -1, -1):
            nodes = np.flatnonzero(depth == d)[::-1]
            tasks, flags, pts, masks = [], [], [], []
            for node in nodes:
                pts.append(None if points is None else np.concatenate(
                    [np.zeros((0, 3))] + [points[o] for o in tree.leaves_under(node)]))
                flags.append(bool(stalled[tree.children(node)].any()))
                parts = [(tree.proxies[k], False) for k in tree.children(node)] + [
                    (proxies[o], True) for o in tree.objects(node)]
                tasks.append([(m.positions, m.faces) for m, _ in parts if m.n_faces > 0])
                masks.append([is_obj for m, is_obj in parts if m.n_faces > 0])
            if pool is None:
                results = map(_node_proxy, tasks, [max_proxy_faces] * len(tasks), flags, pts,
                              [bounds] * len(tasks), masks)
            else:
                chunk = max(1, min(32, len(tasks) // (4 * workers)))
                results = pool.map(_node_proxy, tasks, [max_proxy_faces] * len(tasks), flags, pts,
                                   [bounds] * len(tasks), masks, chunksize=chunk)
            for node, (p, f, err, stalled[node], fid, regen, drop) in zip(nodes, results):
                tree.fidelity[node] = fid
                tree.regenerated += regen
                tree.dropped += drop
                kids, objs = tree.children(node), tree.objects(node)
                box_lo = np.concatenate([tree.lo[kids], lo[objs], p[:, :3]]).min(axis=0)
                box_hi = np.concatenate([tree.hi[kids], hi[objs], p[:, :3]]).max(axis=0)
                if np.isnan(err):  # nothing left to draw: the whole subtree vanishes, an error of its extent
                    err = float(np.linalg.norm(box_hi - box_lo))
                child_err = max(tree.error[kids].max(initial=0.0), obj_err[objs].max(initial=0.0))
                tree.proxies[node] = Mesh(p, f)
                tree.lo[node], tree.hi[node] = box_lo, box_hi
                tree.error[node] = max(err, child_err) if points is not None else err + child_err
                done += 1
                if progress is not None:
                    progress(done, n_nodes)
    finally:
        if pool is not None:
            pool.shutdown()
    return tree


def _node_proxy(parts: list[tuple[np.ndarray, np.ndarray]], max_faces: int, stalled: bool,
                points: np.ndarray | None = None, bounds: Bounds | None = None,
                objects_mask: Sequence[bool] | None = None) -> tuple:
    """One node's proxy from its children's meshes.

    Returns positions, faces, its own error (NaN when empty), stalled, and its measures
    (``Fidelity`` against the merged children, or None), regenerated, dropped.
    With ``bounds`` the candidates, in ladder order, are the parts' LoD1 boxes merged (objects'
    parts; ``objects_mask`` tells them from child proxies), a 2.5-D footprint set
    (``footprints``) and merge-and-decimate; the first within the bounds and the face limit is
    kept (a later one: regenerated); when none passes the best stays and is counted (dropped).
    The error is measured from ``points`` (the subtree's full-detail vertices) when given.
    """
    if not parts:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), 0.0, False, None, 0, 0
    objects_mask = [True] * len(parts) if objects_mask is None else list(objects_mask)
    pos, fac = _merge(parts)
    limit = min(fac.shape[0] // 2, max_faces)
    target = pos if points is None or len(points) == 0 else points
    if bounds is None:
        p, f, stalled = _simplify(pos, fac, limit, stalled)
        if f.shape[0] == 0:
            return p, f, float("nan"), stalled, None, 0, 0
        return p, f, geometric_error(target, p, f, samples=ERROR_SAMPLES), stalled, None, 0, 0
    ref = reference(pos, fac)
    regenerated = dropped = 0
    best = None
    for k, method in enumerate(("blocks", "footprint", "decimate")):
        if method == "blocks":  # every part's LoD1 box, merged (a part already a proxy stays)
            made = [blocks.oriented_box(p_, f_) if n_obj else None for (p_, f_), n_obj in zip(parts, objects_mask)]
            p, f = _merge([m if m is not None else part for m, part in zip(made, parts)])
        elif method == "footprint":
            p, f = footprint_proxy(pos, fac, limit)
        else:
            p, f, stalled = _simplify(pos, fac, limit, stalled)
        if f.shape[0] == 0 or f.shape[0] > limit:
            continue
        err = geometric_error(target, p, f, samples=ERROR_SAMPLES)
        fid = measure(ref, p, f, err, method, with_flip=False)
        ok = bounds.passes(fid, ref.closed)
        if ok:
            fid = measure(ref, p, f, err, method)
            ok = bounds.passes(fid, ref.closed)
        if best is None or (ok, fid.iou) > (best[0], best[4].iou):
            best = (ok, p, f, err, fid)
        if ok:
            regenerated = int(k > 0)
            break
    if best is None:
        return pos[:0], fac[:0], float("nan"), stalled, None, 0, 0
    ok, p, f, err, fid = best
    dropped = int(not ok)  # below the bounds: the best candidate stays, counted, with its measured error
    return p, f, err, stalled, fid, regenerated, dropped
