"""Selection over (level, rendering algorithm) tuples and a cost with a fill term (F&S's O, L, R)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from server.select.camera import View
from server.select.cost import CostModel
from server.select.selection import Levels, Memory, select

BOUNDS = np.array([[-200.0, -10.0, -10.0], [200.0, 400.0, 10.0]])


def _view():
    return View.of_pose([0, 0, 0], [0, 1, 0], [0, 0, 1], 60.0, (640, 360), BOUNDS)


def _row(n: int, levels: int = 3, spacing: float = 6.0) -> Levels:
    """n boxes in a row ahead of the camera, each with ``levels`` levels doubling in size."""
    lo = np.stack([np.zeros(n), 8.0 + spacing * np.arange(n), np.zeros(n) - 1.0], axis=1)
    faces = np.tile(100 * 4 ** np.arange(levels), n)
    return Levels(lo, lo + 2.0, np.arange(n) * levels, np.full(n, levels), faces, faces // 2)


def test_one_algorithm_is_chosen_per_drawn_object_and_the_budget_holds():
    lv = _row(30)
    model = CostModel(c_vertex=1e-6)  # lit and textured cost 1.25× and 1.5× a flat vertex
    choice = select(lv, _view(), model, 0.01, "greedy", 0.0, algorithms=(0, 1, 2))
    assert choice.algorithm is not None and choice.algorithm.shape == choice.reps.shape
    assert set(choice.algorithm.tolist()) <= {0, 1, 2}
    recount = (model.vertex_coefficients()[choice.algorithm] * lv.rep_vertices[choice.reps]).sum()
    assert recount == pytest.approx(choice.cost, rel=1e-9)
    assert choice.cost <= 0.01 * (1 + 1e-9)
    # Lit shading's accuracy counts vertices squared (F&S, m = 2): worth its 25 % more somewhere.
    assert (choice.algorithm == 1).any()


def test_an_offered_subset_maps_back_to_protocol_indices():
    choice = select(_row(10), _view(), CostModel(c_vertex=1e-6), 0.01, "greedy", 0.0, algorithms=(0, 2))
    assert set(choice.algorithm.tolist()) <= {0, 2}
    flat = select(_row(10), _view(), CostModel(c_vertex=1e-6), 0.01, "greedy", 0.0)
    assert flat.algorithm is None  # flat alone: the delta says nothing


def test_a_fill_term_makes_near_objects_cost_more():
    lv = _row(2, levels=1, spacing=150.0)  # one near box, one far box, same geometry
    geometry_only = CostModel(c_vertex=1e-7)
    fill = CostModel(c_vertex=1e-7, c_pixel=[1e-6, 1e-6, 1e-6])
    # With a budget for one box's geometry plus a little, both fit without the fill term;
    # with it the near box's covered pixels cost more than the far one's.
    v = float(lv.rep_vertices[0])
    both = select(lv, _view(), geometry_only, 2.5 * v * 1e-7, "greedy", 0.0)
    assert both.reps.size == 2
    choice = select(lv, _view(), fill, 1e3, "greedy", 0.0)
    assert choice.pixels > 0
    near, far = select(_row(1, 1), _view(), fill, 1e3, "greedy", 0.0), choice
    assert near.cost > 0 and far.cost > near.cost  # two boxes cost more than the nearest alone
    assert choice.cost > 2 * v * 1e-7  # the fill term priced in: more than the geometry alone


@settings(max_examples=30, deadline=None)
@given(st.floats(1e-4, 0.05), st.sampled_from([(0,), (0, 1), (0, 1, 2), (1, 2)]), st.integers(1, 40))
def test_the_budget_is_never_exceeded_over_tuples(budget, algorithms, n):
    lv = _row(n)
    model = CostModel(c_vertex=1e-6, c_pixel=[2e-8, 3e-8, 5e-8])
    choice = select(lv, _view(), model, budget, "greedy", 0.0, algorithms=algorithms, memory=Memory())
    assert choice.cost <= budget * (1 + 1e-9)
    if choice.algorithm is not None:
        assert set(choice.algorithm.tolist()) <= set(algorithms)
