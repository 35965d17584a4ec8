"""Morph schedules (server) executed by the client's schedule executor: Zach's Figures 6 and 7 and invariants.

Objects here are keyed by their level-0 representation id, k levels each:
object o has key o·K and its level l is representation o·K + l.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from client.schedule import Schedule
from server.select.morph import MorphScheduler, mark, rep_parents

TAU = 0.5
K = 5


class Pipeline:
    """The server's scheduler and the client's executor, joined as a session joins them."""

    def __init__(self, tau: float = TAU, morph: bool = True) -> None:
        self.server = MorphScheduler(tau, morph=morph)
        self.client = Schedule()
        self.tau = tau
        self.switch: float | None = None
        self.needed: list[tuple[float, dict]] = []

    def select(self, levels: dict[int, int], arrival: float) -> object:
        """Deliver the solution {object: level} for the next interval; the delta arrives at ``arrival``."""
        reset = self.switch is None
        switch = arrival if reset else self.switch + self.tau
        lead = self.tau if self.server.morph else 0.0
        while not reset and switch - lead < arrival:  # the session's rule: a schedule arrives before it starts
            switch += self.tau
        start = switch if reset else switch - lead
        key = np.array([o * K for o in levels], np.int64)
        level = np.array(list(levels.values()), np.float64)
        tr = self.server.schedule(key, level, start, switch, reset=reset)
        self.client.apply(start, switch, key, level, (tr.key, tr.level_from, tr.level_to, tr.t0, tr.t1),
                          reset=reset, now=arrival)
        self.switch = switch
        self.needed.append((arrival, {int(k): (lo, hi) for k, lo, hi in zip(tr.needed_key, tr.needed_lo, tr.needed_hi)}))
        return tr

    def level(self, o: int, t: float) -> float | None:
        d = self.client.at(t)
        hit = np.nonzero(d.key == o * K)[0]
        return float(d.level[hit[0]]) if hit.size else None


def test_monotone_up_morph_ends_at_the_end_of_its_interval():
    p = Pipeline()
    p.select({0: 1}, arrival=-0.5)  # reset
    p.select({0: 2}, arrival=-0.4)  # switch 0.5: up-morph over [0.5, 1.0)
    p.select({0: 3}, arrival=0.45)  # switch 1.0: up-morph over [1.0, 1.5)
    assert p.level(0, 0.45) == 1.0
    assert p.level(0, 0.75) == pytest.approx(1.5)
    assert p.level(0, 1.0) == pytest.approx(2.0)
    assert p.level(0, 1.25) == pytest.approx(2.5)
    assert p.level(0, 1.6) == pytest.approx(3.0)
    d = p.client.at(0.75)
    assert d.rep.tolist() == [2] and d.weight[0] == pytest.approx(0.5)  # level 2 half-way from level 1


def test_monotone_down_morph_ends_at_the_start_of_its_interval():
    p = Pipeline()
    p.select({0: 4}, arrival=-0.5)
    p.select({0: 3}, arrival=-0.1)  # switch 0.5, start 0.0: down over [0.0, 0.5)
    p.select({0: 2}, arrival=0.45)  # switch 1.0, start 0.5: down over [0.5, 1.0)
    assert p.level(0, 0.25) == pytest.approx(3.5)
    assert p.level(0, 0.5) == pytest.approx(3.0)
    assert p.level(0, 0.75) == pytest.approx(2.5)
    assert p.level(0, 1.0) == pytest.approx(2.0)


def test_alternating_up_then_down_collapses_into_one_transition():
    """Figure 7(b): forward then backward; the planned up-morph is overridden by the down-morph."""
    p = Pipeline()
    p.select({0: 2}, arrival=-0.5)
    tr = p.select({0: 4}, arrival=-0.4)  # planned: up 2 → 4 over [0.5, 1.0)
    assert tr.stats["up"] == 1
    tr = p.select({0: 1}, arrival=0.45)  # arrives before 0.5: one transition 2 → 1 over [0.5, 1.0)
    assert tr.stats["down"] == 1 and tr.stats["collapsed"] == 1
    assert tr.level_from.tolist() == [2.0] and tr.level_to.tolist() == [1.0]
    assert tr.t0.tolist() == [0.5] and tr.t1.tolist() == [1.0]
    levels = [p.level(0, t) for t in np.linspace(0.5, 1.0, 11)]
    assert all(b <= a + 1e-12 for a, b in zip(levels, levels[1:]))  # never climbs toward 4
    assert max(levels) == pytest.approx(2.0) and p.level(0, 1.0) == pytest.approx(1.0)


def test_down_then_up_needs_no_collapse():
    p = Pipeline()
    p.select({0: 3}, arrival=-0.5)
    p.select({0: 1}, arrival=-0.4)  # down 3 → 1 over [0, 0.5)
    tr = p.select({0: 4}, arrival=0.45)  # up 1 → 4 over [1.0, 1.5)
    assert tr.stats["collapsed"] == 0
    assert p.level(0, 0.5) == pytest.approx(1.0) and p.level(0, 0.9) == pytest.approx(1.0)
    assert p.level(0, 1.25) == pytest.approx(2.5) and p.level(0, 1.5) == pytest.approx(4.0)


def test_a_change_across_levels_is_a_chain_of_adjacent_morphs_within_tau():
    p = Pipeline()
    p.select({0: 0}, arrival=-0.5)
    p.select({0: 3}, arrival=-0.4)  # up 0 → 3 over [0.5, 1.0): three morphs of τ/3
    third = TAU / 3
    for j in range(3):
        d = p.client.at(0.5 + third * (j + 0.5))
        assert d.rep.tolist() == [j + 1]  # level j + 1 ...
        assert d.weight[0] == pytest.approx(0.5)  # ... half-way from level j
    assert p.client.at(1.0).rep.tolist() == [3] and p.client.at(1.0).weight[0] == 1.0


def test_forward_then_backward_returns_smoothly():
    p = Pipeline()
    levels = [0, 1, 2, 3, 4, 3, 2, 1, 0]
    arrival = -0.5
    for i, lv in enumerate(levels):
        p.select({0: lv}, arrival=arrival)
        arrival = (p.switch - 0.05)  # each delta arrives just before the next window opens
    ts = np.linspace(-0.5, p.switch + 2 * TAU, 400)
    ls = np.array([p.level(0, t) for t in ts])
    assert np.all(np.abs(np.diff(ls)) <= 4 / TAU * (ts[1] - ts[0]) + 1e-9)  # continuous
    assert ls.max() <= 4.0 and ls[-1] == pytest.approx(0.0)


def test_objects_appear_and_vanish_at_the_switch():
    p = Pipeline()
    p.select({0: 1, 1: 2}, arrival=-0.5)
    tr = p.select({1: 2, 2: 3}, arrival=-0.4)  # switch 0.5
    assert tr.stats["appear"] == 1 and tr.stats["vanish"] == 1
    assert p.level(0, 0.49) == 1.0 and p.level(0, 0.5) is None
    assert p.level(2, 0.49) is None and p.level(2, 0.5) == 3.0


def test_without_morphing_levels_switch_at_the_interval_start():
    p = Pipeline(morph=False)
    p.select({0: 1}, arrival=0.0)
    tr = p.select({0: 3}, arrival=0.1)  # switch 0.5, no window before it
    assert len(tr) == 0
    assert p.level(0, 0.49) == 1.0 and p.level(0, 0.5) == 3.0


def test_a_late_delta_ramps_from_what_is_drawn_instead_of_jumping():
    p = Pipeline()
    p.select({0: 4}, arrival=-0.5)
    p.select({0: 2}, arrival=-0.4)  # switch 0.5: down 4 → 2 over [0, 0.5)
    before = p.level(0, 0.7)
    # A delta for switch 1.0 (start 0.5) that only arrives at 0.7, past the session's rule.
    tr = p.server.schedule(np.array([0]), np.array([0.0]), 0.5, 1.0)
    p.client.apply(0.5, 1.0, np.array([0]), np.array([0.0]), (tr.key, tr.level_from, tr.level_to, tr.t0, tr.t1),
                   now=0.7)
    assert p.client.late == 1
    assert p.level(0, 0.7) == pytest.approx(before)  # no jump at arrival
    assert p.level(0, 1.0) == pytest.approx(0.0)


def test_a_delta_late_into_the_last_moment_before_its_switch_does_not_pop_at_the_switch():
    # The catch-up ramp takes at least min_ramp (0.1 s), so one begun 0.03 s before the switch runs past it;
    # the after phase must carry it on rather than start from the level the server planned for the switch.
    p = Pipeline()
    p.select({0: 4, 1: 1}, arrival=-0.5)
    p.select({0: 4, 1: 1}, arrival=-0.4)  # switch 0.5
    tr = p.server.schedule(np.array([0, K]), np.array([1.0, 3.0]), 0.5, 1.0)  # 0 down 4 → 1, 1 up 1 → 3
    p.client.apply(0.5, 1.0, np.array([0, K]), np.array([1.0, 3.0]),
                   (tr.key, tr.level_from, tr.level_to, tr.t0, tr.t1), now=0.97)
    assert p.client.late == 1
    ts = np.arange(0.96, 1.6, 0.005)
    for o, last in ((0, 1.0), (1, 3.0)):
        lv = np.array([p.level(o, t) for t in ts])
        assert np.abs(np.diff(lv)).max() <= 3 / p.client.min_ramp * 0.005 + 1e-9  # never faster than the catch-up
        assert lv[-1] == pytest.approx(last)  # and still where the server planned
    assert p.level(0, 0.97) == pytest.approx(4.0) and p.level(0, 0.97 + p.client.min_ramp) == pytest.approx(1.0)
    assert p.level(1, 1.0) == pytest.approx(1.0) and p.level(1, 1.5) == pytest.approx(3.0)  # its up-morph as planned


def test_a_reset_delta_is_drawn_from_its_arrival_even_if_its_switch_is_ahead_of_the_clock():
    # The server's switch is its estimate of the client's clock; before the clock sync settles it can run ahead.
    s = Schedule()
    s.apply(0.8, 0.8, np.array([0, K]), np.array([1.0, 2.0]), reset=True, now=0.5)
    assert s.at(0.5).key.tolist() == [0, K] and s.at(0.5).level.tolist() == [1.0, 2.0]
    assert s.late == 0
    # A teleport's reset replaces what is drawn at once too, not at its switch.
    s.apply(1.5, 1.5, np.array([2 * K]), np.array([3.0]), reset=True, now=1.2)
    assert s.at(1.2).key.tolist() == [2 * K] and s.at(1.2).level.tolist() == [3.0]


def test_marking_finds_up_and_down_transitions_across_hierarchies():
    # Two objects: 0 (3 levels, reps 0..2) is the HLOD parent of object 1 (2 levels, reps 3..4).
    parent = rep_parents(np.array([0, 1, 2, 0, 1]), np.array([0, 0, 0, 1, 1]), np.array([-1, 0]),
                         np.array([0, 3]), np.array([3, 2]))
    assert parent.tolist() == [-1, 0, 1, 2, 3]
    kind, source = mark(parent, black=np.array([1]), new=np.array([4]))
    assert kind.tolist() == [1] and source.tolist() == [1]  # a finer node below a black one: up
    kind, source = mark(parent, black=np.array([4]), new=np.array([1]))
    assert kind.tolist() == [-1]  # grey: an ancestor of a black node: down
    kind, _ = mark(parent, black=np.array([1]), new=np.array([1]))
    assert kind.tolist() == [0]


@st.composite
def solutions(draw):
    n = draw(st.integers(1, 6))
    steps = draw(st.integers(2, 9))
    sols = []
    for _ in range(steps):
        chosen = draw(st.lists(st.integers(0, n - 1), unique=True, max_size=n))
        sols.append({o: draw(st.integers(0, K - 1)) for o in chosen})
    lateness = draw(st.lists(st.floats(0.01, 0.49), min_size=steps, max_size=steps))
    return sols, lateness


@settings(max_examples=150, deadline=None)
@given(solutions())
def test_schedules_keep_resident_continuous_and_within_budget(case):
    """From the schedule alone: only needed (resident) reps drawn, weights continuous, budget held."""
    sols, lead = case
    cost = np.array([2.0 ** lv for lv in range(K)])  # a morph costs its finer level
    budget = max([sum(cost[lv] for lv in s.values()) for s in sols] + [0.0])
    p = Pipeline()
    arrivals = []
    for i, s in enumerate(sols):
        arrival = 0.0 if i == 0 else (p.switch - lead[i] * TAU * 0.99)  # before the next window opens
        arrival = max(arrival, arrivals[-1] if arrivals else 0.0)
        p.select(s, arrival=arrival)
        arrivals.append(arrival)
    assert p.client.late == 0
    ts = np.linspace(0.0, p.switch + 2 * TAU, 600)
    prev: dict[int, float] = {}
    dt = ts[1] - ts[0]
    for t in ts:
        d = p.client.at(t)
        # Which delta's keep-set applies: the newest that has arrived by t.
        needed = [nd for a, nd in p.needed if a <= t][-1]
        drawn_cost = 0.0
        for key, level, rep, w in zip(d.key.tolist(), d.level.tolist(), d.rep.tolist(), d.weight.tolist()):
            lo, hi = needed[key]
            lv = rep - key
            assert lo - 1e-9 <= lv <= hi + 1e-9, (t, key, lv, lo, hi)
            if w < 1:
                assert lv - 1 >= lo - 1e-9  # the level it morphs from is resident too
            drawn_cost += cost[lv]
            if key in prev:
                assert abs(level - prev[key]) <= (K - 1) / TAU * dt + 1e-9  # no jump
        assert drawn_cost <= budget + 1e-9
        prev = dict(zip(d.key.tolist(), d.level.tolist()))


@st.composite
def _forest_and_solutions(draw):
    m = draw(st.integers(1, 40))
    parent = np.array([draw(st.integers(-1, i - 1)) for i in range(m)], np.int64)
    black = np.array(draw(st.lists(st.integers(0, m - 1), unique=True, max_size=m)), np.int64)
    new = np.array(draw(st.lists(st.integers(0, m - 1), unique=True, max_size=m)), np.int64)
    return parent, black, new


@settings(max_examples=150, deadline=None)
@given(solutions(), st.lists(st.floats(0.0, 0.99), min_size=9, max_size=9))
def test_late_deltas_never_make_a_level_jump(case, late):
    """Deltas arriving anywhere in their window, or a little past their switch, ramp from what is drawn: no
    level moves faster than the steepest ramp (a catch-up of K − 1 levels over min_ramp)."""
    sols, _ = case
    p = Pipeline()
    p.select(sols[0], arrival=0.0)
    dt = 0.002
    bound = (K - 1) / p.client.min_ramp * dt + 1e-9
    prev: dict[int, float] = {}
    t = arrival = 0.0

    def draw_until(end: float) -> None:
        nonlocal t, prev
        while t < end:
            d = p.client.at(t)
            now = dict(zip(d.key.tolist(), d.level.tolist()))
            for k in now.keys() & prev.keys():
                assert abs(now[k] - prev[k]) <= bound, (t, k, prev[k], now[k])
            prev, t = now, t + dt

    for s, f in zip(sols[1:], late):
        switch, start = p.switch + TAU, p.switch
        arrival = max(arrival, start + f * 1.2 * TAU)  # up to 0.1 τ past the switch
        draw_until(arrival)
        key = np.array([o * K for o in s], np.int64)
        level = np.array(list(s.values()), np.float64)
        tr = p.server.schedule(key, level, start, switch)
        p.client.apply(start, switch, key, level, (tr.key, tr.level_from, tr.level_to, tr.t0, tr.t1), now=t)
        p.switch = switch
    draw_until(p.switch + 2 * TAU)


@settings(max_examples=150, deadline=None)
@given(_forest_and_solutions())
def test_marking_equals_its_definition(case):
    """Up-morph from the nearest black ancestor; down-morph when an ancestor of a black rep (grey), not black."""
    parent, black, new = case

    def ancestors(r):
        out, a = [], parent[r]
        while a >= 0:
            out.append(int(a))
            a = parent[a]
        return out

    blacks = set(black.tolist())
    grey = {a for b in blacks for a in ancestors(b)}
    kind, source = mark(parent, black, new)
    for r, k, s in zip(new.tolist(), kind.tolist(), source.tolist()):
        up = next((a for a in ancestors(r) if a in blacks), -1)
        assert s == up
        assert k == (-1 if r in grey and r not in blacks else 1 if up >= 0 else 0)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 30), st.floats(0, 5), st.floats(0, 5)), max_size=40),
       st.lists(st.tuples(st.integers(0, 30), st.floats(0, 5), st.floats(0, 5)), max_size=40))
def test_needed_union_keeps_the_widest_range_per_key(a, b):
    def table(rows):
        return (np.array([r[0] for r in rows], np.int64), np.array([r[1] for r in rows], float),
                np.array([r[2] for r in rows], float))

    key, lo, hi = MorphScheduler._union(table(a), table(b))
    want = {}
    for k, l, h in a + b:
        w = want.get(k, (np.inf, -np.inf))
        want[k] = (min(w[0], l), max(w[1], h))
    assert key.tolist() == sorted(want)
    assert [(x, y) for x, y in zip(lo.tolist(), hi.tolist())] == [want[k] for k in sorted(want)]
