"""``bench benefit``: objects drawn alone at every level by the real renderer, FLIP against the finest,
and the accuracy models scored against it."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bench.benefit import AZIMUTHS, DISTANCES, MODELS, SIMPLEST_FIRST, choose, predicted_loss, run, score


def test_choose_takes_the_simplest_model_within_ten_percent_of_the_best():
    s = lambda rho: {"spearman": rho, "fit_error": 0.5}  # noqa: E731
    assert choose({"fs": s(0.80), "zach": s(0.50), "sse": s(0.73)}) == "sse"  # 0.73 ≥ 0.9 × 0.80
    assert choose({"fs": s(0.80), "zach": s(0.75), "sse": s(0.70)}) == "zach"
    assert choose({"fs": s(0.80), "zach": s(0.10), "sse": s(0.20)}) == "fs"
    assert SIMPLEST_FIRST[0] == "sse" and set(SIMPLEST_FIRST) == set(MODELS)


def test_score_ranks_a_model_that_predicts_the_error_perfectly_first():
    rng = np.random.default_rng(0)
    n = 60
    samples = {"size": rng.uniform(100, 1e5, n), "faces": rng.integers(10, 5000, n),
               "original": np.full(n, 5000), "error": rng.uniform(0.001, 0.5, n), "extent": np.full(n, 3.0)}
    truth = predicted_loss("sse", **samples)
    samples["measured"] = list(0.2 * truth)
    scores = score({k: list(v) for k, v in samples.items()})
    assert scores["sse"]["spearman"] == pytest.approx(1.0)
    assert scores["sse"]["fit_error"] < 1e-3
    assert all(scores[m]["spearman"] < 1.0 for m in ("fs", "zach"))


def test_bench_benefit_measures_real_frames(demo_store):
    result = run([demo_store], objects=2, viewport=(96, 54))
    scene = result["scenes"]["demo"]
    assert scene["objects"] == 2
    assert 0 < scene["samples"] <= 2 * len(DISTANCES) * len(AZIMUTHS) * 8
    assert result["default"] in MODELS
    for model in MODELS:
        rho = result["scores"][model]["spearman"]
        assert math.isnan(rho) or -1.0 <= rho <= 1.0
    # coarser levels differ from the finest in the picture: some measured error is positive
    assert 0.0 < scene["measured_max"] < 10.0  # per covered pixel: FLIP blurs error a little beyond them
    assert any("default" in line for line in result["lines"])


def test_bench_benefit_cli_refuses_a_missing_store(tmp_path):
    done = subprocess.run([sys.executable, "-m", "walkstream", "bench", "benefit", "--store", str(tmp_path / "x.db")],
                          capture_output=True, text=True, timeout=120, cwd=Path(__file__).resolve().parents[2],
                          env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])})
    assert done.returncode == 2 and "no such store" in done.stderr and "Traceback" not in done.stderr
