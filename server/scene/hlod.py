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

import numpy as np

from server.scene import blocks
from server.scene.fidelity import Bounds
from server.scene.lod import geometric_error
from server.scene.proxies import (DECIMATE_MAX_FACES, ERROR_SAMPLES, ProxyJob, merge, node_proxy, proxy_limit,
                                  simplify)
from server.scene.source import Mesh
from server.scene.workers import process_pool

__all__ = ["HLODTree", "build_hlod"]


@dataclass
class HLODTree:
    """Inner nodes 0..N-1 in BFS order (root 0) over n objects, as a structure of arrays.

    parent        : (N,) int32, -1 for the root; parent[i] < i
    depth         : (N,) int16, 0 at the root
    lo, hi        : (N, 3) float64 — box of the node's objects and of its proxy
    error         : (N,) float64 — geometric error of the proxy (metres), non-decreasing toward the
                    root; for a node not kept, the largest error under it
    proxies       : N meshes, the stand-ins of the subtrees (empty for a node not kept)
    object_parent : (n,) int32 — the (lowest) inner node each object hangs under
    fidelity      : per node, the proxy's measures (``Fidelity``) or None when unmeasured
    kept          : (N,) bool — the node has a proxy (guarded: one within the bounds)
    closed        : (N,) bool — guarded: the area bound applied to the node (its objects are closed)
    regenerated, dropped : proxies made by a later method of the ladder / nodes not kept

    The kept forest (what a store holds) links each kept node and each object to its nearest
    kept ancestor: ``kept_parent`` and ``kept_object_parent``.
    """

    parent: np.ndarray
    depth: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    error: np.ndarray
    proxies: list[Mesh]
    object_parent: np.ndarray
    fidelity: list = field(default_factory=list)
    kept: np.ndarray = field(default=None)  # type: ignore[assignment]
    closed: np.ndarray = field(default=None)  # type: ignore[assignment]
    regenerated: int = 0
    dropped: int = 0
    _child_start: np.ndarray = field(init=False, repr=False)
    _object_order: np.ndarray = field(init=False, repr=False)
    _object_start: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        n_nodes = self.parent.shape[0]
        if self.kept is None:
            self.kept = np.ones(n_nodes, bool)
        if self.closed is None:
            self.closed = np.zeros(n_nodes, bool)
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

    def _kept_ancestor(self) -> np.ndarray:
        """(N,) int64: each node's nearest kept ancestor, itself included (−1: none)."""
        up = np.full(self.n_nodes, -1, np.int64)
        for d in range(self.height):  # parents before children: one depth at a time
            at = np.flatnonzero(self.depth == d)
            above = np.where(self.parent[at] >= 0, up[np.maximum(self.parent[at], 0)], -1)
            up[at] = np.where(self.kept[at], at, above)
        return up

    def kept_parent(self) -> np.ndarray:
        """(N,) int64: each node's nearest kept proper ancestor (−1: none); parents before children."""
        up = self._kept_ancestor()
        return np.where(self.parent >= 0, up[np.maximum(self.parent, 0)], -1)

    def kept_object_parent(self) -> np.ndarray:
        """(n,) int64: each object's nearest kept ancestor node (−1: the object is a root)."""
        return self._kept_ancestor()[self.object_parent]

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
    boxes: Sequence[tuple[np.ndarray, np.ndarray] | None] | None = None,
    min_saving: float = 0.4,
) -> HLODTree:
    """Cluster n objects into an HLOD tree and build every inner node's proxy.

    lo, hi          : (n, 3) object boxes
    proxies         : n meshes, each object's stand-in inside its parent's merge
                      (the builder passes each object's coarsest level)
    fanout          : most inner-node children of an inner node (≥ 2)
    leaf_size       : most objects under a lowest inner node (≥ 1)
    max_proxy_faces : cap on a node proxy's faces; unguarded, a proxy also has at most
                      half the faces of its children's merged proxies
    object_error    : (n,) geometric error of each object's proxy, added into its
                      parent's error (zeros when omitted)
    progress        : called as progress(done, total) after each inner node
    workers         : processes building proxies (1: in this process); the result
                      does not depend on it
    points          : n arrays of each object's full-detail vertices (a subsample); a node's
                      error is then measured from its subtree's points to its proxy
    bounds          : choose each proxy among measured candidates within these bounds
                      (``proxies.node_proxy``); a node with none is not kept. None: merge
                      and decimate, unmeasured, every node kept
    boxes           : with bounds, n LoD1 boxes (``blocks.oriented_box`` of each object's
                      finest level; None where there is none)
    min_saving      : with bounds, a proxy saves at least this share of the cost (faces and
                      draws, ``proxies.proxy_limit``) of what it replaces in a cut: its kept
                      children's proxies (or what stands in for a child not kept) and its
                      objects' proxies

    Without ``points``, a node's error is the estimated Hausdorff distance from the merged
    children's vertices to its proxy plus the largest child error; with them it is measured
    from the subtree's full-detail points, and made no less than the errors under it.
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
    if bounds is not None:
        if boxes is None:
            boxes = [blocks.oriented_box(m.positions, m.faces) for m in proxies]
    stalled = np.zeros(n_nodes, bool)  # the node's proxy needed vertex clustering
    standing: list[list[Mesh]] = [[] for _ in range(n_nodes)]  # what a node not kept leaves in a cut
    pool = process_pool(workers) if workers > 1 else None
    done = 0
    try:
        # Bottom-up one depth at a time: the nodes of a depth are independent.
        for d in range(int(depth.max()), -1, -1):
            nodes = np.flatnonzero(depth == d)[::-1]
            tasks, flags, pts, parts_of = [], [], [], []
            for node in nodes:
                under = tree.leaves_under(node)
                pts.append(np.concatenate([np.zeros((0, 3))] + [points[o] for o in under])
                           if points is not None else None)
                parts = [m for k in tree.children(node)
                         for m in ([tree.proxies[k]] if tree.kept[k] else standing[k])]
                parts += [proxies[o] for o in tree.objects(node)]
                parts = [m for m in parts if m.n_faces > 0]
                parts_of.append(parts)
                if bounds is None:
                    flags.append(bool(stalled[tree.children(node)].any()))
                    tasks.append([(m.positions, m.faces) for m in parts])
                    continue
                faces = sum(m.n_faces for m in parts)
                tasks.append(ProxyJob(
                    objects=[(proxies[o].positions, proxies[o].faces) for o in under],
                    boxes=[boxes[o] for o in under],
                    parts=[(m.positions, m.faces) for m in parts] if faces <= DECIMATE_MAX_FACES else [],
                    points=pts[-1] if pts[-1] is not None else np.zeros((0, 3)),
                    limit=proxy_limit(faces, len(parts), min_saving, max_proxy_faces)))
            if bounds is None:
                args = (tasks, [max_proxy_faces] * len(tasks), flags, pts)
                fn = _merged_proxy
            else:
                args = (tasks, [bounds] * len(tasks))
                fn = node_proxy
            if pool is None:
                results = map(fn, *args)
            else:
                chunk = max(1, min(32, len(tasks) // (4 * workers)))
                results = pool.map(fn, *args, chunksize=chunk)
            for node, parts, out in zip(nodes, parts_of, results):
                if bounds is None:
                    p, f, err, stalled[node] = out
                else:
                    p, f, err = out.positions, out.faces, out.error
                    tree.fidelity[node] = out.fidelity
                    tree.closed[node] = out.closed
                    tree.regenerated += out.regenerated
                    if p is None:  # nothing passed: not kept, its parts stand in a cut
                        tree.kept[node] = False
                        tree.dropped += 1
                        standing[node] = parts
                        p, f = np.zeros((0, 3)), np.zeros((0, 3), np.int64)
                kids, objs = tree.children(node), tree.objects(node)
                box_lo = np.concatenate([tree.lo[kids], lo[objs], p[:, :3]]).min(axis=0)
                box_hi = np.concatenate([tree.hi[kids], hi[objs], p[:, :3]]).max(axis=0)
                child_err = max(tree.error[kids].max(initial=0.0), obj_err[objs].max(initial=0.0))
                if not tree.kept[node]:
                    err = 0.0  # its error is the largest under it, which its kept ancestors take on
                elif np.isnan(err):  # nothing left to draw: the whole subtree vanishes, an error of its extent
                    err = float(np.linalg.norm(box_hi - box_lo))
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


def _merged_proxy(parts: list[tuple[np.ndarray, np.ndarray]], max_faces: int, stalled: bool,
                  points: np.ndarray | None = None) -> tuple:
    """Unguarded: the children's meshes merged and decimated to half their faces (at most ``max_faces``).

    Returns positions, faces, its own error (NaN when empty) and whether decimation stalled. The
    error is measured from ``points`` (the subtree's full-detail vertices) when given.
    """
    if not parts:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), 0.0, False
    pos, fac = merge(parts)
    p, f, stalled = simplify(pos, fac, min(fac.shape[0] // 2, max_faces), stalled)
    if f.shape[0] == 0:
        return p, f, float("nan"), stalled
    target = pos if points is None or len(points) == 0 else points
    return p, f, geometric_error(target, p, f, samples=ERROR_SAMPLES), stalled
