"""Screen-space error accuracy: the stored geometric error projected to pixels, in numpy and in the kernel."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from server.select import kernels, options
from server.select.benefit import (
    DEFAULT_ACCURACY,
    BenefitFactors,
    algorithm_accuracy,
    benefit_matrix,
    projected_error,
    resolved_accuracy,
    screen_error_accuracy,
)


@pytest.fixture(scope="module")
def kern():
    kernels.use_kernels(True)
    yield kernels.compiled().view
    kernels.use_kernels(None)


def test_projected_error_on_hand_worked_values():
    # A box of diagonal 2 covering 200 px spans √400 = 20 px along its diagonal: an error of 0.5 spans 5 px.
    assert projected_error(np.array([[0.5, 0.0]]), np.array([200.0]), np.array([2.0])).tolist() == [[5.0, 0.0]]
    assert screen_error_accuracy(np.array([0.0, 1.0, 3.0])).tolist() == [1.0, 0.5, 0.25]


@settings(max_examples=60, deadline=None)
@given(st.floats(0, 1e3), st.floats(0, 1e3), st.floats(1, 1e7), st.floats(0.01, 1e3))
def test_accuracy_falls_with_error_and_with_screen_size(e1, e2, size, extent):
    lo, hi = sorted((e1, e2))
    a = screen_error_accuracy(projected_error(np.array([hi, lo]), np.array(size), np.array(extent)))
    assert 0.0 < a[0] <= a[1] <= 1.0
    nearer = screen_error_accuracy(projected_error(np.array(hi), np.array(size * 4), np.array(extent)))
    assert nearer <= a[0]


def test_detail_beyond_the_pixels_is_not_worthless():
    """An object whose levels all have more faces than it covers pixels: F&S's capped accuracy prices the
    levels alike, the screen-space error still pays for the finer ones while their error spans pixels."""
    size, faces = np.array([400.0]), np.array([[1000, 4000, 16000]])
    fs = algorithm_accuracy(size, faces)
    assert np.ptp(fs) == 0.0
    factors = BenefitFactors(accuracy="sse", focus=False, motion=False, hysteresis=False, importance=False)
    b = benefit_matrix(size, faces, factors=factors, error=np.array([[0.2, 0.05, 0.0]]), extent=np.array([4.0]))
    assert b[0, 0] < b[0, 1] < b[0, 2] == pytest.approx(400.0)


def test_auto_resolves_to_the_default_where_errors_are_known():
    f = BenefitFactors()
    assert resolved_accuracy(f, errors=True).accuracy == DEFAULT_ACCURACY == "sse"
    assert resolved_accuracy(f, hierarchical=True, errors=False).accuracy == "zach"
    assert resolved_accuracy(f).accuracy == "fs"


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 60), levels=st.integers(1, 4), r=st.integers(1, 3),
       hysteresis=st.booleans())
def test_kernel_screen_error_equals_the_numpy_path(kern, seed, n, levels, r, hysteresis):
    rng = np.random.default_rng(seed)
    cams = int(rng.integers(1, 4))
    k = levels * r
    faces = np.sort(rng.integers(1, 5_000, (n, levels)), axis=1).repeat(r, axis=1).astype(np.int32)
    vertices = (faces * rng.uniform(0.5, 1.5, faces.shape)).astype(np.int32)
    valid = np.arange(k)[None, :] < (rng.integers(1, levels + 1, n) * r)[:, None]
    error = np.sort(rng.uniform(0, 2, (n, levels)), axis=1)[:, ::-1].repeat(r, axis=1).copy()
    extent = rng.uniform(0.1, 50, n)
    size = rng.choice([0.0, 3.0, 400.0, 2e5], (cams, n)) * rng.uniform(0.5, 1.5, (cams, n))
    offset = rng.uniform(0, 1.2, (cams, n))
    speed = [rng.uniform(0, 3000, n) if j % 2 else None for j in range(cams)]
    weight = rng.uniform(0.05, 1.0, cams)
    previous = rng.integers(-1, k + 1, n)
    factors = BenefitFactors(accuracy="sse", hysteresis=hysteresis, algorithm_names=("flat", "lit", "textured")[:r])
    want = np.zeros((n, k))
    for j in range(cams):
        want += weight[j] * benefit_matrix(size[j], faces, algorithms=r, factors=factors, vertices=vertices,
                                           offset=offset[j], speed=speed[j], previous=previous, error=error,
                                           extent=extent)
    want = np.where(valid, want, 0.0)
    got = options.benefit_kernel(kern, size, offset, speed, weight, faces, vertices, valid, r, factors, None,
                                 None, previous, None, error, extent)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def test_views_of_an_index_carry_its_errors_unless_it_stores_none(demo_store):
    import dataclasses

    from server.scene.store import SceneStore
    from server.select.selection import Levels, Scene

    with SceneStore.open(demo_store) as store:
        index = store.index
    scene = Scene.of(index)
    assert scene.flat.rep_error is not None and scene.hierarchy.rep_error is not None
    last = index.rep_first + index.rep_count - 1
    coarse = np.setdiff1d(np.arange(index.n_representations), last)
    assert (scene.flat.rep_error[coarse] > 0).all()  # a coarser level is never as good as full detail
    blank = dataclasses.replace(index, rep_error=np.zeros_like(index.rep_error))
    assert Levels.of(blank).rep_error is None  # no errors measured: F&S's / Zach's accuracy, not "all perfect"
