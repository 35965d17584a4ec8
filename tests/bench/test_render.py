"""``walkstream bench render``: linearity, client CPU against drawn reps, and the cost model's held-out error."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from bench.machine import frame_noise
from bench.render import delta_apply, replay


def _frames(n, c_vertex=2e-7, c_draw=1e-5, overhead=1e-3, noise=0.02, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        v = rng.uniform(1e4, 2e5, 3) * np.array([1.0, 0.5, 0.2])
        d = rng.integers(50, 500, 3)
        t = overhead + c_vertex * v.sum() + c_draw * d.sum()
        out.append({"t": i / 30.0, "time": float(t * (1 + noise * rng.standard_normal())), "splats": 0,
                    "terms": {"triangles": (2 * v).astype(int).tolist(), "vertices": v.astype(int).tolist(),
                              "pixels": [1000, 0, 0], "draws": d.tolist()}})
    return out


def test_replay_scores_the_online_model_held_out_against_zach_and_the_last_frame():
    result = replay(_frames(300))
    assert result["frames"] == sum(1 for f in _frames(300) if f["t"] >= 2.0)
    # A machine with a per-draw cost and a fixed overhead: the fitted model beats c_vertex alone.
    assert result["p95_pct"] < result["zach_p95_pct"]
    assert result["p95_pct"] < 10.0 and result["goal_met"]
    assert result["chosen"] in ("draw", "stages")
    assert result["last_frame_p95_pct"] > result["p95_pct"]  # the frames vary: persistence is no model
    json.dumps(result)


def test_frame_noise_pairs_only_consecutive_frames_of_the_same_work():
    t = np.arange(10) * 0.5
    time_s = np.array([9, 9, 1.0, 1.2, 1.0, 2.0, 2.0, 2.2, 1.0, 1.0])
    vertices = np.array([5, 5, 100, 100, 100, 300, 300, 300, 100, 100.5])
    noise = frame_noise(t, time_s, vertices, warmup=1.0)
    # pairs from t = 1 s on with equal vertices: 1.2/1.0, 1.0/1.2, 2.0/2.0, 2.2/2.0, 1.0/1.0 (the changes are not)
    assert noise["pairs"] == 5 and noise["p50"] == 1.0
    assert noise["p99"] == round(float(np.percentile([1.2, 1 / 1.2, 1.0, 1.1, 1.0], 99)), 3)
    assert noise["frame_sd"] == pytest.approx(np.std(np.log([1.2, 1 / 1.2, 1.0, 1.1, 1.0])) / np.sqrt(2))
    assert frame_noise(t, time_s, np.arange(10) * 100.0 + 100)["pairs"] == 0
    # Only pairs whose both frames take at least ``least``: here those of 2.0-2.2 s.
    slow = frame_noise(t, time_s, vertices, warmup=1.0, least=1.5)
    assert slow["pairs"] == 2 and slow["p99"] == round(float(np.percentile([1.0, 1.1], 99)), 3)


def test_delta_apply_sums_the_loop_held_against_run_and_target():
    d = delta_apply(np.array([0.0, 0.2, 0.0, 0.05, 0.0]), duration=10.0, target=0.05)
    assert d == {"total_s": 0.25, "share_of_run": 0.025, "max_ms": 200.0, "max_vs_target": 4.0,
                 "frames_with_deltas": 2}


def test_bench_render_command_prints_its_figures_and_json(auditorium_store):
    cmd = [sys.executable, "-m", "walkstream", "bench", "render", "--quick", "--store", str(auditorium_store),
           "--duration", "8", "--json"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    lin, cpu, cost = result["linearity"], result["client_cpu"], result["cost_model"]
    assert lin["triangles"] == sorted(lin["triangles"]) and len(lin["ms"]) == len(lin["triangles"])
    assert lin["ns_per_triangle"] > 0 and 0 <= lin["repeat_p95_pct"] < 1000
    assert [r["reps"] for r in cpu["rows"]] == [100, 1000]
    assert all(r["cpu_ms"] > 0 and r["submit_ms"] >= r["cpu_ms"] and r["per_draw_loop_ms"] > 0 for r in cpu["rows"])
    assert cost["scene"] == "auditorium" and cost["frames"] > 10
    assert cost["chosen"] in ("vertex", "draw", "stages")
    assert set(cost["report"]["models"]) == {"vertex", "draw", "stages"}
    assert sum(cost["algorithms_drawn"].values()) > 0.99  # every frame's draws, split by algorithm
    assert cost["delta_apply"]["total_s"] > 0 and cost["delta_apply"]["frames_with_deltas"] >= 1
    assert cost["identical_work"]["pairs"] > 0 and cost["identical_work"]["p99"] >= cost["identical_work"]["p50"]
    for needle in ("Frame time against triangles", "Client CPU per frame", "Cost-model error", "applying deltas",
                   "identical work"):
        assert needle in done.stderr
