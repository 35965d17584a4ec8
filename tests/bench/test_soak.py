"""The soak's schedule and its pass lines (pure); the soak itself runs in tests/integration/test_kiosk_soak.py."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from bench.soak import RECOVERY_S, Sample, SoakPlan, judge


def _samples(n: int, *, rss=100 << 20, threads=10, sockets=3, every=10.0, frames_per=100) -> list[Sample]:
    return [Sample(t=i * every, rss=rss, threads=threads, sockets=sockets, frames=i * frames_per + 1, deltas=i,
                   cache_bytes=1 << 20, gpu_memory=None, state="attract") for i in range(n)]


def test_the_hour_cuts_every_five_minutes_for_a_minute_and_restarts_once_between_cuts() -> None:
    plan = SoakPlan.scaled(3600)
    assert plan.cuts[0] == (300.0, 360.0) and all(b - a == 60.0 for a, b in plan.cuts)
    assert len(plan.cuts) == 11
    r = plan.restart
    assert r is not None and not any(a <= r <= b for a, b in plan.cuts)
    assert [k for _, k in plan.events()].count("restart") == 1


@given(st.floats(60.0, 7200.0))
def test_every_plan_keeps_its_events_inside_the_run_and_the_restart_outside_cuts(duration) -> None:
    plan = SoakPlan.scaled(duration)
    times = [t for t, _ in plan.events()]
    assert times == sorted(times) and all(0 < t < duration for t in times)
    if plan.restart is not None:
        assert not any(a <= plan.restart < b + RECOVERY_S for a, b in plan.cuts)


def test_a_plan_is_refused_with_the_field_named() -> None:
    with pytest.raises(ValueError, match="cut_for"):
        SoakPlan(duration=600, cut_every=60, cut_for=60)
    with pytest.raises(ValueError, match="restart_at"):
        SoakPlan(duration=600, cut_every=200, cut_for=30, restart_at=210)


def test_a_clean_run_passes_every_line() -> None:
    plan = SoakPlan.scaled(120)
    v = judge(plan, _samples(13), [(50.0, 1.2), (65.0, 0.8), (90.0, 2.0)], out_of_bounds=0)
    assert v["passed"], v
    assert v["lines"]["deltas_resume"]["figure"] == 2.0


def test_each_failure_fails_its_own_line() -> None:
    plan = SoakPlan.scaled(120)
    good = _samples(13)
    grown = good[:-1] + [Sample(**{**good[-1].__dict__, "rss": int(good[-1].rss * 1.2)})]
    assert not judge(plan, grown, [(50.0, 1.0)], 0)["lines"]["rss_growth"]["ok"]
    stalled = good[:5] + [Sample(**{**good[5].__dict__, "frames": good[4].frames})] + good[6:]
    assert not judge(plan, stalled, [(50.0, 1.0)], 0)["lines"]["frames_advance"]["ok"]
    leaking = good[:5] + [Sample(**{**s.__dict__, "threads": s.threads + 2}) for s in good[5:]]
    v = judge(plan, leaking, [(50.0, 1.0)], 0)
    assert not v["lines"]["threads_sockets_baseline"]["ok"] and not v["passed"]
    assert not judge(plan, good, [(50.0, 7.5)], 0)["lines"]["deltas_resume"]["ok"]
    assert not judge(plan, good, [(50.0, None)], 0)["lines"]["deltas_resume"]["ok"]
    assert not judge(plan, good, [(50.0, 1.0)], 3)["lines"]["camera_in_bounds"]["ok"]


def test_rss_is_compared_with_minute_two_in_an_hour_and_a_third_of_a_short_run() -> None:
    long = judge(SoakPlan.scaled(3600), _samples(361), [(360.0, 1.0)], 0)
    assert long["lines"]["rss_growth"]["reference_s"] == 120.0
    short = judge(SoakPlan.scaled(120), _samples(13), [(50.0, 1.0)], 0)
    assert short["lines"]["rss_growth"]["reference_s"] == 40.0
