"""Benefit: F&S's factors one by one, their product, Zach's accuracy, and the old skeleton API."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from server.select.benefit import (
    MIN_FACTOR,
    BenefitFactors,
    accuracy,
    algorithm_accuracy,
    benefit,
    benefit_matrix,
    focus,
    hysteresis,
    importance,
    importance_table,
    motion,
    original_faces,
    resolved_accuracy,
    zach_accuracy,
)

unit = st.floats(0, 1)
nonneg = st.floats(0, 1e6)
strength = st.floats(0, 50)


def test_old_api_is_size_times_flat_accuracy():
    assert accuracy(np.array([1, 2, 10])).tolist() == [0.5, 0.75, 0.95]
    assert accuracy(np.array([2.0]), m=2.0)[0] == 1 - 0.5 / 4
    np.testing.assert_allclose(benefit(np.array([100.0, 10.0]), np.array([1, 10])), [50.0, 9.5])


def test_accuracy_per_algorithm_counts_faces_for_flat_and_vertices_squared_for_lit():
    size = np.array([1000.0, 3.0])
    faces = np.array([[10, 10, 40, 40], [10, 10, 40, 40]])
    verts = np.array([[8, 8, 30, 30], [8, 8, 30, 30]])
    acc = algorithm_accuracy(size, faces, verts, algorithms=2)  # options: (L0 flat, L0 lit, L1 flat, L1 lit)
    np.testing.assert_allclose(acc[0], [1 - 0.5 / 10, 1 - 0.5 / 64, 1 - 0.5 / 40, 1 - 0.5 / 900])
    # Samples never exceed the pixels covered: a 3-pixel object gets 3 samples whatever the level.
    np.testing.assert_allclose(acc[1], [1 - 0.5 / 3, 1 - 0.5 / 9, 1 - 0.5 / 3, 1 - 0.5 / 9])


def test_zach_accuracy_on_hand_worked_values():
    # S = 1000 px, 10 000 original faces, 100 faces: max(1, 0.1) / max(1, 10) = 0.1
    assert zach_accuracy(1000.0, 100, 10_000) == pytest.approx(0.1)
    # At least one face per pixel: as good as the original.
    assert zach_accuracy(1000.0, 2000, 10_000) == 1.0
    # S = 20 000: max(1, 2) / max(1, 4) = 0.5
    assert zach_accuracy(20_000.0, 5000, 10_000) == pytest.approx(0.5)


@settings(max_examples=80, deadline=None)
@given(st.floats(1, 1e7), st.integers(1, 10**6), st.integers(1, 10**6))
def test_zach_accuracy_in_unit_interval_and_rising_with_faces(s, f, extra):
    orig = f + extra
    a, b = zach_accuracy(s, f, orig), zach_accuracy(s, orig, orig)
    assert 0 < a <= b == 1.0


def test_importance_looks_up_class_weights():
    table = importance_table(["wall", "pencil", "chair"], {"pencil": 0.2, "chair": 0.5})
    assert table.tolist() == [1.0, 0.2, 0.5]
    assert importance(np.array([0, 1, 2, -1, 7]), table).tolist() == [1.0, 0.2, 0.5, 1.0, 1.0]
    with pytest.raises(ValueError):
        importance_table(["a"], {"a": 1.5})
    with pytest.raises(ValueError):
        importance(np.array([0]), np.array([0.0]))


@settings(max_examples=100, deadline=None)
@given(unit, unit, strength)
def test_focus_in_unit_interval_and_falling_with_offset(a, b, s):
    lo, hi = sorted((a, b))
    fl, fh = focus(np.array([lo, hi]), s)
    assert MIN_FACTOR <= fh <= fl <= 1.0
    assert focus(np.array([0.0]), s)[0] == 1.0
    if 1e-6 < s < 1 and hi - lo > 1e-6:
        assert fh < fl


@settings(max_examples=100, deadline=None)
@given(nonneg, nonneg, st.floats(1, 1e5), st.floats(0.01, 50))
def test_motion_in_unit_interval_falling_with_speed_rising_with_polygon_size(a, b, poly, s):
    lo, hi = sorted((a, b))
    slow, fast = motion(np.array([lo, hi]), poly, s)
    assert 0 < fast <= slow <= 1.0
    assert motion(np.array([0.0]), poly, s)[0] == 1.0
    if hi - lo > 1e-3:
        assert fast < slow
    assert motion(hi, 4 * poly, s) >= fast


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 3), st.integers(1, 6), st.data())
def test_hysteresis_is_one_at_the_previous_tuple_and_falls_with_distance_in_level(r, levels, data):
    k = r * levels
    n = data.draw(st.integers(1, 8))
    prev = np.array(data.draw(st.lists(st.integers(-1, k - 1), min_size=n, max_size=n)))
    lw, aw = data.draw(st.floats(0.01, 5)), data.draw(st.floats(0.01, 5))
    h = hysteresis(np.arange(k), prev, r, lw, aw)
    assert h.shape == (n, k) and ((h > 0) & (h <= 1)).all()
    drawn = prev >= 0
    assert (h[~drawn] == 1).all()
    assert (h[np.flatnonzero(drawn), prev[drawn]] == 1).all()
    # Same algorithm as before: the further the level, the lower.
    for i in np.flatnonzero(drawn):
        same = np.arange(prev[i] % r, k, r)
        dist = np.abs(same // r - prev[i] // r)
        order = np.argsort(dist, kind="stable")
        assert (np.diff(h[i, same][order]) <= 0).all()
        assert (h[i, same][dist > 0] < 1).all()


def test_factors_are_validated():
    for bad in ({"focus_strength": -1.0}, {"motion_strength": float("nan")}, {"level_weight": float("inf")},
                {"accuracy": "psnr"}, {"exponent": {"flat": -1.0, "lit": 2.0, "textured": 2.0}},
                {"exponent": {"flat": 1.0}}):
        with pytest.raises(ValueError):
            BenefitFactors(**bad)


def test_benefit_matrix_on_a_hand_worked_case():
    size = np.array([400.0, 100.0])
    faces = np.array([[10, 10, 100, 100], [4, 4, 16, 16]])
    verts = np.array([[6, 6, 60, 60], [3, 3, 10, 10]])
    table = np.array([1.0, 0.5])
    f = BenefitFactors(focus_strength=0.5, motion_strength=1.0, frame_time=0.1, level_weight=1.0, algorithm_weight=0.5)
    got = benefit_matrix(size, faces, algorithms=2, factors=f, vertices=verts, object_class=np.array([0, 1]),
                         importance_table=table, offset=np.array([0.0, 1.0]), speed=np.array([0.0, 50.0]),
                         previous=np.array([-1, 1]))
    # Object 0: size · accuracy only (no offset, no motion, no previous).
    acc0 = [1 - 0.5 / 10, 1 - 0.5 / 36, 1 - 0.5 / 100, 1 - 0.5 / 3600]
    np.testing.assert_allclose(got[0], 400 * np.array(acc0))
    # Object 1: importance 0.5, focus 1 − 0.5·1 = 0.5; motion (the object's, against its coarsest
    # level's polygons): 50 px/s · 0.1 s / √(100/4); previous = option 1 (level 0, lit): a change keeps
    # the share 1/(1 + |ΔL| + 0.5·|ΔR|) of the benefit it gains, and loses the rest more.
    acc1 = np.array([1 - 0.5 / 4, 1 - 0.5 / 9, 1 - 0.5 / 16, 1 - 0.5 / 100])
    blur = 5.0 / np.sqrt(100 / 4)
    raw = 100 * acc1 * 0.5 * 0.5 / (1 + blur)
    keep = 1 / (1 + np.array([0.5, 0.0, 1.5, 1.0]))
    np.testing.assert_allclose(got[1], raw - (1 - keep) * np.abs(raw - raw[1]))


def test_zach_mode_uses_the_finest_level_as_original():
    size = np.array([1000.0])
    faces = np.array([[100, 500, 2000]])
    got = benefit_matrix(size, faces, factors=BenefitFactors(accuracy="zach"))
    np.testing.assert_allclose(got[0], 1000 * np.array([0.1, 0.5, 1.0]))


def test_original_faces_of_a_node_are_its_subtree_leaves_finest_faces():
    #        0            rows: 0 root (HLOD), 1, 2 inner, 3..6 leaves; 7 a lone chain
    #      /   \
    #     1     2
    #    / \   / \
    #   3   4 5   6
    parent = np.array([-1, 0, 0, 1, 1, 2, 2, -1])
    finest = np.array([50, 30, 40, 1000, 2000, 3000, 4000, 700])
    got = original_faces(finest, parent)
    np.testing.assert_array_equal(got, [10_000, 3000, 7000, 1000, 2000, 3000, 4000, 700])
    # Rows need not come parents first; a chain (no hierarchy) is its finest level.
    order = np.array([6, 3, 7, 1, 0, 5, 2, 4])
    where = np.argsort(order)
    np.testing.assert_array_equal(original_faces(finest[order], np.where(parent[order] >= 0, where[parent[order]], -1)),
                                  got[order])
    np.testing.assert_array_equal(original_faces(finest), finest)
    # Never fewer than the node's own finest level.
    assert original_faces(np.array([5000, 10]), np.array([-1, 0]))[0] == 5000


def test_original_faces_rejects_bad_parents():
    with pytest.raises(ValueError, match="like finest"):
        original_faces(np.ones(3), np.array([-1, 0]))
    with pytest.raises(ValueError, match="−1"):
        original_faces(np.ones(2), np.array([-1, 5]))
    with pytest.raises(ValueError, match="cycle"):
        original_faces(np.ones(3), np.array([-1, 2, 1]))


def test_auto_accuracy_is_zach_on_the_hierarchy_and_fs_elsewhere_and_explicit_wins():
    auto = BenefitFactors()
    assert auto.accuracy == "auto"
    assert resolved_accuracy(auto, hierarchical=True).accuracy == "zach"
    assert resolved_accuracy(auto, hierarchical=False).accuracy == "fs"
    assert resolved_accuracy(auto, True) is resolved_accuracy(auto, True)  # kept, not rebuilt each τ
    for explicit in ("fs", "zach", "off"):
        f = BenefitFactors(accuracy=explicit)
        assert resolved_accuracy(f, True) is f and resolved_accuracy(f, False) is f
    size, faces = np.array([300.0, 5e4]), np.array([[10, 100, 1000], [20, 200, 2000]])
    np.testing.assert_array_equal(benefit_matrix(size, faces, factors=auto),
                                  benefit_matrix(size, faces, factors=BenefitFactors(accuracy="fs")))


def test_zach_mode_takes_given_original_faces():
    # A coarse node standing for 40k faces, seen over 100k pixels: its 1,000 faces are 2.5 % accurate.
    got = benefit_matrix(np.array([1e5]), np.array([[1000]]), factors=BenefitFactors(accuracy="zach"),
                         original_faces=np.array([40_000]))
    assert got[0, 0] == pytest.approx(1e5 * 1000 / 40_000)


def _inputs(draw, n, levels, r):
    k = levels * r
    size = draw(arrays(np.float64, n, elements=st.floats(1, 1e6)))
    faces = np.sort(draw(arrays(np.int64, (n, levels), elements=st.integers(1, 10**6))), axis=1)
    faces = np.repeat(faces, r, axis=1)
    return dict(
        size=size, faces=faces, algorithms=r,
        vertices=np.maximum(faces // 2, 1),
        object_class=draw(arrays(np.int64, n, elements=st.integers(-1, 3))),
        importance_table=np.array([1.0, 0.5, 0.25]),
        offset=draw(arrays(np.float64, n, elements=unit)),
        speed=draw(arrays(np.float64, n, elements=nonneg)),
        previous=draw(arrays(np.int64, n, elements=st.integers(-1, k - 1))),
    )


FACTORS = {"importance": ("object_class",), "focus": ("offset",), "motion": ("speed",), "hysteresis": ("previous",)}


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 6), st.integers(1, 4), st.integers(1, 3), st.sampled_from(sorted(FACTORS)), st.data())
def test_each_factor_is_a_multiplier_in_unit_interval_and_switching_it_off_removes_it(n, levels, r, name, data):
    kw = _inputs(data.draw, n, levels, r)
    full = benefit_matrix(**kw)
    base = benefit_matrix(**kw, factors=BenefitFactors(importance=False, focus=False, motion=False, hysteresis=False))
    assert full.shape == (n, levels * r) and (full > 0).all() and (full <= base * (1 + 1e-12)).all()
    off = benefit_matrix(**kw, factors=BenefitFactors(**{name: False}))
    missing = benefit_matrix(**{**kw, **{key: None for key in FACTORS[name]}})
    np.testing.assert_array_equal(off, missing)
    ratio = full / off
    assert ((ratio > 0) & (ratio <= 1 + 1e-12)).all()
    only = benefit_matrix(**kw, factors=BenefitFactors(**{f: f == name for f in FACTORS}))
    np.testing.assert_allclose(only / base, ratio, rtol=1e-9)


def test_size_and_accuracy_can_be_switched_off():
    size, faces = np.array([50.0]), np.array([[1, 4]])
    np.testing.assert_allclose(benefit_matrix(size, faces, factors=BenefitFactors(size=False)), [[0.5, 0.875]])
    np.testing.assert_allclose(benefit_matrix(size, faces, factors=BenefitFactors(accuracy="off")), [[50.0, 50.0]])
