"""Why a governed run's mean and std are what they are: each factor measured from its frames, and the checks say so."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from bench.report.checks import bound_mask, checks
from bench.report.figures import write_traces
from bench.report.governed import explain
from bench.report.results import run_at
from client.governor import NEAR

from tests.bench.test_report import synthetic_results

T = 50.0


def _frames(aim: np.ndarray, ratio: np.ndarray, free: np.ndarray, landing: float = 1.02,
            free_ms: float = 30.0) -> dict:
    """Frames of a governor that aimed at ``aim`` × T, predicted ``landing`` × the aim and measured ``ratio`` ×
    the prediction; the ``free`` ones drew everything offered at ``free_ms``."""
    n = aim.size
    pred = np.where(free, free_ms, landing * aim * T)
    ms = pred * ratio
    return {"t": (0.05 * np.arange(n)).tolist(), "time_ms": ms.tolist(), "seq": [1] * n,
            "governor_aim": aim.tolist(), "governor_predicted_ms": pred.tolist(),
            "governor_bound": (~free).tolist(), "triangles": (1e5 + 1e4 * np.arange(n)).tolist(),
            "reps": np.where(free, 90, 150).tolist(), "bytes": np.where(free, 20_000, 1_000).tolist()}


def test_each_factor_is_measured_from_the_frames():
    n = 400
    free = np.zeros(n, bool)
    free[::10] = True
    f = _frames(np.full(n, 0.8), np.ones(n), free)
    why = explain(f, np.ones(n, bool), T)
    assert why["frames"] == n
    assert why["aim"] == pytest.approx(0.8)
    assert why["landing"] == pytest.approx(1.02)
    assert why["measured_vs_predicted"] == pytest.approx(1.0)
    assert why["free"] == pytest.approx(0.1)
    assert why["free_mean"] == pytest.approx(30.0 / T)
    # the mean is what the factors make of it: held frames at aim × landing, free ones at their own
    assert why["mean"] == pytest.approx(0.9 * 0.8 * 1.02 + 0.1 * 30.0 / T)
    assert (why["free_draws"], why["held_draws"]) == (90, 150)
    assert why["free_bytes_s"] > why["held_bytes_s"]


def test_the_std_without_the_aims_movement_and_without_the_free_frames():
    n = 400
    aim = np.where(np.arange(n) < n // 2, 0.7, 0.9)  # two stretches: the aim stepped between them
    free = np.zeros(n, bool)
    free[50:60] = True
    why = explain(_frames(aim, np.ones(n), free, landing=1.0), np.ones(n, bool), T)
    assert why["std_ms"] > 5.0
    # Each held frame sits on its aim: with the aim held still and the free frames out, nothing is left.
    assert why["std_held_ms"] == pytest.approx(0.0, abs=1e-9)
    assert 0 < why["std_steady_ms"] < why["std_ms"]
    assert why["miss_ms"] == pytest.approx(0.0, abs=1e-9)


def test_the_aims_quantile_counts_only_frames_predicted_near_the_target():
    n = 400
    rng = np.random.default_rng(1)
    ratio = 1.0 + 0.05 * rng.standard_normal(n)
    free = np.zeros(n, bool)
    f = _frames(np.full(n, 0.8), ratio, free)
    base = explain(f, np.ones(n, bool), T)["ratio_p99"]
    # cheap frames (predicted far under the target) that stall do not teach the aim, nor this figure
    g = copy.deepcopy(f)
    cheap = np.arange(0, n, 7)
    pred = np.asarray(g["governor_predicted_ms"])
    pred[cheap] = 0.5 * NEAR * T
    ms = np.asarray(g["time_ms"])
    ms[cheap] = 10 * pred[cheap]
    g["governor_predicted_ms"], g["time_ms"] = pred.tolist(), ms.tolist()
    got = explain(g, np.ones(n, bool), T)["ratio_p99"]
    assert got < 1.3 and got == pytest.approx(base, rel=0.05)


def test_the_machines_scatter_comes_from_consecutive_frames_of_the_same_work():
    n = 2000
    rng = np.random.default_rng(2)
    per_frame = 0.05
    ratio = np.exp(per_frame * rng.standard_normal(n))
    f = _frames(np.full(n, 0.8), ratio, np.zeros(n, bool))
    f["triangles"] = [2e5] * n  # every frame the same work
    why = explain(f, np.ones(n, bool), T)
    mean_ms = why["mean"] * T
    assert why["machine_ms"] == pytest.approx(per_frame * mean_ms, rel=0.1)
    f["triangles"] = (1e5 * (1 + np.arange(n) % 2)).tolist()  # no two consecutive frames alike: not measured
    assert explain(f, np.ones(n, bool), T)["machine_ms"] is None


def test_a_run_without_the_governors_figures_is_not_explained():
    f = _frames(np.full(50, 0.8), np.ones(50), np.zeros(50, bool))
    for name in ("governor_aim", "governor_predicted_ms", "governor_bound"):
        g = {k: v for k, v in f.items() if k != name}
        assert explain(g, np.ones(50, bool), T) is None
    assert explain({**f, "governor_aim": [0.0] * 50}, np.ones(50, bool), T) is None  # ungoverned: aim 0
    assert explain(f, np.zeros(50, bool), T) is None  # no bound frames


def _governed(results: dict, aim: float, ratio_sd: float, free_every: int = 0, stretch: float = 0.0) -> dict:
    """``results`` with an optimization+gov run at the target whose frames carry the governor's figures."""
    out = copy.deepcopy(results)
    run = copy.deepcopy(run_at(results, "optimization", T))
    n = len(run["frames"]["t"])
    rng = np.random.default_rng(3)
    a = np.full(n, aim) + np.where(np.arange(n) < n // 2, -stretch, stretch)
    free = np.zeros(n, bool)
    if free_every:
        free[::free_every] = True
    f = _frames(a, 1.0 + ratio_sd * rng.standard_normal(n), free)
    f["t"] = run["frames"]["t"]
    run["frames"].update(f)
    run["governor"] = True
    ms = np.asarray(f["time_ms"])
    run["summary"].update(frame_mean_ms=float(ms.mean()), frame_std_ms=float(ms.std()),
                          frame_max_ms=float(ms.max()), frame_p99_ms=float(np.percentile(ms, 99)),
                          over_pct=float(100 * np.mean(ms > 1.1 * T)), flip_mean=0.01)
    out["runs"].append(run)
    return out


def _by_name(res: dict) -> dict:
    return {c["name"]: c for c in checks(res)}


def test_a_missed_mean_says_what_the_aim_was_and_why():
    res = _governed(synthetic_results(), aim=0.75, ratio_sd=0.02, free_every=10)
    gov = run_at(res, "optimization", T, governor=True)
    assert bound_mask(res, gov, T).sum() > 100
    c = _by_name(res)["governor_mean_bound"]
    assert c["passed"] is False
    assert c["why"]["aim"] == pytest.approx(0.75)
    assert "the governor aimed these frames at 0.750 × target" in c["line"]
    assert "in 10 % of them everything offered fitted under the aim" in c["line"]
    # a mean that passes carries its figures but no excuse
    ok = _by_name(_governed(synthetic_results(), aim=0.9, ratio_sd=0.01))["governor_mean_bound"]
    assert ok["passed"] is True and "why" in ok and "aimed these frames" not in ok["line"]


def test_a_missed_std_says_how_much_the_aims_movement_and_the_free_frames_add():
    res = _governed(synthetic_results(), aim=0.8, ratio_sd=0.01, free_every=6, stretch=0.15)
    c = _by_name(res)["opt_std_bound_vs_static"]
    assert c["passed"] is False, c["line"]
    why = c["why"]
    assert why["std_held_ms"] < why["std_steady_ms"] < why["std_ms"]
    assert f"with the aim held at its mean the std is {why['std_steady_ms']:.2f} ms" in c["line"]


def test_the_traces_draw_the_governors_aim(tmp_path):
    res = _governed(synthetic_results(), aim=0.8, ratio_sd=0.02)
    with_aim = write_traces(res, tmp_path / "a.png").read_bytes()
    gov = run_at(res, "optimization", T, governor=True)
    gov["frames"]["governor_aim"] = [0.0] * len(gov["frames"]["t"])
    without = write_traces(res, tmp_path / "b.png").read_bytes()
    assert with_aim != without
