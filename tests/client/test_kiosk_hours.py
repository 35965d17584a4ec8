"""Opening hours: open and closed across midnight, the closed screen and its fade, the nightly restart."""

from __future__ import annotations

from datetime import datetime, timedelta, timezone

import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from client.kiosk.hours import DIM, DIM_RATE, FADE_S, Hours, Screen

hhmm = st.builds(lambda h, m: f"{h:02d}:{m:02d}", st.integers(0, 23), st.integers(0, 59))
moments = st.datetimes(min_value=datetime(2000, 1, 1), max_value=datetime(2100, 1, 1))


def _minutes(s: str) -> int:
    return int(s[:2]) * 60 + int(s[3:])


def _reference_open(open_: str, close: str, now: datetime) -> bool:
    """The rule as a person states it: open from the open time until the close time, maybe past midnight."""
    o, c, t = _minutes(open_) * 60, _minutes(close) * 60, now.hour * 3600 + now.minute * 60 + now.second
    if o == c:
        return True
    if o < c:
        return o <= t < c
    return t >= o or t < c


@given(hhmm, hhmm, moments)
def test_open_is_the_interval_from_open_to_close_even_past_midnight(open_: str, close: str, now: datetime) -> None:
    assert Hours(open_, close).is_open(now) == _reference_open(open_, close, now)


@given(hhmm, moments)
def test_open_equal_to_close_is_always_open_at_full_brightness(t: str, now: datetime) -> None:
    hours = Hours(t, t, closed="black")
    assert hours.is_open(now) and hours.screen(now) == Screen(True, 1.0, 1.0)


@given(hhmm, hhmm, st.dates(min_value=datetime(2000, 1, 1).date(), max_value=datetime(2099, 1, 1).date()))
def test_a_day_is_open_for_exactly_the_span_from_open_to_close(open_: str, close: str, day) -> None:
    assume(open_ != close)
    hours = Hours(open_, close)
    start = datetime.combine(day, datetime.min.time())
    minutes_open = sum(hours.is_open(start + timedelta(minutes=m)) for m in range(24 * 60))
    assert minutes_open == (_minutes(close) - _minutes(open_)) % (24 * 60)


@given(hhmm, hhmm, st.sampled_from(["dim", "black"]), moments)
def test_the_screen_is_full_when_open_and_the_closed_look_when_closed_once_faded(
        open_: str, close: str, closed: str, now: datetime) -> None:
    assume(open_ != close)
    hours = Hours(open_, close, closed=closed)
    s = hours.screen(now)
    low = (DIM, DIM_RATE) if closed == "dim" else (0.0, 0.0)
    assert s.open == hours.is_open(now)
    assert low[0] <= s.brightness <= 1.0 and low[1] <= s.rate <= 1.0
    boundary = _minutes(open_ if s.open else close) * 60
    since = (now.hour * 3600 + now.minute * 60 + now.second + now.microsecond / 1e6 - boundary) % 86_400
    if since >= FADE_S:
        assert (s.brightness, s.rate) == ((1.0, 1.0) if s.open else low)
    assert hours.brightness(now) == s.brightness


@given(st.sampled_from(["dim", "black"]), st.floats(0, 2 * FADE_S))
def test_the_fade_moves_steadily_from_one_look_to_the_other(closed: str, after: float) -> None:
    hours = Hours("09:00", "18:00", closed=closed)
    at_close = datetime(2024, 5, 1, 18, 0)
    low = DIM if closed == "dim" else 0.0
    going = hours.brightness(at_close + timedelta(seconds=after))
    assert going == pytest.approx(1.0 + min(1.0, after / FADE_S) * (low - 1.0), abs=1e-6)  # µs-resolved times
    coming = hours.brightness(at_close.replace(hour=9) + timedelta(seconds=after))
    assert coming == pytest.approx(low + min(1.0, after / FADE_S) * (1.0 - low), abs=1e-6)


@given(hhmm, moments, st.floats(0, 3 * 86_400))
def test_the_restart_falls_due_once_its_hour_has_come_round_since_the_start(
        at: str, started: datetime, later: float) -> None:
    hours = Hours(restart_at=at)
    due = hours.next_restart(started)
    assert due is not None and started < due <= started + timedelta(days=1)
    assert (due.hour, due.minute, due.second) == (int(at[:2]), int(at[3:]), 0)
    now = started + timedelta(seconds=later)
    assert hours.restart_due(started, now) == (now >= due)
    assert not hours.restart_due(started, started)  # a kiosk started at its restart hour does not loop
    assert hours.restart_due(started, started + timedelta(days=1))


@given(moments, st.floats(0, 3 * 86_400))
def test_no_restart_hour_never_restarts(started: datetime, later: float) -> None:
    assert not Hours().restart_due(started, started + timedelta(seconds=later))
    assert Hours().next_restart(started) is None


def test_aware_times_count_in_their_own_wall_clock() -> None:
    cet = timezone(timedelta(hours=1))
    hours = Hours("09:00", "18:00", restart_at="03:30")
    assert hours.is_open(datetime(2024, 1, 5, 9, 30, tzinfo=cet))
    assert not hours.is_open(datetime(2024, 1, 5, 8, 30, tzinfo=timezone.utc))  # 09:30 in CET, but its own wall time
    started = datetime(2024, 1, 5, 12, 0, tzinfo=cet)
    assert hours.next_restart(started) == datetime(2024, 1, 6, 3, 30, tzinfo=cet)


@pytest.mark.parametrize("kw, field", [
    ({"open": "9:00"}, "open"), ({"close": "24:00"}, "close"), ({"open": "12:60"}, "open"),
    ({"closed": "grey"}, "closed"), ({"restart_at": "3"}, "restart_at"), ({"close": " 18:00"}, "close"),
])
def test_bad_values_are_refused_naming_the_field(kw: dict, field: str) -> None:
    with pytest.raises(ValueError, match=f"^{field}: "):
        Hours(**kw)
