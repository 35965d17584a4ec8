"""The kiosk tour and its comparison of tour-aware with linear prediction (``walkstream bench predict``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench.kiosk import image_kiosk, kiosk_tour, predict_kiosk
from client.app import HELLO_PLAN_KEYS, tour_plan
from proto.codec import MAX_CLIENT_FRAME, encode
from proto.messages import TourKey
from proto.tour import Tour
from server.scene.store import SceneStore
from server.select.navigation import Plan


@pytest.fixture(scope="module")
def walk(demo_store):
    with SceneStore.open(demo_store) as store:
        grid = store.walkable()
    return grid, kiosk_tour(grid, stops=3, dwell=2.0, seed=1)


def test_a_kiosk_tour_walks_on_the_ground_at_bounded_speed_and_stands_at_its_stops(walk):
    grid, keys = walk
    for k in keys:
        TourKey(**k)  # every key is a valid wire key
    tour = Tour(keys)
    t = np.arange(tour.t[0], tour.t[-1], 0.05)
    eye, fwd, _ = tour.pose_at(t)
    assert grid.walkable(eye[:, :2]).all()
    speed = np.linalg.norm(np.diff(eye[:, :2], axis=0), axis=1) / 0.05
    assert speed.max() <= 1.2 * (1 + 1e-4)  # (key times are rounded to microseconds)
    turn = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", fwd[1:], fwd[:-1]), -1, 1))) / 0.05
    assert turn.max() <= 60.0 * 1.1  # nlerp between keys ≤ 45° apart turns a little unevenly
    keys_eye = np.array([k["eye"] for k in keys])
    np.testing.assert_allclose(keys_eye[:, 2], grid.height(keys_eye[:, :2]) + 1.7, atol=1e-5)
    still = (speed < 1e-9)
    assert still.sum() * 0.05 >= 2 * 2.0  # the dwells at the stops after the first
    assert keys[0]["eye"] == keys[-1]["eye"]  # closed


def test_tour_aware_prediction_is_exact_on_the_kiosk_tour_and_linear_is_not(walk):
    grid, keys = walk
    result = predict_kiosk(keys, grid, horizons=(0.5, 1.0))
    for row in result["rows"]:
        assert row["plan_pos_mean"] < 1e-6 and row["plan_ang_mean"] < 1e-4
        assert row["linear_pos_mean"] > 0.01 and row["plan_pos_ratio"] < 1e-3
        assert row["walk_pos_ratio"] is not None
    assert any("plan/lin" in line for line in result["lines"])


def test_a_runs_plan_unrolls_the_looping_tour_and_fits_one_hello(walk):
    _, keys = walk
    tour = Tour(keys)
    duration = 1.5 * tour.duration
    plan = tour_plan(keys, duration)
    assert len(plan.keys) <= HELLO_PLAN_KEYS and len(encode(plan)) < MAX_CLIENT_FRAME - 4096
    covered = Plan.of(plan.keys, 0.0)
    t = np.arange(tour.t[0], min(duration, covered.t[-1]), 0.1)
    assert covered.covers(t).all()
    eye, fwd, _ = covered.poses(t)
    true_eye, true_fwd, _ = tour.pose_at(t)
    np.testing.assert_allclose(eye, true_eye, atol=1e-9)
    np.testing.assert_allclose(fwd, true_fwd, atol=1e-9)


def test_the_eval_runs_the_kiosk_tour_with_and_without_its_plan(walk, demo_store):
    _, keys = walk
    result = image_kiosk(demo_store, keys, duration=3.5, viewport=(160, 90), samples=3)
    for mode in ("linear", "plan"):
        run = result["runs"][mode]
        assert run["errors"] == 0 and run["frames"] > 0 and run["samples"] > 0
        assert math.isfinite(run["flip_mean"]) and run["psnr_mean"] > 0
    assert result["ratios"]["flip"] is not None and any("tour-aware / linear" in line for line in result["lines"])
