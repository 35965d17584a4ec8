"""The report folder: written from a results dict alone, its tables equal the summaries, its checks bite at
their limits, its Pareto front is right, and its index links every file that exists and escapes text."""

from __future__ import annotations

import csv
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from bench.report.checks import bound_frames, checks, pareto, pareto_miss, quality_points
from bench.report.folder import summary_lines, write_report
from bench.report.table import COLUMNS, table1, write_table1

METHODS = ["none", "static", "feedback", "optimization", "hierarchical", "predictive", "mixed"]
#: Plausible per-method behaviour at budget b: (frame mean as × b or ms if budget-free, std share, FLIP at 1×)
_SHAPE = {
    "none": (215.0, 0.70, 0.0),
    "static": (55.0, 0.40, 0.08),
    "feedback": (1.0, 0.25, 0.07),
    "optimization": (0.97, 0.06, 0.05),
    "hierarchical": (0.96, 0.08, 0.055),
    "predictive": (0.95, 0.07, 0.045),
    "mixed": (0.95, 0.07, 0.047),
}


def _summary(t, ms, compute, tris, quality, warmup) -> dict:
    keep = t >= warmup
    x = ms[keep]
    return {
        "frames": int(keep.sum()),
        "compute_mean_ms": float(compute[keep].mean()), "compute_max_ms": float(compute[keep].max()),
        "frame_mean_ms": float(x.mean()), "frame_max_ms": float(x.max()), "frame_std_ms": float(x.std()),
        "frame_p95_ms": float(np.percentile(x, 95)), "frame_p99_ms": float(np.percentile(x, 99)),
        "over_pct": float(100 * np.mean(x > 55.0)),
        "triangles_mean": float(tris[keep].mean()), "reps_mean": 400.0, "bytes_total": 123456,
        "flip_mean": float(np.mean(quality["flip"])), "psnr_mean": float(np.mean(quality["psnr"])),
        "ssim_mean": float(np.mean(quality["ssim"])), "popping_mean": float(np.mean(quality["popping"])),
        "errors": 0, "late": 0, "deltas": 12,
    }


def synthetic_results(scene: str = "auditorium", *, seed: int = 0, target: float = 50.0, duration: float = 20.0,
                      methods=METHODS, images: dict | None = None) -> dict:
    """A plausible evaluation result (the schema's shape) without a server, a client or a GPU."""
    rng = np.random.default_rng(seed)
    budgets = [target / 2, target, target * 2]
    warmup = 2.0
    runs = []
    for method in methods:
        mean, std, flip = _SHAPE[method]
        free = method in ("none", "static")
        for b in [target] if free else budgets:
            centre = mean if free else mean * b
            n = int(duration * 1000.0 / centre)
            t = np.cumsum(np.full(n, centre / 1000.0))
            ms = np.abs(rng.normal(centre, std * centre, n)) + 1.0
            compute = np.abs(rng.normal(0.4, 0.1, n))
            tris = rng.normal(3e5 * (b / target if not free else 1.0), 1e4, n)
            frame = np.arange(0, n, 10)
            frame = frame[t[frame] >= warmup]
            err = flip * (target / b if not free else 1.0)
            quality = {
                "t": t[frame].tolist(), "frame": frame.tolist(),
                "flip": np.abs(rng.normal(err, 0.005, frame.size)).tolist() if err else [0.0] * frame.size,
                "psnr": (30 + 5 * rng.random(frame.size)).tolist() if err else [math.inf] * frame.size,
                "ssim": (0.9 + 0.05 * rng.random(frame.size)).tolist(),
                "popping": np.abs(rng.normal(0.3, 0.1, frame.size)).tolist(),
            }
            runs.append({
                "method": method, "target_ms": b, "solver": method, "predict": method in ("predictive", "mixed"),
                "morph": method in ("predictive", "mixed"),
                "frames": {"t": t.tolist(), "time_ms": ms.tolist(), "compute_ms": compute.tolist(),
                           "triangles": tris.tolist(), "reps": [400] * n, "bytes": [0] * n, "morphs": [0] * n,
                           "predicted_ms": ms.tolist()},
                "quality": quality,
                "summary": _summary(t, ms, compute, tris, quality, warmup),
            })
    return {
        "scene": scene, "store": "/tmp/x.db", "target_ms": target, "budgets_ms": budgets, "viewport": [640, 360],
        "fov_y": 60.0, "tau_s": 0.5, "seed": seed, "duration_s": duration, "warmup_s": warmup,
        "viewpoints": {"A": 5.0, "B": 10.0, "C": 15.0}, "methods": list(methods), "runs": runs,
        "images": images or {},
        "scenarios": [{"name": "spin", "title": "sudden complexity: the spin at C", "passed": True,
                       "line": "PASS spin at C: p95 51 ms ≤ 62.5 ms", "figures": {}},
                      {"name": "turn", "title": "abrupt turn", "passed": False, "line": "FAIL turn: recovery 1.9 s",
                       "figures": {}}],
    }


def _png(path: Path) -> None:
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.zeros((9, 16, 3), np.uint8)).save(path)


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    """One synthetic report (charts are the slow part: write them once for the module's tests)."""
    out = tmp_path_factory.mktemp("report")
    images = {label: {m: f"images/{label}-{m}.png" for m in ["full", "optimization", "predictive", "static"]}
              for label in ("A", "C")}
    for label in images:
        for rel in images[label].values():
            _png(out / rel)
    images["C"]["mixed"] = "images/C-mixed.png"  # named but never written: must not be linked as an image
    results = synthetic_results("aud <b>&\"x\"", images=images)
    index = write_report(results, out, date="2024-01-01T00:00:00")
    return results, out, index


def test_report_writes_every_file_non_empty(report):
    results, out, index = report
    assert index == out / "index.html"
    for name in ("results.json", "table1.csv", "table1.md", "traces.png", "quality.png", "quality_psnr.png",
                 "checks.md", "index.html"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    for name in ("traces.png", "quality.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # strict JSON (the infinite PSNR of full detail becomes null), otherwise the same results
    back = json.loads((out / "results.json").read_text(), parse_constant=lambda c: pytest.fail(f"non-strict {c}"))
    assert back["scene"] == results["scene"] and len(back["runs"]) == len(results["runs"])
    assert back["runs"][0]["summary"]["psnr_mean"] is None  # none: identical to full detail → ∞ → null


def test_csv_has_the_columns_and_the_summaries_values(report):
    results, out, _ = report
    with (out / "table1.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == ["method"] + [key for key, _, _ in COLUMNS]
    assert [r["method"] for r in rows] == METHODS  # F&S order, one row per method at the target
    at_target = {r["method"]: r["summary"] for r in results["runs"] if r["target_ms"] == results["target_ms"]}
    for row in rows:
        summary = at_target[row["method"]]
        for key, _, _ in COLUMNS:
            if key == "frames":
                assert int(row[key]) == summary[key]
            elif key == "repeats":  # one run each: no spread
                assert int(row[key]) == 1 and float(row["frame_mean_spread_ms"]) == 0.0
            elif key == "frame_mean_spread_ms" or (key not in summary and row[key] == ""):
                continue
            else:
                assert float(row[key]) == pytest.approx(summary[key], rel=1e-12), (row["method"], key)


def test_markdown_table_has_one_row_per_method(report):
    _, out, _ = report
    lines = [ln for ln in (out / "table1.md").read_text().splitlines() if ln.startswith("|")]
    assert len(lines) == 2 + len(METHODS)
    assert "(ms)" in lines[0] and lines[1].startswith("|---")
    assert [ln.split("|")[1].strip() for ln in lines[2:]] == METHODS
    assert all(ln.count("|") == lines[0].count("|") for ln in lines)


def test_table1_budget_free_methods_count_at_every_budget_and_missing_figures_are_none():
    results = synthetic_results(methods=["static", "optimization"])
    rows = table1(results, target_ms=25.0)
    assert [r["method"] for r in rows] == ["static", "optimization"]
    opt25 = next(r for r in results["runs"] if r["method"] == "optimization" and r["target_ms"] == 25.0)
    assert rows[1]["frame_mean_ms"] == opt25["summary"]["frame_mean_ms"]
    assert table1(results, target_ms=33.0)[0]["method"] == "static" and len(table1(results, target_ms=33.0)) == 1
    for run in results["runs"]:
        del run["summary"]["flip_mean"]
    assert table1(results)[1]["flip_mean"] is None


def test_write_table1_renders_missing_as_empty_and_dash(tmp_path):
    row = {"method": "x", **{key: None for key, _, _ in COLUMNS}}
    csv_path, md_path = write_table1([row], tmp_path)
    assert csv_path.read_text().splitlines()[1] == "x" + "," * len(COLUMNS)
    assert "—" in md_path.read_text()


def test_pareto_excludes_dominated_points_and_keeps_ties():
    pts = np.array([[10.0, 0.5], [20.0, 0.2], [15.0, 0.6], [30.0, 0.1], [20.0, 0.2], [25.0, 0.2], [np.nan, 0.0]])
    mask = pareto(pts)
    # (15, .6) is dominated by (10, .5); (25, .2) by (20, .2); the two (20, .2) tie and both stay; NaN is out
    assert mask.tolist() == [True, True, False, True, True, False, False]
    assert pareto(np.zeros((0, 2))).tolist() == []
    assert pareto([[1.0, 1.0]]).tolist() == [True]
    with pytest.raises(ValueError):
        pareto(np.zeros((3, 3)))


def test_pareto_miss_is_the_smallest_relative_improvement():
    pts = np.array([[10.0, 0.5], [20.0, 0.2], [24.0, 0.25], [30.0, 0.1]])
    assert pareto_miss(pts, 0) == (0.0, None)
    miss, who = pareto_miss(pts, 2)
    # (24, .25) is dominated by (20, .2): 1 − 20/24 = 16.7 % faster, or 1 − .2/.25 = 20 % less error
    assert miss == pytest.approx(1 - 20 / 24) and who == 1
    # after that improvement it is on the front (at the boundary it ties on x: nudge past it)
    moved = pts.copy()
    moved[2, 0] = 24.0 * (1 - miss) * (1 - 1e-9)
    assert pareto(moved)[2]


def _crafted(opt_std: float, static_std: float, feedback_std: float, opt_max: float, target: float = 50.0) -> dict:
    def run(method, std=5.0, mx=60.0, mean=50.0, flip=0.05, b=target):
        return {"method": method, "target_ms": b, "summary": {
            "frames": 100, "frame_mean_ms": mean, "frame_std_ms": std, "frame_max_ms": mx, "frame_p95_ms": mx,
            "compute_mean_ms": 0.1, "compute_max_ms": 0.2, "flip_mean": flip}}

    return {"scene": "s", "target_ms": target, "methods": ["static", "feedback", "optimization", "predictive"],
            "runs": [run("static", std=static_std), run("feedback", std=feedback_std),
                     run("optimization", std=opt_std, mx=opt_max, mean=48.0, flip=0.05),
                     run("predictive", mean=49.0, flip=0.06),
                     run("predictive", mean=30.0, flip=0.07, b=25.0)]}


def _by_name(cs):
    return {c["name"]: c for c in cs}


def test_checks_pass_exactly_at_the_limits():
    cs = _by_name(checks(_crafted(opt_std=1.0, static_std=3.0, feedback_std=3.0, opt_max=55.0)))
    for name in ("opt_std_vs_static", "opt_std_vs_feedback", "opt_max"):
        assert cs[name]["passed"] is True, cs[name]["line"]
        assert cs[name]["line"].startswith("PASS")
    assert cs["opt_std_vs_static"]["value"] == pytest.approx(1 / 3)
    assert cs["opt_max"]["value"] == pytest.approx(1.10) and cs["opt_max"]["limit"] == 1.10
    assert set(cs["opt_max"]) >= {"name", "passed", "value", "limit", "line"}


def test_checks_fail_just_over_the_limits_and_say_by_how_much():
    cs = _by_name(checks(_crafted(opt_std=1.01, static_std=3.0, feedback_std=6.0, opt_max=55.1)))
    assert cs["opt_std_vs_static"]["passed"] is False and "misses by 1.01×" in cs["opt_std_vs_static"]["line"]
    assert cs["opt_std_vs_feedback"]["passed"] is True
    assert cs["opt_max"]["passed"] is False and "misses by 0.1 ms" in cs["opt_max"]["line"]


def test_pareto_checks_pass_on_the_front_and_fail_with_the_distance_off_it():
    cs = _by_name(checks(_crafted(1.0, 3.0, 3.0, 50.0)))
    # optimization (48, .05) dominates static/feedback (50, .05) and is on the front
    assert cs["opt_pareto"]["passed"] is True and cs["opt_pareto"]["value"] == 0.0
    # predictive at the target (49, .06) is dominated by optimization (48, .05)
    pred = cs["pred_pareto"]
    assert pred["passed"] is False and pred["value"] == pytest.approx(min(1 - 48 / 49, 1 - 0.05 / 0.06))
    assert "dominated by optimization@50" in pred["line"]
    assert pred["budgets"]["predictive@25"] == 0.0  # its 25 ms point is on the front


def test_checks_skip_absent_methods_and_unmeasured_quality():
    results = _crafted(1.0, 3.0, 3.0, 50.0)
    results["runs"] = [r for r in results["runs"] if r["method"] not in ("static", "predictive")]
    for run in results["runs"]:
        del run["summary"]["flip_mean"]
    cs = _by_name(checks(results))
    assert cs["opt_std_vs_static"]["passed"] is None and cs["opt_std_vs_static"]["line"].startswith("SKIP")
    assert cs["opt_std_vs_feedback"]["passed"] is True
    assert cs["opt_pareto"]["passed"] is None and cs["pred_pareto"]["passed"] is None
    assert checks({"target_ms": 50.0, "runs": []})[0]["passed"] is None


def test_quality_points_give_budget_free_methods_one_point():
    points = quality_points(synthetic_results(methods=["none", "optimization"]))
    assert [(p["method"], p["budget_ms"]) for p in points] == [("none", None), ("optimization", 25.0),
                                                                ("optimization", 50.0), ("optimization", 100.0)]


def test_index_links_every_existing_file_and_escapes_text(report):
    results, out, index = report
    text = index.read_text()
    srcs = set(re.findall(r'<img[^>]* src="([^"]+)"', text))
    assert {"traces.png", "quality.png", "quality_psnr.png"} <= srcs
    for label, by_method in results["images"].items():
        for rel in by_method.values():
            assert (rel in srcs) == (out / rel).is_file(), rel
    assert all((out / s).is_file() for s in srcs)  # nothing links a file that is not there
    assert "aud <b>" not in text and "aud &lt;b&gt;&amp;&quot;x&quot;" in text
    assert "2024-01-01T00:00:00" in text and "target 50 ms" in text
    for method in METHODS:
        assert f"<td>{method}</td>" in text
    assert text.count('class="pass"') >= 1 and 'class="fail"' in text  # the scenarios' PASS and FAIL
    assert "sudden complexity: the spin at C" in text and "FAIL turn: recovery 1.9 s" in text
    assert "&quot;A&quot;: 5.0" in text  # settings: viewpoints


def test_report_without_quality_or_images_leaves_those_out(tmp_path):
    results = synthetic_results(methods=["static", "optimization"], duration=6.0)
    for run in results["runs"]:
        run.pop("quality")
        for key in ("flip_mean", "psnr_mean", "ssim_mean", "popping_mean"):
            run["summary"][key] = None
    results["viewpoints"], results["images"], results["scenarios"] = {}, {}, []
    index = write_report(results, tmp_path)
    assert (tmp_path / "traces.png").is_file() and not (tmp_path / "quality.png").exists()
    text = index.read_text()
    assert "quality.png" not in text and "No quality chart" in text
    assert "Viewpoint" not in text and "Scenarios" not in text


def test_summary_lines_hold_the_table_and_the_checks():
    results = synthetic_results(methods=["static", "feedback", "optimization", "predictive"])
    lines = summary_lines(results)
    assert lines[0].startswith("Table 1 — auditorium, target 50 ms")
    body = [ln for ln in lines[3:] if ln.split() and ln.split()[0] in METHODS]
    assert [ln.split()[0] for ln in body] == ["static", "feedback", "optimization", "predictive"]
    names = ("opt_std_vs_static", "opt_std_vs_feedback", "opt_max", "opt_pareto", "pred_pareto")
    assert all(any(name in ln for ln in lines) for name in names)
    assert len({len(ln) for ln in lines[1:3]}) == 1  # aligned heading and rule


def test_bad_target_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match="target"):
        table1({"runs": []})
    with pytest.raises(ValueError, match="target"):
        write_report({"target_ms": -5, "runs": []}, tmp_path)


def _frames(t, ms):
    t = np.asarray(t, float)
    return {"t": t.tolist(), "time_ms": list(map(float, ms)), "seq": [1] * t.size}


def test_bound_frames_judge_methods_where_full_detail_exceeds_the_target():
    """A cheap stretch (full detail under the target, t in [10, 20)) where every method draws fast frames
    is left out of the bound std; where full detail is dear, a method holding the budget is steady."""
    t = np.arange(2.0, 30.0, 0.05)
    cheap = (t >= 10) & (t < 20)
    none = np.where(cheap, 15.0, 200.0)
    steady = np.where(cheap, 5.0, 48.0 + np.sin(t))  # holds the budget where it binds, nothing to draw elsewhere
    wild = np.where(cheap, 10.0, 50.0 + 20 * np.sin(3 * t))  # follows the scene
    results = {"scene": "s", "target_ms": 50.0, "warmup_s": 2.0, "methods": ["none", "static", "optimization"],
               "runs": [{"method": "none", "target_ms": 50.0, "frames": _frames(t, none), "summary": {}},
                        {"method": "static", "target_ms": 50.0, "frames": _frames(t, wild), "summary": {}},
                        {"method": "optimization", "target_ms": 50.0, "frames": _frames(t, steady),
                         "summary": {"frame_std_ms": float(steady[t >= 2].std())}}]}
    bound = bound_frames(results)
    opt = bound["methods"]["optimization"]
    assert bound["share"] == pytest.approx(1 - cheap.mean(), abs=0.01)
    assert opt["frames"] == int((~cheap).sum()) and opt["frame_max_ms"] <= 49.0
    assert opt["frame_std_ms"] == pytest.approx(steady[~cheap].std())
    assert bound["methods"]["static"]["frame_std_ms"] == pytest.approx(wild[~cheap].std())
    cs = _by_name(checks(results))
    assert cs["opt_std_bound_vs_static"]["passed"] is True and "% of optimization's" in cs["opt_std_bound_vs_static"]["line"]
    assert cs["opt_std_bound_vs_feedback"]["passed"] is None  # no feedback run
    # The whole-path std, F&S's own, fails on the same runs: the cheap stretch dominates it.
    results["runs"][1]["summary"]["frame_std_ms"] = float(wild[t >= 2].std())
    assert _by_name(checks(results))["opt_std_vs_static"]["passed"] is False
    # Without a none run there is nothing to tell the stretches apart by.
    results["runs"] = results["runs"][1:]
    assert bound_frames(results) is None and _by_name(checks(results))["opt_std_bound_vs_static"]["passed"] is None


def test_table1_takes_figures_a_summary_lacks_from_the_runs_frames():
    """Results written before p99 and the share over 1.1 × target were summarised still report them."""
    results = synthetic_results(methods=["static", "optimization"])
    for run in results["runs"]:
        del run["summary"]["frame_p99_ms"], run["summary"]["over_pct"]
    rows = {r["method"]: r for r in table1(results)}
    run = next(r for r in results["runs"] if r["method"] == "optimization" and r["target_ms"] == 50.0)
    t, ms = np.array(run["frames"]["t"]), np.array(run["frames"]["time_ms"])
    x = ms[t >= results["warmup_s"]]
    assert rows["optimization"]["frame_p99_ms"] == pytest.approx(np.percentile(x, 99))
    assert rows["optimization"]["over_pct"] == pytest.approx(100 * np.mean(x > 55.0))
    assert rows["static"]["over_pct"] > rows["optimization"]["over_pct"]
