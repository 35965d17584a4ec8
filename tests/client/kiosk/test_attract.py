"""The attract machine: its invariants under any input schedule, and the WCAG countdown."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from client.kiosk.attract import ATTRACT, COUNTDOWN, VISITOR, AttractMachine, reported_state
from proto.messages import KIOSK_STATES

events = st.lists(st.tuples(st.floats(0.0, 60.0), st.booleans()), max_size=60)


@settings(max_examples=300, deadline=None)
@given(st.floats(0.5, 120.0), st.floats(0.5, 60.0), events)
def test_invariants_hold_under_any_input(idle_s, countdown_s, schedule):
    m = AttractMachine(idle_s, countdown_s, now=0.0)
    now = 0.0
    for dt, touched in schedule:
        now += dt
        before, last = m.state, m.last_input
        out = m.input(now) if touched else m.tick(now)
        assert m.state in KIOSK_STATES[:3]
        if touched:  # input always leads to the visitor, at once
            assert m.state == VISITOR and m.last_input == now
        # Never counting down without idle_s of no input, never back in attract before the countdown ran out.
        if m.state == COUNTDOWN:
            assert m.last_input is not None and now - m.last_input >= idle_s
            assert now - m.last_input < idle_s + countdown_s
            assert 0 < m.seconds_left(now) <= countdown_s + 1
        if m.state == ATTRACT and m.last_input is not None:
            assert now - m.last_input >= idle_s + countdown_s
        if m.state == VISITOR:
            assert now - m.last_input < idle_s
        # Transitions only ever go round the cycle, and each at the exact time it was due.
        order = [ATTRACT, VISITOR, COUNTDOWN]
        state = before
        for entered, at in out:
            if entered == VISITOR:
                assert at == now
            else:
                assert entered == order[(order.index(state) + 1) % 3]
                assert at == pytest.approx(last + (idle_s if entered == COUNTDOWN else idle_s + countdown_s))
            state = entered
        assert state == m.state


def test_the_countdown_shows_the_seconds_left_and_input_cancels_it():
    m = AttractMachine(90.0, 20.0, now=0.0)
    assert m.tick(500.0) == [] and m.state == ATTRACT  # nobody came: the attract loop goes on
    assert m.input(500.0) == [(VISITOR, 500.0)]
    assert m.tick(589.9) == [] and m.seconds_left(589.9) is None
    assert m.tick(590.0) == [(COUNTDOWN, 590.0)] and m.seconds_left(590.0) == 20
    assert m.seconds_left(599.5) == 11
    assert m.input(600.0) == [(VISITOR, 600.0)]  # a touch: back to the visitor, the countdown gone
    assert m.tick(689.0) == [] and m.state == VISITOR
    # A late tick (a stalled frame) still makes both steps, at their exact times.
    assert m.tick(800.0) == [(COUNTDOWN, 690.0), (ATTRACT, 710.0)]


def test_what_the_heartbeat_reports():
    assert reported_state(VISITOR, link_up=True, open_now=True) == VISITOR
    assert reported_state(VISITOR, link_up=False, open_now=True) == "reconnecting"
    assert reported_state(ATTRACT, link_up=False, open_now=False) == "closed"
