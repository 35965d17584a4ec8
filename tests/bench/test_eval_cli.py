"""``walkstream eval`` end to end: the real server and client, the replay's image error in worker processes,
a scenario, and the report folder — on the small demo store, in a few seconds of tour per run."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path


def _walkstream(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "walkstream", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=Path(__file__).resolve().parents[2])


def test_eval_writes_a_report_from_real_runs(demo_store, tmp_path) -> None:
    out = tmp_path / "report"
    done = _walkstream("eval", str(demo_store), "--methods", "static,optimization", "--budgets", "50",
                       "--duration", "4", "--samples", "2", "--scenario", "below_coarsest", "--out", str(out),
                       "--repeats", "1", "--json")
    assert done.returncode == 0, done.stderr[-3000:]
    figures = json.loads(done.stdout.strip().splitlines()[-1])
    assert [r["method"] for r in figures["table1"]] == ["static", "optimization", "optimization+gov"]
    names = {c["name"] for c in figures["checks"]}
    assert names >= {"opt_std_vs_static", "opt_max", "opt_pareto", "governor_mean_bound", "governor_p99",
                     "governor_over", "governor_flip_ratio", "opt_std_bound_vs_static", "opt_std_bound_vs_feedback"}
    gov = {c["name"]: c for c in figures["checks"] if c["name"].startswith("governor_")}
    assert gov["governor_p99"]["passed"] is not None
    # The ratio needs a picture to improve on: a short run may find Optimization already at full detail.
    flip = gov["governor_flip_ratio"]
    assert flip["passed"] is not None or "full-detail picture (FLIP 0)" in flip["skipped"]
    assert [s["name"] for s in figures["scenarios"]] == ["below_coarsest"]
    assert figures["scenarios"][0]["line"].split()[0] in ("PASS", "FAIL")
    results = json.loads((out / "results.json").read_text())
    for run in results["runs"]:
        q = run["quality"]
        assert 1 <= len(q["flip"]) <= 2 and len(q["flip"]) == len(q["ssim"]) == len(q["psnr"]) == len(q["popping"])
        assert all(0.0 <= f <= 1.0 for f in q["flip"]) and all(-1.0 <= s <= 1.0 for s in q["ssim"])
        assert all(p >= 0.0 for p in q["popping"])
        s = run["summary"]
        assert math.isclose(s["flip_mean"], sum(q["flip"]) / len(q["flip"]), rel_tol=1e-9)
        assert s["frames"] > 0 and s["frame_mean_ms"] > 0
    index = (out / "index.html").read_text()
    for name in ("table1.csv", "table1.md", "traces.png", "quality.png"):
        assert (out / name).stat().st_size > 0
        assert name in index
    assert "below_coarsest" in index


def test_eval_refuses_what_it_cannot_run(tmp_path) -> None:
    done = _walkstream("eval", str(tmp_path / "nowhere.db"), "--no-scenarios")
    assert done.returncode == 2 and "nowhere.db" in done.stderr
    done = _walkstream("eval", "auditorium", "--methods", "optimization,magic")
    assert done.returncode == 2 and "magic" in done.stderr
    done = _walkstream("eval", "auditorium", "--scenario", "earthquake")
    assert done.returncode == 2 and "earthquake" in done.stderr
