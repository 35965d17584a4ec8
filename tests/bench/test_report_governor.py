"""The governor's checks and the repeats in the report: median runs, spread, and each check at its limit."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from bench.report.checks import checks, quality_points
from bench.report.figures import write_traces
from bench.report.results import repeats_at, run_at
from bench.report.table import table1

from tests.bench.test_report import synthetic_results


def _with_governor(results: dict, scale: float = 1.0, flip: float = 0.03) -> dict:
    """Add an optimization+gov run at every budget: frames at ``scale`` × target, FLIP ``flip``."""
    out = copy.deepcopy(results)
    for run in [r for r in results["runs"] if r["method"] == "optimization"]:
        g = copy.deepcopy(run)
        b = float(g["target_ms"])
        n = len(g["frames"]["t"])
        ms = np.full(n, scale * b)
        g["frames"]["time_ms"] = ms.tolist()
        g["governor"] = True
        x = ms[np.asarray(g["frames"]["t"]) >= results["warmup_s"]]
        g["summary"].update(frame_mean_ms=float(x.mean()), frame_std_ms=0.0, frame_max_ms=float(x.max()),
                            frame_p99_ms=float(np.percentile(x, 99)), over_pct=float(100 * np.mean(x > 1.1 * b)),
                            flip_mean=flip)
        out["runs"].append(g)
    return out


def _by_name(res: dict) -> dict:
    return {c["name"]: c for c in checks(res)}


def test_governor_checks_pass_a_governor_that_holds_the_target():
    res = _with_governor(synthetic_results(), scale=0.95, flip=0.03)
    c = _by_name(res)
    for name in ("governor_mean_bound", "governor_p99", "governor_over", "governor_flip_ratio"):
        assert c[name]["passed"] is True, c[name]["line"]
    assert c["governor_mean_bound"]["value"] == pytest.approx(0.95)
    base = run_at(res, "optimization", 50.0)["summary"]["flip_mean"]
    assert c["governor_flip_ratio"]["value"] == pytest.approx(0.03 / base)
    # the bound std checks are Optimization with the governor's (a steady time: std 0)
    assert c["opt_std_bound_vs_static"]["passed"] is True and "optimization+gov" in c["opt_std_bound_vs_static"]["line"]


def test_the_flip_check_says_the_ratio_over_every_repeat_and_the_samples_it_lowers():
    res = _with_governor(synthetic_results(), scale=0.95)
    for run in res["runs"]:  # three samples each; the governed run lowers the first two, matches the third
        if run["method"] == "optimization":
            run["quality"]["flip"] = [0.02, 0.01, 0.04] if run.get("governor") else [0.04, 0.02, 0.04]
    c = _by_name(res)["governor_flip_ratio"]
    assert c["all_repeats"] == pytest.approx(0.07 / 0.10)
    assert (c["samples_lower"], c["samples_erring"]) == (2, 3)
    assert "over every repeat 0.700, the governed error lower in 2 of the 3 samples" in c["line"]
    assert c["value"] == pytest.approx(0.03 / run_at(res, "optimization", 50.0)["summary"]["flip_mean"])


def test_governor_checks_fail_where_it_misses_and_say_so():
    c = _by_name(_with_governor(synthetic_results(), scale=0.6, flip=0.049))
    assert c["governor_mean_bound"]["passed"] is False and "misses" in c["governor_mean_bound"]["line"]
    assert c["governor_flip_ratio"]["passed"] is False
    c = _by_name(_with_governor(synthetic_results(), scale=1.2))
    assert c["governor_p99"]["passed"] is False and c["governor_over"]["passed"] is False
    assert c["governor_over"]["value"] == pytest.approx(1.0)


def test_the_mean_check_names_the_ceiling_the_machines_scatter_sets():
    res = _with_governor(synthetic_results(), scale=0.8)
    run = run_at(res, "optimization", 50.0, governor=True)
    frames = run["frames"]
    n = len(frames["t"])
    frames["triangles"] = [100_000] * n  # the same work every frame, its time alternating 40 / 52 ms
    frames["time_ms"] = [40.0 if i % 2 else 52.0 for i in range(n)]
    c = _by_name(res)["governor_mean_bound"]
    noise = c["identical_work"]
    assert noise["pairs"] > 10 and noise["p99"] == pytest.approx(1.3)
    assert "at most about 0.85 ×" in c["line"] and "1.300 × apart" in c["line"]
    # frames whose work changes every frame say nothing of the machine
    frames["triangles"] = [100_000 if i % 2 else 120_000 for i in range(n)]
    c = _by_name(res)["governor_mean_bound"]
    assert c["identical_work"]["pairs"] == 0 and "apart" not in c["line"]


def test_the_flip_ratio_is_skipped_where_full_detail_never_exceeds_the_target():
    """Den Haag at 50 ms: full detail is cheaper than the target everywhere, both runs draw the whole scene and
    their FLIPs differ by sampling noise; the ratio is not a verdict on the governor there."""
    res = _with_governor(synthetic_results(), scale=0.95, flip=0.049)
    assert _by_name(res)["governor_flip_ratio"]["passed"] is False  # where full detail binds it counts
    for run in res["runs"]:
        if run["method"] == "none":
            run["frames"]["time_ms"] = [0.5 * float(run["target_ms"])] * len(run["frames"]["time_ms"])
    c = _by_name(res)["governor_flip_ratio"]
    assert c["passed"] is None and "never exceeds the target" in c["skipped"]
    assert _by_name(res)["governor_p99"]["passed"] is True  # the tail is still checked


def test_governor_checks_skip_without_a_governor_run():
    c = _by_name(synthetic_results())
    assert all(c[n]["passed"] is None for n in ("governor_mean_bound", "governor_p99", "governor_over",
                                                  "governor_flip_ratio"))
    assert "optimization std" in c["opt_std_bound_vs_static"]["line"]


def test_table_shows_the_median_repeat_with_the_spread_and_the_governor_row(tmp_path):
    res = _with_governor(synthetic_results())
    runs = []
    for k, shift in enumerate((3.0, -2.0, 0.0)):  # three repeats of every run, interleaved
        for r in res["runs"]:
            r = copy.deepcopy(r)
            r["repeat"] = k
            r["summary"]["frame_mean_ms"] += shift
            runs.append(r)
    res["runs"] = runs
    assert len(repeats_at(res, "optimization", 50.0)) == 3
    median = run_at(res, "optimization", 50.0)
    assert median["repeat"] == 2  # the middle mean of (+3, −2, 0)
    rows = {r["method"]: r for r in table1(res)}
    assert list(rows).index("optimization+gov") == list(rows).index("optimization") + 1
    assert rows["optimization"]["repeats"] == 3 and rows["optimization"]["frame_mean_spread_ms"] == pytest.approx(5.0)
    gov = run_at(res, "optimization", 50.0, governor=True)
    assert gov["governor"] and rows["optimization+gov"]["frame_mean_ms"] == gov["summary"]["frame_mean_ms"]
    labels = {p["method"] for p in quality_points(res)}
    assert {"optimization", "optimization+gov"} <= labels
    # one point per (method, budget), from the median repeat
    opt = [p for p in quality_points(res) if p["method"] == "optimization"]
    assert len(opt) == 3


def test_traces_draw_the_calibration_under_the_runs(tmp_path):
    res = _with_governor(synthetic_results(methods=["none", "static", "optimization"]))
    for r in res["runs"]:
        r["calibration"] = {"t": [0.0, 1.0, 2.0, 3.0], "ms": [2.0, 2.1, 3.5, 2.2]}
    path = write_traces(res, tmp_path / "traces.png")
    assert path is not None and path.stat().st_size > 0
    from PIL import Image

    plain = write_traces(synthetic_results(methods=["none", "static", "optimization"]), tmp_path / "plain.png")
    # one panel more (optimization+gov) and the calibration panel below: a taller figure
    assert Image.open(path).size[1] > Image.open(plain).size[1]
