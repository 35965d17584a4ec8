"""The selection's compiled kernels (projection, benefit) against the numpy reference they replace.

A session's selection runs ``kernels.view`` once numba is warm and the numpy
functions of ``camera`` and ``benefit`` before that (or with WALKSTREAM_NUMBA=0):
both must give the same sizes, offsets, speeds and benefits (up to rounding), and
so the same choices.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from proto.camera import far_plane, projection_matrix, view_matrix
from server.scene.store import SceneStore
from server.select import options
from server.select.benefit import BenefitFactors, benefit_matrix, importance
from server.select.camera import View, centre_offset, cull_boxes, screen_size, screen_speed, widened
from server.select.cost import CostModel
from server.select.selection import Interval, Memory, Scene, select
from server.select import kernels

BOUNDS = np.array([[-60.0, -60.0, -5.0], [60.0, 60.0, 30.0]])


@pytest.fixture(scope="module")
def kern():
    kernels.use_kernels(True)  # waits for the compile (or the cache)
    yield kernels.compiled().view
    kernels.use_kernels(None)


def _boxes(seed: int, n: int, dtype=np.float32):
    rng = np.random.default_rng(seed)
    lo = rng.uniform(-50, 50, (n, 3))
    lo[:, 2] = rng.uniform(-3, 10, n)
    hi = lo + rng.uniform(0.05, 15, (n, 3))
    return lo.astype(dtype), hi.astype(dtype)


def _view(seed: int, fov: float = 60.0) -> View:
    rng = np.random.default_rng(seed + 1000)
    eye = rng.uniform(-40, 40, 3)
    eye[2] = rng.uniform(1, 20)
    forward = rng.normal(size=3) * 20 - eye  # roughly towards the boxes, so that some are in view
    return View.of_pose(eye, forward, [0, 0, 1.0], fov, (640, 360), BOUNDS)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 300), cams=st.integers(1, 4), dt=st.floats(0.05, 2.0),
       box64=st.booleans())
def test_project_equals_the_numpy_camera_functions(kern, seed, n, cams, dt, box64):
    _project_as_numpy(kern, seed, n, cams, dt, box64)


def test_the_projection_examples_hold_culled_and_sized_boxes(kern):
    """What the property test compares includes both kinds of box (one random camera may see none)."""
    sizes = np.concatenate([_project_as_numpy(kern, seed, 300, 2, 0.5, False).ravel() for seed in range(8)])
    assert (sizes == 0).any() and (sizes > 0).any()


def _project_as_numpy(kern, seed, n, cams, dt, box64) -> np.ndarray:
    """``project``'s outputs checked against the numpy camera functions; its sizes."""
    lo, hi = _boxes(seed, n, np.float64 if box64 else np.float32)
    views = [widened(_view(seed + j, 40.0 + 30 * j), 10.0) for j in range(cams)]
    before = _view(seed + 77).matrix()
    rows = np.random.default_rng(seed).permutation(n)[: max(1, n // 2)].astype(np.int64)
    clips = np.stack([v.matrix() for v in views])
    planes = np.stack([v.planes() for v in views])
    wd = np.array([v.width for v in views], float)
    ht = np.array([v.height for v in views], float)
    size, offset, moved = (np.empty((cams, rows.size)) for _ in range(3))
    kern.project(lo, hi, rows, clips, planes, wd, ht, True, before, True, size, offset, moved)
    l, h = lo[rows], hi[rows]
    for j, v in enumerate(views):
        want = np.where(cull_boxes(l, h, v.planes()), screen_size(l, h, v.matrix(), v.width, v.height), 0.0)
        np.testing.assert_allclose(size[j], want, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(offset[j], centre_offset(l, h, v.matrix(), v.width, v.height), rtol=1e-12,
                                   atol=1e-12)
        speed = screen_speed(l, h, v.matrix(), before, dt, v.width, v.height)
        np.testing.assert_allclose(moved[j] / dt, speed, rtol=1e-10, atol=1e-7)
    return size


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 80), levels=st.integers(1, 5), r=st.integers(1, 3),
       accuracy=st.sampled_from(["fs", "zach", "off"]), size_on=st.booleans(), focus=st.booleans(),
       motion=st.sampled_from(["all", "some", "none"]), hysteresis=st.booleans(), imp=st.booleans())
def test_benefit_sum_equals_the_weighted_benefit_matrices(kern, seed, n, levels, r, accuracy, size_on, focus, motion,
                                                           hysteresis, imp):
    rng = np.random.default_rng(seed)
    cams = int(rng.integers(1, 5))
    k = levels * r
    faces = np.sort(rng.integers(1, 20_000, (n, levels)), axis=1).repeat(r, axis=1).astype(np.int32)
    vertices = (faces * rng.uniform(0.5, 1.5, faces.shape)).astype(np.int32)
    valid = np.arange(k)[None, :] < (rng.integers(1, levels + 1, n) * r)[:, None]
    size = rng.choice([0.0, 0.5, 3.0, 400.0, 2e5], (cams, n)) * rng.uniform(0.5, 1.5, (cams, n))
    offset = rng.uniform(0, 1.2, (cams, n))
    speed = [rng.uniform(0, 3000, n) if (motion == "all" or (motion == "some" and j % 2)) else None
             for j in range(cams)]
    weight = rng.uniform(0.05, 1.0, cams)
    klass = rng.integers(-1, 4, n)
    table = np.array([1.0, 0.5, 0.25])
    previous = rng.integers(-1, k + 1, n)
    names = ("flat", "lit", "textured")[:r]
    factors = BenefitFactors(size=size_on, accuracy=accuracy, focus=focus, hysteresis=hysteresis, importance=imp,
                             algorithm_names=names)
    want = np.zeros((n, k))
    for j in range(cams):
        want += weight[j] * benefit_matrix(size[j], faces, algorithms=r, factors=factors, vertices=vertices,
                                           object_class=klass, importance_table=table, offset=offset[j],
                                           speed=speed[j], previous=previous)
    want = np.where(valid, want, 0.0)
    got = options.benefit_kernel(kern, size, offset, speed, weight, faces, vertices, valid, r, factors, klass,
                                 table, previous)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    if imp and klass.size:
        assert importance(klass, table).shape == (n,)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 60), levels=st.integers(1, 4), r=st.integers(1, 3),
       hysteresis=st.booleans())
def test_benefit_sum_with_original_faces_equals_the_numpy_path(kern, seed, n, levels, r, hysteresis):
    """Zach's accuracy with a hierarchy's #originalFaces (a subtree's, more than the row's own faces)."""
    rng = np.random.default_rng(seed)
    cams = int(rng.integers(1, 4))
    k = levels * r
    faces = np.sort(rng.integers(1, 5_000, (n, levels)), axis=1).repeat(r, axis=1).astype(np.int32)
    vertices = (faces * rng.uniform(0.5, 1.5, faces.shape)).astype(np.int32)
    valid = np.arange(k)[None, :] < (rng.integers(1, levels + 1, n) * r)[:, None]
    original = faces.max(axis=1) * rng.choice([1.0, 3.0, 40.0], n)
    size = rng.choice([0.0, 3.0, 400.0, 2e5], (cams, n)) * rng.uniform(0.5, 1.5, (cams, n))
    offset = rng.uniform(0, 1.2, (cams, n))
    speed = [rng.uniform(0, 3000, n) if j % 2 else None for j in range(cams)]
    weight = rng.uniform(0.05, 1.0, cams)
    previous = rng.integers(-1, k + 1, n)
    factors = BenefitFactors(accuracy="zach", hysteresis=hysteresis, algorithm_names=("flat", "lit", "textured")[:r])
    want = np.zeros((n, k))
    for j in range(cams):
        want += weight[j] * benefit_matrix(size[j], faces, algorithms=r, factors=factors, vertices=vertices,
                                           original_faces=original, offset=offset[j], speed=speed[j],
                                           previous=previous)
    want = np.where(valid, want, 0.0)
    got = options.benefit_kernel(kern, size, offset, speed, weight, faces, vertices, valid, r, factors, None,
                                 None, previous, original)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    # The original faces are really read: a node of 1,000 faces standing for 40,000, over 10⁵ pixels.
    one = options.benefit_kernel(kern, np.array([[1e5]]), np.zeros((1, 1)), [None], np.ones(1),
                                 np.array([[1000]]), np.array([[600]]), np.ones((1, 1), bool), 1,
                                 BenefitFactors(accuracy="zach", focus=False), None, None, None,
                                 np.array([40_000.0]))
    assert one[0, 0] == pytest.approx(1e5 * 1000 / 40_000)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 300), st.integers(1, 6), st.integers(1, 3), st.booleans())
def test_tuple_cost_equals_predict_terms(kern, seed, n, levels, r, int32):
    """The kernel prices each valid option as ``predict_terms`` does, to the bit, and invalid ones at inf."""
    rng = np.random.default_rng(seed)
    model = CostModel(algorithms=r, c_poly=rng.uniform(0, 1e-7, r) * (rng.random(r) < 0.7),
                      c_vert=rng.uniform(0, 1e-6, r), c_pixel=rng.uniform(0, 1e-8, r) * (rng.random(r) < 0.7),
                      c_draw=float(rng.uniform(0, 1e-5)))
    k = levels * r
    dtype = np.int32 if int32 else np.int64
    faces = rng.integers(0, 200_000, (n, k)).astype(dtype)
    vertices = (faces * rng.uniform(0.4, 1.2, (n, k))).astype(dtype)
    valid = rng.random((n, k)) < 0.6
    pixels = rng.uniform(0, 2e6, n) * (rng.random(n) < 0.9)
    alg = np.arange(k) % r
    want = np.where(valid, model.predict_terms(faces, vertices, pixels[:, None], alg[None, :], 1.0), np.inf)
    got = options._tuple_cost(model, faces, vertices, pixels, alg, valid, kern)
    assert np.array_equal(got, want)
    assert np.array_equal(options._tuple_cost(model, faces, vertices, pixels, alg, valid, None), want)


def test_the_view_matrix_is_protos_cached_and_read_only():
    rng = np.random.default_rng(5)
    for _ in range(200):
        eye, forward, up = rng.normal(size=3) * 50, rng.normal(size=3), rng.normal(size=3)
        bounds = np.sort(rng.normal(size=(2, 3)) * 100, axis=0)
        v = View.of_pose(eye, forward, up, rng.uniform(10, 150), (640, 360), bounds)
        assert v.far == far_plane(eye, bounds)  # the same far plane, to the bit
        want = projection_matrix(v.fov_y, v.aspect, 0.1, v.far) @ view_matrix(v.eye, v.forward, v.up)
        np.testing.assert_allclose(v.matrix(), want, rtol=0, atol=1e-13 * np.abs(want).max())
    m = v.matrix()
    assert v.matrix() is m and v.planes() is v.planes()
    with pytest.raises(ValueError):
        m[0, 0] = 1.0  # shared by every caller: read-only


def _tour_views(index, steps: int):
    c = np.asarray(index.bounds).mean(axis=0)
    r = 0.6 * float(np.ptp(np.asarray(index.bounds)[:, :2], axis=0).max())
    out = []
    for i in range(steps):
        a = 0.35 * i
        eye = c + [r * np.cos(a), r * np.sin(a), 15.0]
        views = tuple(View.of_pose(eye + [0, 0, 0.5 * s], c - eye + [3 * s, 0, 0], [0, 0, 1.0], 60.0, (640, 360),
                                   index.bounds) for s in range(3))
        wide = View.of_pose(eye - 10 * (c - eye) / np.linalg.norm(c - eye), c - eye, [0, 0, 1.0], 100.0, (640, 360),
                            index.bounds)
        out.append(Interval(views, wide, 0.1, (0.5 * i + 0.1, 0.5 * i + 0.2, 0.5 * i + 0.3)))
    return out


@pytest.mark.parametrize("solver,algorithms", [("greedy", (0,)), ("greedy", (0, 1, 2)), ("hierarchical", (0,))])
def test_kernels_and_numpy_choose_alike_over_a_walk(kern, denhaag_store, solver, algorithms):
    with SceneStore.open(denhaag_store) as store:
        index = store.index
        scene = Scene.of(index, np.ones(len(index.class_names)))
        cost = CostModel(c_vertex=2e-7)
        walk = _tour_views(index, 8)
        runs = []
        for compiled in (True, False):
            kernels.use_kernels(compiled)
            memory, choices = Memory(), []
            for i, view in enumerate(walk):
                choices.append(select(scene, view, cost, 0.01, solver, 0.0, memory=memory, t=0.5 * i + 0.1,
                                      algorithms=algorithms))
            runs.append(choices)
        kernels.use_kernels(True)
    drawn = 0
    for a, b in zip(*runs):
        assert a.reps.tolist() == b.reps.tolist()
        assert a.cost == pytest.approx(b.cost, rel=1e-9) and a.benefit == pytest.approx(b.benefit, rel=1e-9)
        drawn += a.reps.size
    assert drawn > 0


def test_the_hot_path_uses_the_kernels_and_is_fast(kern, denhaag_store, monkeypatch):
    """With the kernels warm no per-camera numpy pass runs, and a selection takes a few ms, not tens."""
    with SceneStore.open(denhaag_store) as store:
        index = store.index
        scene = Scene.of(index, np.ones(len(index.class_names)))
        cost = CostModel(c_vertex=2e-7)
        walk = _tour_views(index, 12)

        def numpy_pass(*a, **k):
            raise AssertionError("the numpy reference ran on the hot path")

        for name in ("screen_size", "centre_offset", "screen_speed", "cull_boxes", "benefit_matrix"):
            monkeypatch.setattr(options, name, numpy_pass)
        memory, cpu = Memory(), []
        for i, view in enumerate(walk):
            c0 = time.thread_time()
            select(scene, view, cost, 0.01, "greedy", 0.0, memory=memory, t=0.5 * i + 0.1)
            cpu.append(time.thread_time() - c0)
    # Thread CPU time, so other work on the machine does not count; before the kernels this was ~25 ms at
    # 2,340 objects (here fewer); now ~2 ms. The bound only catches a fall back to per-camera numpy.
    assert float(np.median(cpu[2:])) < 0.015
