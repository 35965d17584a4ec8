"""The terrain quadtree: structure, errors, meshes, and crack-freedom where patches of any levels meet."""

from __future__ import annotations

import numpy as np
import pytest

from server.scene.data import data_file
from server.scene.importers.dem import load_dem
from server.scene.source import HeightGrid
from server.scene.terrain import build_quadtree, surface_deviation


def _synthetic() -> HeightGrid:
    rng = np.random.default_rng(7)
    r, c = np.mgrid[0:70, 0:53]
    h = 40 * np.sin(r / 9.0) * np.cos(c / 7.0) + 5 * rng.standard_normal(r.shape) + 0.3 * r
    h[:6, :9] = np.nan  # a void corner, one whole leaf of it
    h[30, 20] = np.nan
    return HeightGrid("synthetic", h, (1000.0, 2000.0), (2.0, 3.0))


@pytest.fixture(scope="module", params=["synthetic", "sthelens"])
def tree(request):
    if request.param == "synthetic":
        return build_quadtree(_synthetic(), patch=8)
    return build_quadtree(load_dem(data_file("terrain/SainteHelens.dem")).grids[0], patch=32)


def test_structure(tree):
    R, C = tree.grid.heights.shape
    assert tree.parent[0] == -1 and (tree.parent[1:] < np.arange(1, len(tree))).all()
    assert (tree.depth[1:] == tree.depth[tree.parent[1:]] + 1).all()
    assert (np.diff(tree.depth) >= 0).all()  # BFS
    assert tree.patch << tree.depth_max >= max(R, C) - 1 > tree.patch << (tree.depth_max - 1)
    assert tree.depth.max() == tree.depth_max
    assert tuple(tree.footprint[0]) == (0, 0, C - 1, R - 1)
    # children tile the parent: present quadrants match, absent ones are empty or void
    for p in range(len(tree)):
        if tree.depth[p] == tree.depth_max:
            assert (tree.children[p] == -1).all()
            continue
        c0, r0, c1, r1 = tree.footprint[p]
        half = (tree.patch << (tree.depth_max - tree.depth[p])) // 2
        cells = 0
        for q in range(4):
            di, dj = divmod(q, 2)
            e = (c0 + dj * half, r0 + di * half, min(c0 + (dj + 1) * half, C - 1), min(r0 + (di + 1) * half, R - 1))
            empty = e[0] >= C - 1 or e[1] >= R - 1
            if not empty:
                cells += (e[2] - e[0]) * (e[3] - e[1])
            k = tree.children[p, q]
            if k >= 0:
                assert tree.parent[k] == p and tuple(tree.footprint[k]) == e
            else:
                assert empty or tree.void[e[1]:e[3] + 1, e[0]:e[2] + 1].all()
        assert cells == (c1 - c0) * (r1 - r0)


def test_errors(tree):
    leaves = tree.depth == tree.depth_max
    assert (tree.error[leaves] == 0).all()
    assert (tree.error[1:] <= tree.error[tree.parent[1:]]).all()
    assert (tree.error >= tree.deviation).all() and tree.error[0] > 0
    assert (tree.skirt >= tree.error).all()
    assert (tree.lo[1:] >= tree.lo[tree.parent[1:]]).all() and (tree.hi[1:] <= tree.hi[tree.parent[1:]]).all()


def test_meshes(tree):
    for i in range(len(tree)):
        pos, faces = tree.mesh(i)
        assert np.isfinite(pos).all() and faces.min() >= 0 and faces.max() < len(pos)
        rows, cols = tree.samples(i)
        assert len(rows) <= tree.patch + 1 and len(cols) <= tree.patch + 1
        assert (pos >= tree.lo[i] - 1e-9).all() and (pos <= tree.hi[i] + 1e-9).all()
        top = faces[: 2 * (len(rows) - 1) * (len(cols) - 1)]
        a, b, c = pos[top[:, 0]], pos[top[:, 1]], pos[top[:, 2]]
        assert (np.cross(b - a, c - a)[:, 2] > 0).all()  # counter-clockwise from above


def test_deviation_matches_brute_force():
    tree = build_quadtree(_synthetic(), patch=8)
    g = tree.grid
    for i in range(min(len(tree), 12)):
        pos, faces = tree.mesh(i, skirt=False)
        c0, r0, c1, r1 = tree.footprint[i]
        rr, cc = np.mgrid[r0:r1 + 1, c0:c1 + 1]
        px = g.origin[0] + cc.ravel() * g.spacing[0]
        py = g.origin[1] + rr.ravel() * g.spacing[1]
        h = tree.filled[rr.ravel(), cc.ravel()]
        best = np.full(h.shape, np.inf)
        for f in faces:
            a, b, c = pos[f]
            m = np.array([[b[0] - a[0], c[0] - a[0]], [b[1] - a[1], c[1] - a[1]]])
            s, t = np.linalg.solve(m, np.vstack([px - a[0], py - a[1]]))
            inside = (s >= -1e-9) & (t >= -1e-9) & (s + t <= 1 + 1e-9)
            z = a[2] + s * (b[2] - a[2]) + t * (c[2] - a[2])
            best[inside] = np.minimum(best[inside], np.abs(z - h)[inside])
        assert np.isfinite(best).all()
        assert np.isclose(best.max(), tree.deviation[i], atol=1e-9)
    assert (surface_deviation(tree.filled, 1) == 0).all()


def _border(tree, i, axis, line, lo, hi):
    """Node i's surface vertices on the border line (axis 0: a column ``line``; 1: a row), within [lo, hi]."""
    rows, cols = tree.samples(i)
    pos = tree.mesh(i, skirt=False)[0].reshape(len(rows), len(cols), 3)
    if axis == 0:
        k = np.flatnonzero(cols == line)[0]
        along, pts = rows, pos[:, k]
    else:
        k = np.flatnonzero(rows == line)[0]
        along, pts = cols, pos[k]
    keep = (along >= lo) & (along <= hi)
    return along[keep], pts[keep], along, pts


def _neighbour_pairs(tree):
    fp = tree.footprint
    c0, r0, c1, r1 = fp.T
    pairs = []
    for a in range(len(tree)):
        east = np.flatnonzero((c0 == c1[a]) & (np.maximum(r0, r0[a]) < np.minimum(r1, r1[a])))
        north = np.flatnonzero((r0 == r1[a]) & (np.maximum(c0, c0[a]) < np.minimum(c1, c1[a])))
        pairs += [(a, int(b), 0, int(c1[a]), max(r0[a], r0[b]), min(r1[a], r1[b])) for b in east]
        pairs += [(a, int(b), 1, int(r1[a]), max(c0[a], c0[b]), min(c1[a], c1[b])) for b in north]
    return pairs


def test_crack_free(tree):
    pairs = _neighbour_pairs(tree)
    mixed = same = 0
    for a, b, axis, line, lo, hi in pairs:
        coarse, fine = (a, b) if tree.depth[a] <= tree.depth[b] else (b, a)
        ca, cp, call, cpall = _border(tree, coarse, axis, line, lo, hi)
        fa, fpts, _, _ = _border(tree, fine, axis, line, lo, hi)
        # (a) every coarse border vertex is a fine border vertex, bit for bit
        k = np.searchsorted(fa, ca)
        assert (k < len(fa)).all() and (fa[k] == ca).all()
        assert (fpts[k] == cp).all()
        if tree.depth[a] == tree.depth[b]:
            same += 1
            assert np.array_equal(fa, ca) and np.array_equal(fpts, cp)
            continue
        mixed += 1
        # (b) the gap at every fine border vertex is covered by the higher patch's skirt
        zc = np.interp(fa, call, cpall[:, 2])
        gap = fpts[:, 2] - zc
        higher = np.where(gap > 0, fine, coarse)
        assert (np.abs(gap) <= tree.skirt[higher] + 1e-9).all()
        assert (np.abs(gap) <= np.minimum(tree.skirt[coarse], tree.skirt[fine]) + 1e-9).all()
    assert mixed > 0 and same > 0


def test_skirt_false_and_bad_input():
    t = build_quadtree(_synthetic(), patch=8, skirt=False)
    assert (t.skirt == 0).all()
    with pytest.raises(ValueError):
        build_quadtree(HeightGrid("x", np.full((4, 4), np.nan), (0, 0), (1, 1)))
    with pytest.raises(ValueError):
        build_quadtree(HeightGrid("x", np.zeros((1, 4)), (0, 0), (1, 1)))
    one = build_quadtree(HeightGrid("x", np.arange(9.0).reshape(3, 3), (0, 0), (1, 1)), patch=32)
    assert len(one) == 1 and one.error[0] == 0 and one.depth_max == 0
