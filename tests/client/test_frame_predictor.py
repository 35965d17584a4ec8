"""The governor's frame-time predictor: the time per unit drawn, and the same with the frame's fixed part."""

from __future__ import annotations

import numpy as np
import pytest

from client.frame_predictor import FramePredictor


def _feed(pred: FramePredictor, units: np.ndarray, time: np.ndarray) -> None:
    for u, t in zip(units, time):
        pred.observe(float(t), float(u))


def test_a_fixed_part_is_found_and_used_when_it_predicts_better():
    rng = np.random.default_rng(1)
    units = rng.uniform(0.01, 0.04, 120)  # the governor's steps move the units drawn
    time = 1.3 * (0.02 + units) * rng.lognormal(0.0, 0.02, units.size)
    pred = FramePredictor()
    _feed(pred, units, time)
    report = pred.report()
    assert pred.chosen == "offset" and report["offset_error"] < 0.7 * report["ratio_error"]
    assert pred.alpha == pytest.approx(0.02, rel=0.2)
    # The units a 50 ms frame may draw, as the machine draws them.
    fits = pred.units_for(0.05)
    assert 1.3 * (0.02 + fits) == pytest.approx(0.05, rel=0.05)


def test_frames_proportional_to_the_units_keep_the_simplest_predictor():
    rng = np.random.default_rng(2)
    units = rng.uniform(0.01, 0.04, 120)
    time = 1.1 * units * rng.lognormal(0.0, 0.02, units.size)
    pred = FramePredictor()
    _feed(pred, units, time)
    assert pred.chosen == "ratio" and pred.alpha == 0.0
    assert pred.predict(0.03) == pytest.approx(0.033, rel=0.05)


def test_units_that_do_not_vary_tell_nothing_about_a_fixed_part():
    pred = FramePredictor()
    _feed(pred, np.full(80, 0.03), np.full(80, 0.045))
    assert pred.report()["offset_alpha"] == 0.0 and pred.chosen == "ratio"


def test_a_machine_twice_slower_is_followed_after_two_frames():
    rng = np.random.default_rng(3)
    units = rng.uniform(0.01, 0.04, 100)
    speed = np.where(np.arange(units.size) < 60, 1.0, 2.0)
    time = speed * (0.015 + units)
    pred = FramePredictor()
    for i, (u, t) in enumerate(zip(units, time)):
        if i in (61, 62):  # one slow frame alone does not move it ...
            guess = pred.predict(u)
            assert guess is not None and (guess / t < 0.75 if i == 61 else abs(guess / t - 1) < 0.05), (i, guess / t)
        pred.observe(float(t), float(u))  # ... two in a row do


def _drifting(n: int, seed: int, rho: float = 0.9, sigma: float = 0.05) -> np.ndarray:
    """A machine's speed that drifts in stretches (log speed AR(1)): a slow frame is followed by a slow one."""
    rng = np.random.default_rng(seed)
    log = np.zeros(n)
    for i in range(1, n):
        log[i] = rho * log[i - 1] + rng.normal(0.0, sigma)
    return np.exp(log)


def test_the_speed_is_the_last_frames_or_the_median_whichever_predicts_better():
    units = np.full(300, 0.03)
    drifting = FramePredictor()
    _feed(drifting, units, 1.2 * units * _drifting(units.size, seed=4))
    independent = FramePredictor()
    _feed(independent, units, 1.2 * units * np.random.default_rng(4).lognormal(0.0, 0.1, units.size))
    assert drifting.report()["speed"] == "last"
    assert drifting.report()["last_error"] < drifting.report()["median_error"]
    assert independent.report()["speed"] == "median"
    assert independent.report()["median_error"] < 0.9 * independent.report()["last_error"]


def test_with_the_last_frame_in_force_a_twice_slower_machine_is_followed_after_one_frame():
    """On a drifting machine: the frame after the step is predicted at the new speed, and the fixed part, which
    the step does not change, is kept (the frames before the step are not fitted together with those after)."""
    rng = np.random.default_rng(6)
    n, step = 400, 300
    units = rng.uniform(0.01, 0.04, n)
    speed = _drifting(n, seed=6, rho=0.95, sigma=0.01) * np.where(np.arange(n) < step, 1.0, 2.0)
    time = speed * (0.015 + units)
    pred = FramePredictor()
    for i, (u, t) in enumerate(zip(units, time)):
        if i in (step, step + 1):
            assert pred.report()["speed"] == "last" and pred.chosen == "offset"
            guess = pred.predict(u)
            assert guess is not None and (guess / t < 0.75 if i == step else abs(guess / t - 1) < 0.05), (i, guess / t)
        pred.observe(float(t), float(u))
        if i == step + 1:
            assert len(pred.units) == 2  # the line restarted at the step
        if i == step + 30:  # refitted on the new speed's frames only
            assert pred.alpha == pytest.approx(0.015, rel=0.1)


def test_a_stall_is_not_taken_for_a_new_speed():
    rng = np.random.default_rng(8)
    units = rng.uniform(0.01, 0.04, 200)
    time = 1.2 * (0.015 + units) * _drifting(units.size, seed=8, rho=0.95, sigma=0.01)
    time[150] *= 3.0  # one stalled frame: the next is back to the machine's speed
    pred = FramePredictor()
    _feed(pred, units[:152], time[:152])
    # The frame after the stall was predicted at the stall's rate; the one after that is not.
    guess = pred.predict(float(units[152]))
    assert guess is not None and abs(guess / time[152] - 1) < 0.05
    assert len(pred.units) == pred.units.maxlen  # the line was not restarted
    assert pred.alpha == pytest.approx(0.015, rel=0.1)


@pytest.mark.parametrize("time, units", [(float("nan"), 0.02), (0.03, 0.0), (-1.0, 0.02), (0.03, float("inf"))])
def test_frames_that_say_nothing_are_ignored(time, units):
    pred = FramePredictor()
    pred.observe(time, units)
    assert pred.rate is None and pred.predict(0.02) is None and pred.units_for(0.05) is None
    with pytest.raises(ValueError):
        FramePredictor(window=4)
