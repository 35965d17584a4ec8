"""Selection: culling and screen size against hand-worked cases, the greedy knapsack's guarantees."""

from __future__ import annotations

import itertools

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from server.select.camera import View, cull_boxes, frustum_planes, screen_size, widened
from server.select.cost import CostModel
from server.select.selection import Levels, select
from server.select.solvers.candidates import Candidates
from server.select.solvers.greedy import solve

BOUNDS = np.array([[-100.0, -100.0, -10.0], [100.0, 100.0, 10.0]])


def _view(fov=60.0, w=640, h=360):
    # At the origin, looking along +y, z up.
    return View.of_pose([0, 0, 0], [0, 1, 0], [0, 0, 1], fov, (w, h), BOUNDS)


def test_culling_keeps_what_is_in_front_and_drops_what_is_behind_or_aside():
    lo = np.array([[-1, 9, -1], [-1, -11, -1], [50, 9, -1], [-1, 0.5, -1]], float)
    hi = lo + 2
    vis = cull_boxes(lo, hi, frustum_planes(_view().matrix()))
    assert vis.tolist() == [True, False, False, True]


def test_screen_size_matches_the_projection_of_a_facing_square():
    view = _view(fov=90.0, w=400, h=400)
    # A 2 × 2 square (thin box) 10 m ahead spans 2/(2·10) of the half-width: 0.1 of NDC's [-1, 1] per side.
    lo, hi = np.array([[-1, 10, -1]], float), np.array([[1, 10.001, 1]], float)
    size = screen_size(lo, hi, view.matrix(), view.width, view.height)
    expected = (0.2 * 200) ** 2  # 40 × 40 pixels
    assert abs(size[0] - expected) / expected < 0.01


def test_screen_size_is_clipped_to_the_viewport_and_full_when_the_box_surrounds_the_eye():
    view = _view(w=320, h=200)
    big = screen_size(np.array([[-500, 1, -500]], float), np.array([[500, 2, 500]], float), view.matrix(), 320, 200)
    around = screen_size(np.array([[-1, -1, -1]], float), np.array([[1, 1, 1]], float), view.matrix(), 320, 200)
    assert big[0] == 320 * 200 and around[0] == 320 * 200


def test_widening_keeps_pixel_density():
    view = _view()
    wide = widened(view, 20.0)
    lo, hi = np.array([[-0.2, 30, -0.2]], float), np.array([[0.2, 30.1, 0.2]], float)
    a = screen_size(lo, hi, view.matrix(), view.width, view.height)[0]
    b = screen_size(lo, hi, wide.matrix(), wide.width, wide.height)[0]
    assert abs(a - b) / a < 0.02
    side = np.array([[-33.0, 30, -0.2]]), np.array([[-32.0, 30.1, 0.2]])  # outside ±45.7° across, inside ±56°
    assert not cull_boxes(*side, frustum_planes(view.matrix()))[0]
    assert cull_boxes(*side, frustum_planes(wide.matrix()))[0]


# ----------------------------------------------------------------------------- greedy knapsack


def _instances(draw_n=st.integers(1, 40), draw_k=st.integers(1, 5)):
    @st.composite
    def inst(draw):
        n, k = draw(draw_n), draw(draw_k)
        inc_c = draw(arrays(np.float64, (n, k), elements=st.floats(1e-4, 1.0)))
        inc_b = draw(arrays(np.float64, (n, k), elements=st.floats(0.0, 1.0)))
        count = draw(arrays(np.int64, n, elements=st.integers(1, k)))
        budget = draw(st.floats(0.0, float(inc_c.sum()) * 1.1))
        valid = np.arange(k)[None, :] < count[:, None]
        return np.cumsum(inc_b, axis=1), np.cumsum(inc_c, axis=1), valid, budget

    return inst()


@settings(max_examples=400, deadline=None)
@given(_instances())
def test_greedy_never_exceeds_the_budget(inst):
    b, c, valid, budget = inst
    r = solve(Candidates.of(b, c, valid), budget)
    chosen = r.level >= 0
    assert (r.level < valid.sum(axis=1)).all()
    assert valid[chosen, r.level[chosen]].all()
    spent = c[chosen, r.level[chosen]].sum()
    assert spent <= budget * (1 + 1e-12) and abs(spent - r.cost) <= 1e-9 * max(1.0, spent)


@settings(max_examples=200, deadline=None)
@given(_instances(st.integers(1, 4), st.integers(1, 3)))
def test_greedy_reaches_at_least_half_the_optimum(inst):
    b, c, valid, budget = inst
    r = solve(Candidates.of(b, c, valid), budget)
    best = 0.0
    n, k = b.shape
    for choice in itertools.product(range(-1, k), repeat=n):
        picks = [(i, l) for i, l in enumerate(choice) if l >= 0]
        if any(not valid[i, l] for i, l in picks):
            continue
        if sum(c[i, l] for i, l in picks) <= budget:
            best = max(best, sum(b[i, l] for i, l in picks))
    assert r.benefit >= 0.5 * best - 1e-9


def test_greedy_prefers_value_and_fills_the_budget():
    b = np.array([[1.0, 1.5], [2.0, 2.2]])
    c = np.array([[1.0, 3.0], [1.0, 2.0]])
    r = solve(Candidates.of(b, c), budget=3.0)
    assert r.level.tolist() == [0, 1] and r.cost == 3.0  # the fill round takes object 1's finer level


def test_selection_draws_every_visible_object_before_refining_any():
    # Twenty objects ahead, two levels each; the budget allows all coarse levels and a few fine ones.
    n = 20
    lo = np.stack([np.linspace(-5, 5, n), np.full(n, 20.0), np.zeros(n)], axis=1)
    # 4 m boxes cover ~10⁴ pixels: more than the fine level's polygons, so refining gains accuracy (F&S
    # count at most one sample per pixel).
    levels = Levels(lo, lo + 4.0, np.arange(n) * 2, np.full(n, 2), np.tile([100, 1000], n), np.tile([60, 600], n))
    model = CostModel(c_vertex=1e-6)
    budget = model.c_vertex * (60 * n + 540 * 3)
    choice = select(levels, _view(), model, budget)
    assert choice.reps.size == n and choice.cost <= budget
    assert (choice.reps % 2 == 1).sum() == 3


def test_cost_model_moves_toward_measured_time_per_vertex():
    m = CostModel(c_vertex=1e-7, alpha=0.5)
    for _ in range(20):
        m.update(0.05, 100_000)  # 5e-7 s per vertex
    assert abs(m.c_vertex - 5e-7) < 1e-9
    assert not m.update(0.05, 10)  # too few vertices to say anything
    assert not m.update(float("nan"), 100_000)
