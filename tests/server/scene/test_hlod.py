"""HLOD tree: every object covered once, boxes nest, limits hold, proxies shrink, error grows to the root."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from server.scene.fidelity import Bounds
from server.scene.hlod import build_hlod
from server.scene.source import Mesh


def _scene(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    centre = np.column_stack([rng.uniform(0, 400, (n, 2)), np.zeros(n)])
    size = rng.uniform(4, 12, (n, 3))
    base = trimesh.creation.icosphere(1)  # 80 faces: a proxy that decimates well
    proxies, lo, hi = [], [], []
    for c, s in zip(centre, size):
        p = base.vertices * s / 2 + c + [0, 0, s[2] / 2]
        proxies.append(Mesh(p, base.faces))
        lo.append(p.min(0))
        hi.append(p.max(0))
    return np.array(lo), np.array(hi), proxies


@pytest.fixture(scope="module")
def built():
    lo, hi, proxies = _scene(700)
    calls = []
    tree = build_hlod(lo, hi, proxies, fanout=4, leaf_size=6, max_proxy_faces=1500,
                      progress=lambda d, t: calls.append((d, t)))
    return lo, hi, proxies, tree, calls


def test_shape_and_order(built):
    lo, _, _, tree, calls = built
    n_nodes = tree.n_nodes
    assert tree.parent[0] == -1 and tree.depth[0] == 0
    assert np.all(tree.parent[1:] >= 0) and np.all(tree.parent[1:] < np.arange(1, n_nodes))  # parents first
    assert np.all(np.diff(tree.parent[1:]) >= 0)  # BFS: children contiguous, in parent order
    assert np.all(tree.depth[1:] == tree.depth[tree.parent[1:]] + 1)
    assert tree.height == int(tree.depth.max()) + 1 >= 3
    assert tree.lo.shape == tree.hi.shape == (n_nodes, 3) and tree.error.shape == (n_nodes,)
    assert len(tree.proxies) == n_nodes and tree.object_parent.shape == (lo.shape[0],)
    assert calls[-1] == (n_nodes, n_nodes) and len(calls) == n_nodes


def test_coverage(built):
    lo, _, _, tree, _ = built
    n = lo.shape[0]
    # Bottom-up: every object's parent chain reaches the root.
    for node in tree.object_parent:
        seen = 0
        while node != -1:
            node = tree.parent[node]
            seen += 1
            assert seen <= tree.n_nodes
    # Top-down: a traversal from the root reaches every object exactly once.
    reached = np.zeros(n, int)
    stack = [0]
    while stack:
        node = stack.pop()
        reached[tree.objects(node)] += 1
        stack.extend(tree.children(node).tolist())
    assert np.all(reached == 1)
    assert np.array_equal(tree.leaves_under(0), np.arange(n))
    for node in range(1, tree.n_nodes, 37):
        under = tree.leaves_under(node)
        anc = tree.object_parent[under]
        for _ in range(tree.height):
            anc = np.where((anc > node) & (anc != -1), tree.parent[np.maximum(anc, 0)], anc)
        assert np.all(anc == node)


def test_limits(built):
    lo, _, _, tree, _ = built
    for node in range(tree.n_nodes):
        kids, objs = tree.children(node), tree.objects(node)
        assert len(kids) <= 4 and len(objs) <= 6
        assert (len(kids) == 0) != (len(objs) == 0)  # a node holds inner nodes or objects, not both
        if len(kids):
            assert len(kids) >= 2


def test_boxes_nest(built):
    lo, hi, _, tree, _ = built
    for node in range(tree.n_nodes):
        kids, objs = tree.children(node), tree.objects(node)
        inner_lo = np.concatenate([tree.lo[kids], lo[objs]])
        inner_hi = np.concatenate([tree.hi[kids], hi[objs]])
        assert np.all(tree.lo[node] <= inner_lo.min(0)) and np.all(tree.hi[node] >= inner_hi.max(0))
        p = tree.proxies[node].positions
        if p.size:
            assert np.all(p.min(0) >= tree.lo[node]) and np.all(p.max(0) <= tree.hi[node])


def test_proxies_shrink_and_error_grows(built):
    _, _, proxies, tree, _ = built
    for node in range(tree.n_nodes):
        merged = sum(tree.proxies[k].n_faces for k in tree.children(node))
        merged += sum(proxies[o].n_faces for o in tree.objects(node))
        assert 0 < tree.proxies[node].n_faces <= min(merged // 2, 1500)
        f = tree.proxies[node].faces
        assert f.min() >= 0 and f.max() < tree.proxies[node].n_vertices
    assert np.all(tree.error >= 0)
    assert np.all(tree.error[tree.parent[1:]] >= tree.error[1:])
    assert tree.error[0] > 0


def test_deterministic():
    lo, hi, proxies = _scene(120, seed=5)
    a = build_hlod(lo, hi, proxies, fanout=3, leaf_size=4)
    b = build_hlod(lo, hi, proxies, fanout=3, leaf_size=4)
    for name in ("parent", "depth", "lo", "hi", "error", "object_parent"):
        assert np.array_equal(getattr(a, name), getattr(b, name))
    for pa, pb in zip(a.proxies, b.proxies):
        assert np.array_equal(pa.positions, pb.positions) and np.array_equal(pa.faces, pb.faces)


def test_small_and_errors():
    lo, hi, proxies = _scene(5)
    tree = build_hlod(lo, hi, proxies, leaf_size=8)
    assert tree.n_nodes == 1 and tree.height == 1 and np.all(tree.object_parent == 0)
    assert np.array_equal(tree.leaves_under(0), np.arange(5)) and tree.children(0).size == 0
    err = np.full(5, 0.25)
    assert build_hlod(lo, hi, proxies, object_error=err).error[0] >= 0.25
    with pytest.raises(ValueError):
        build_hlod(lo[:0], hi[:0], [])
    with pytest.raises(ValueError):
        build_hlod(lo, hi, proxies, fanout=1)


def test_many_tiny_parts_still_fit():
    """Quadric decimation stalls on thousands of small boxes; the proxy must still meet its cap."""
    rng = np.random.default_rng(1)
    box = trimesh.creation.box((2, 2, 3))
    c = rng.uniform(0, 500, (600, 3))
    proxies = [Mesh(box.vertices + x, box.faces) for x in c]
    tree = build_hlod(c - [1, 1, 1.5], c + [1, 1, 1.5], proxies, fanout=8, leaf_size=64, max_proxy_faces=200)
    assert all(p.n_faces <= 200 for p in tree.proxies)
    assert tree.proxies[0].n_faces > 0


def test_workers_give_the_same_tree():
    lo, hi, proxies = _scene(150, seed=2)
    a = build_hlod(lo, hi, proxies, fanout=4, leaf_size=4)
    b = build_hlod(lo, hi, proxies, fanout=4, leaf_size=4, workers=2)
    assert np.array_equal(a.error, b.error) and np.array_equal(a.lo, b.lo)
    assert all(np.array_equal(x.positions, y.positions) for x, y in zip(a.proxies, b.proxies))


def _walk_up(tree, node: int) -> int:
    """Nearest kept ancestor of ``node`` (itself included), by walking the parent links."""
    while node >= 0 and not tree.kept[node]:
        node = int(tree.parent[node])
    return node


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_kept_forest_links_to_the_nearest_kept_ancestor(seed) -> None:
    lo, hi, proxies = _scene(60, seed=seed % 7)
    tree = build_hlod(lo, hi, proxies, fanout=3, leaf_size=4)
    tree.kept = np.random.default_rng(seed).uniform(size=tree.n_nodes) < 0.5
    up, above = tree.kept_parent(), tree.kept_object_parent()
    for j in range(tree.n_nodes):
        assert up[j] == (-1 if tree.parent[j] < 0 else _walk_up(tree, int(tree.parent[j])))
        assert up[j] < j
    for o in range(tree.n_objects):
        assert above[o] == _walk_up(tree, int(tree.object_parent[o]))


def _guarded(bounds: Bounds, n: int = 120):
    lo, hi, proxies = _scene(n, seed=4)
    points = [m.positions for m in proxies]
    return proxies, build_hlod(lo, hi, proxies, fanout=4, leaf_size=6, bounds=bounds, points=points)


def test_guarded_proxies_pass_the_bounds_and_save_faces() -> None:
    bounds = Bounds()
    proxies, tree = _guarded(bounds)
    assert tree.kept.any()
    for node in range(tree.n_nodes):
        if not tree.kept[node]:
            assert tree.proxies[node].n_faces == 0 and tree.fidelity[node] is None
            continue
        assert bounds.passes(tree.fidelity[node], bool(tree.closed[node]))
        # what the node replaces in a cut: its kept children, or what stands in for the others
        stand = [k for k in range(tree.n_nodes) if tree.kept[k] and tree.kept_parent()[k] == node]
        replaced = sum(tree.proxies[k].n_faces for k in stand)
        replaced += sum(proxies[o].n_faces for o in np.flatnonzero(tree.kept_object_parent() == node))
        assert tree.proxies[node].n_faces <= 0.6 * replaced
    up = tree.kept_parent()
    linked = np.flatnonzero(tree.kept & (up >= 0))
    assert np.all(tree.error[up[linked]] >= tree.error[linked])  # error grows toward the roots
    assert tree.dropped == int((~tree.kept).sum())


def test_a_node_without_a_passing_proxy_is_not_kept() -> None:
    """Bounds nothing can meet: no node is kept and every object is a root of the kept forest."""
    _, tree = _guarded(Bounds(iou=1.01), n=40)
    assert not tree.kept.any() and tree.dropped == tree.n_nodes
    assert np.all(tree.kept_object_parent() == -1) and np.all(tree.kept_parent() == -1)
