"""The selection benchmark: its instances bite, its plain reference is the same greedy, its figures are whole."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bench.select import GOALS, instance, moved, reference_greedy, run


def _figures_finite(row: dict, keys) -> None:
    for key in keys:
        assert isinstance(row[key], (int, float)) and math.isfinite(row[key]), (key, row[key])


@given(n=st.integers(1, 400), levels=st.integers(1, 5), seed=st.integers(0, 2**16))
@settings(max_examples=30, deadline=None)
def test_instance_is_deterministic_and_its_budget_bites(n, levels, seed):
    cand, budget = instance(n, levels, seed)
    again, budget2 = instance(n, levels, seed)
    assert budget == budget2
    np.testing.assert_array_equal(cand.benefit, again.benefit)
    np.testing.assert_array_equal(cand.cost, again.cost)
    assert cand.benefit.shape == cand.cost.shape == (n, levels)
    if levels >= 2:
        assert cand.cost[:, -1].sum() > budget  # full detail does not fit: the knapsack bites
    assert cand.cost[:, 0].sum() <= budget  # the coarsest level of everything does
    assert (np.diff(cand.cost, axis=1) > 0).all() and (np.diff(cand.benefit, axis=1) > 0).all()
    assert (cand.benefit <= cand.size[:, None]).all()  # Size · Accuracy, accuracy < 1


def test_instances_differ_by_seed_and_sizes_are_heavy_tailed():
    a, _ = instance(20_000, 4, 0)
    b, _ = instance(20_000, 4, 1)
    assert not np.array_equal(a.benefit, b.benefit)
    size = a.size
    assert size.max() > 50 * np.median(size)  # log-normal: a few objects cover most pixels
    np.testing.assert_array_equal(a.faces[:, 1:] // a.faces[:, :-1], 4)


def test_a_camera_move_changes_sizes_a_little_and_keeps_the_previous_selection():
    cand, budget = instance(20_000, 4, 3)
    prev = np.random.default_rng(0).integers(-1, 4, cand.n)
    nxt = moved(cand, prev, seed=3)
    entered = (nxt.previous == -1) & (prev != -1)
    assert 0 < entered.sum() < 0.02 * cand.n  # a few objects enter (and as many leave)
    same = (nxt.previous == prev) & (prev >= 0)  # drawn before and still there
    ratio = nxt.size[same] / cand.size[same]
    assert 0.005 < np.std(np.log(ratio)) < 0.03
    np.testing.assert_array_equal(nxt.cost[same], cand.cost[same])  # costs of staying objects do not change


@given(n=st.integers(1, 60), levels=st.integers(1, 4), seed=st.integers(0, 2**16),
       fraction=st.floats(0.05, 0.9))
@settings(max_examples=40, deadline=None)
def test_reference_greedy_agrees_with_the_solvers_greedy(n, levels, seed, fraction):
    from server.select import solvers

    cand, budget = instance(n, levels, seed, fraction=fraction)
    level, cost, benefit = reference_greedy(cand.benefit, cand.cost, budget)
    assert cost <= budget * (1 + 1e-9)
    rows = np.flatnonzero(level >= 0)
    assert cost == pytest.approx(cand.cost[rows, level[rows]].sum(), rel=1e-9)
    assert benefit == pytest.approx(cand.benefit[rows, level[rows]].sum(), rel=1e-9)
    fast = solvers.get("greedy")(cand, budget)
    assert benefit == pytest.approx(fast.benefit, rel=1e-3)  # both greedy by value over the hull


def test_reference_greedy_takes_the_hull_and_the_best_single_option():
    # Object 0's middle option lies under the chord from (0, 0) to its last: the hull skips it.
    benefit = np.array([[1.0, 1.2, 4.0], [1.0, 1.1, 1.15]])
    cost = np.array([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0]])
    level, c, b = reference_greedy(benefit, cost, 4.0)
    assert level.tolist() == [2, 0] and (c, b) == (4.0, 5.0)
    # One valuable but dear option beats the greedy's cheap ones (the factor-two guarantee).
    level, c, b = reference_greedy(np.array([[1.0], [1.0], [10.0]]), np.array([[0.1], [0.1], [1.0]]), 1.0)
    assert level.tolist() == [-1, -1, 0] and b == 10.0


def test_run_returns_every_figure():
    result = run(sizes=[200], repeats=1)
    assert result["levels"] == 4 and result["repeats"] == 1
    (row,) = result["sizes"]
    _figures_finite(row, [
        "objects", "budget_s", "greedy_ms", "greedy_benefit", "coherent_ms", "coherent_cold_ms", "coherent_greedy_ms",
        "optimization_benefit", "lp_bound", "greedy_vs_lp", "optimization_vs_lp", "exact_benefit",
        "greedy_vs_exact", "optimization_vs_exact", "reference_ms", "reference_benefit", "speedup_vs_reference",
        "greedy_numpy_ms", "kernels_speedup",
    ])
    assert row["greedy_feasible"] and row["optimization_feasible"] and row["numpy_agrees"]
    assert result["kernels"] in ("numba", "numpy") and result["kernels_warm_s"] >= 0
    assert 0.5 <= row["greedy_vs_exact"] <= 1 + 1e-9 and 0.5 <= row["optimization_vs_exact"] <= 1 + 1e-9
    assert row["exact_benefit"] <= row["lp_bound"] * (1 + 1e-9)
    assert row["reference_benefit"] == pytest.approx(row["greedy_benefit"], rel=1e-3)
    assert [g["goal"] for g in result["goals"]] == [g[0] for g in GOALS]
    assert all(g["met"] is None for g in result["goals"])  # none of the goals' sizes was run
    assert any("greedy" in line for line in result["lines"])


def test_goals_are_judged_with_their_margin():
    result = run(sizes=[1000], repeats=1, reference_max=0)
    goal = next(g for g in result["goals"] if g["goal"] == "optimality_1k")
    row = result["sizes"][0]
    assert goal["value"] == row["greedy_vs_exact"]
    assert goal["met"] == (goal["value"] >= 0.99) and goal["margin"] == pytest.approx(goal["value"] - 0.99)
    assert row["reference_ms"] is None and row["speedup_vs_reference"] is None  # capped by reference_max
    json.dumps(result)  # everything is plain JSON


def test_cli_prints_the_figures_as_json():
    done = subprocess.run([sys.executable, "-m", "walkstream", "bench", "select", "--sizes", "300", "--repeats", "1",
                           "--json"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    figures = json.loads(done.stdout)  # stdout is the JSON alone: no solver banner before it
    (row,) = figures["sizes"]
    assert row["objects"] == 300 and "lines" not in figures
    _figures_finite(row, ["greedy_ms", "coherent_ms", "greedy_vs_exact", "greedy_vs_lp", "speedup_vs_reference"])
    assert "300 objects" in done.stderr and "goal optimality_1k" in done.stderr


def test_cli_rejects_bad_sizes():
    done = subprocess.run([sys.executable, "-m", "walkstream", "bench", "select", "--sizes", "ten"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "--sizes" in done.stderr
