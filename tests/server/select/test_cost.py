"""Cost: the online c_vertex feedback (Zach) and F&S's max-of-terms model and its fit to measured frames."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from server.select.cost import ALGORITHM_SCALE, CostModel


def test_online_feedback_is_unchanged():
    m = CostModel(c_vertex=1e-7, alpha=0.5)
    assert m.predict(np.array([10, 20])).tolist() == [1e-6, 2e-6]
    assert not m.update(1.0, 10) and not m.update(float("nan"), 10**6) and m.updates == 0
    assert m.update(0.3, 10**6) and m.c_vertex == pytest.approx(1e-7 + 0.5 * (3e-7 - 1e-7)) and m.updates == 1


def test_default_terms_are_the_vertex_model_and_follow_the_feedback():
    m = CostModel(c_vertex=1e-7)
    faces, verts, pix = np.array([[100, 400]]), np.array([[60, 250]]), np.array([[1e6]])
    np.testing.assert_allclose(m.predict_terms(faces, verts, pix, 0), m.predict(verts))
    np.testing.assert_allclose(m.predict_terms(faces, verts, pix, 2), 1e-7 * ALGORITHM_SCALE[2] * verts)
    m.update(5e-7 * 10**6, 10**6)
    np.testing.assert_allclose(m.predict_terms(faces, verts, pix, 0), m.predict(verts))


def test_cost_is_the_larger_of_geometry_and_fill_plus_the_draw():
    m = CostModel(c_poly=[1.0, 2.0], c_vert=[0.5, 1.0], c_pixel=[0.01, 0.1], c_draw=3.0, algorithms=2)
    faces = np.array([[10, 10, 20, 20], [1, 1, 2, 2]])
    verts = np.array([[4, 4, 8, 8], [1, 1, 1, 1]])
    pixels = np.array([[100.0], [1000.0]])
    alg = np.array([0, 1, 0, 1])
    got = m.predict_terms(faces, verts, pixels, alg)
    # Object 0 is geometry-bound: flat 10 + 2 = 12, lit 20 + 4 = 24, flat 20 + 4 = 24, lit 40 + 8 = 48.
    # Object 1 is fill-bound: flat max(1.5, 10) = 10, lit max(3, 100) = 100, flat max(2.5, 10), lit max(5, 100).
    np.testing.assert_allclose(got, np.array([[12, 24, 24, 48], [10, 100, 10, 100]]) + 3.0)
    assert m.predict_terms(faces, verts, pixels, np.tile(alg, (2, 1)), draws=0).shape == (2, 4)
    with pytest.raises(ValueError):
        m.predict_terms(faces, verts, pixels, 2)


@settings(max_examples=60, deadline=None)
@given(st.floats(0, 1e6), st.floats(0, 1e6), st.floats(0, 1e7), st.integers(0, 2))
def test_predicted_cost_is_at_least_each_term(p, v, pix, r):
    m = CostModel(c_poly=[1e-8, 2e-8, 3e-8], c_vert=[1e-7, 2e-7, 3e-7], c_pixel=[1e-8, 5e-9, 2e-8], c_draw=1e-5)
    t = m.predict_terms(p, v, pix, r)
    assert t >= m.c_poly[r] * p + m.c_vert[r] * v + 1e-5 - 1e-18
    assert t >= m.c_pixel[r] * pix + 1e-5 - 1e-18


def test_bad_coefficients_are_refused():
    for bad in ({"c_poly": [-1.0, 0, 0]}, {"c_pixel": [0.0, 0.0]}, {"c_vert": [float("nan")] * 3}, {"c_draw": -1.0}):
        with pytest.raises(ValueError):
            CostModel(**bad)


def _frames(rng, f, fill_share=0.4, noise=0.02):
    verts = rng.uniform(1e5, 2e6, f)
    faces = verts * rng.uniform(0.4, 1.6, f)
    # Fill-bound frames have many pixels for their geometry.
    pixels = np.where(rng.random(f) < fill_share, rng.uniform(2.0, 4.0, f), rng.uniform(0.05, 0.6, f)) * verts
    draws = rng.integers(20, 400, f).astype(float)
    return faces, verts, pixels, draws, noise


def test_fit_recovers_known_coefficients_from_noisy_frames():
    rng = np.random.default_rng(7)
    faces, verts, pixels, draws, noise = _frames(rng, 300)
    c1, c2, c3, c0 = 3e-8, 1.5e-7, 1e-7, 4e-5
    truth = np.maximum(c1 * faces + c2 * verts, c3 * pixels) + c0 * draws
    times = truth * (1 + rng.normal(0, noise, truth.size))
    m = CostModel()
    out = m.fit(faces, verts, pixels, draws, times)
    # The dominant terms within 5 %; C1 carries a sixth of the geometry time, so noise moves it more.
    np.testing.assert_allclose(m.c_vert, c2, rtol=0.05)
    np.testing.assert_allclose(m.c_pixel, c3, rtol=0.05)
    np.testing.assert_allclose(m.c_poly, c1, rtol=0.15)
    assert m.c_draw == pytest.approx(c0, rel=0.3)  # a small term: loosely determined, still found
    assert out["rms_relative"] < 1.5 * noise and 0.25 * 300 < out["fill_bound"] < 0.55 * 300
    pred = m.predict_terms(faces, verts, pixels, 0, draws)
    assert np.abs(pred / truth - 1).max() < 0.03


def test_fit_leaves_the_fill_term_at_zero_when_no_frame_is_fill_bound():
    rng = np.random.default_rng(8)
    faces, verts, pixels, draws, noise = _frames(rng, 200, fill_share=0.0)
    truth = 2e-8 * faces + 1e-7 * verts + 1e-5 * draws
    m = CostModel()
    out = m.fit(faces, verts, pixels, draws, truth * (1 + rng.normal(0, noise, truth.size)))
    assert (m.c_pixel == 0).all() and out["fill_bound"] == 0
    assert not any(t.startswith("c_pixel") for t in out["terms"])
    np.testing.assert_allclose(m.c_vert, 1e-7, rtol=0.05)


def test_fit_drops_a_geometry_term_the_frames_do_not_need():
    rng = np.random.default_rng(9)
    faces, verts, pixels, draws, noise = _frames(rng, 200, fill_share=0.0)
    truth = 1.2e-7 * verts  # the vertex model: no polygon term, no per-draw overhead
    m = CostModel()
    out = m.fit(faces, verts, pixels, draws, truth * (1 + rng.normal(0, noise, truth.size)))
    assert out["terms"] == ["c_vert[0]"]
    assert (m.c_poly == 0).all() and m.c_draw == 0.0
    np.testing.assert_allclose(m.c_vert, 1.2e-7, rtol=0.02)


def test_fit_of_one_algorithm_leaves_the_others_alone():
    rng = np.random.default_rng(10)
    faces, verts, pixels, draws, noise = _frames(rng, 150, fill_share=0.0)
    m = CostModel(c_vertex=1e-7)
    before = m.vertex_coefficients().copy()
    m.fit(faces, verts, pixels, draws, 3e-7 * verts * (1 + rng.normal(0, noise, 150)), algorithm=2)
    np.testing.assert_allclose(m.c_vert[:2], before[:2])
    np.testing.assert_allclose(m.c_vert[2], 3e-7, rtol=0.02)


def test_fit_with_sums_per_algorithm():
    rng = np.random.default_rng(11)
    f = 300
    verts = rng.uniform(1e4, 1e6, (f, 3))
    faces = verts * rng.uniform(0.4, 1.6, (f, 3))
    pixels = rng.uniform(1e4, 1e6, (f, 3))
    draws = rng.integers(20, 400, f).astype(float)
    c1, c2, c3 = np.array([3e-8, 5e-8, 7e-8]), np.array([1e-7, 1.5e-7, 2e-7]), np.array([1e-7, 2e-7, 3e-7])
    truth = np.maximum((c1 * faces + c2 * verts).sum(1), (c3 * pixels).sum(1)) + 2e-5 * draws
    m = CostModel()
    m.fit(faces, verts, pixels, draws, truth * (1 + rng.normal(0, 0.02, f)))
    np.testing.assert_allclose(m.c_vert, c2, rtol=0.1)
    np.testing.assert_allclose(m.c_pixel, c3, rtol=0.1)
    pred = np.maximum((m.c_poly * faces + m.c_vert * verts).sum(1), (m.c_pixel * pixels).sum(1)) + m.c_draw * draws
    assert np.abs(pred / truth - 1).max() < 0.05


def test_fit_refuses_bad_frames():
    with pytest.raises(ValueError):
        CostModel().fit([1.0, 2.0], [1.0, 2.0], [1.0, 2.0], [1.0, 1.0], [0.1, -1.0])
    with pytest.raises(ValueError):
        CostModel().fit(np.ones((4, 2)), np.ones((4, 2)), np.ones((4, 2)), np.ones(4), np.ones(4))
