"""The frame governor: every frame, the server's selection corrected along the delta's ladder to fit the target.

The server selects every τ for an interval a round trip ahead; between two
selections the view changes, and so does the machine's speed. The client knows
its own frames exactly and at once, so it corrects the plan every frame, F&S's
incremental step run locally: each delta's ladder (``server.select.ladder``)
offers, per selected object, a step down to the next coarser resident level and
a step up to a finer one sent ahead, each with its cost change (model seconds)
and its value (benefit per second). The steps, sorted by value (a step up never
before its object's step down: values are made concave per object), form one
list; a state is a prefix of it. Each frame the governor predicts the frame's
time as the time per unit of drawn model cost measured over the last frame times
the units of a state, then takes decrements of lowest value until the prediction
fits its aim (a share of the target), or increments of highest value while it
fits (outside a band around the aim, so noise does not make it chatter; and none
while a decrement is still ramping).

A change is never drawn at once: each object's offset from the plan ramps over
``ramp`` seconds (a change of two levels as a chain of two adjacent morphs), drawn
as the schedule's geomorph between adjacent levels, so nothing pops.

Pure numpy, no clocks: the caller passes client times and measured frame times.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Governor", "GovernorLadder", "RAMP"]

#: Seconds a governor change takes by default: two frames at a 50 ms target, so a step change of the
#: machine is absorbed within three frames, and well within the quarter second that keeps it from popping.
RAMP = 0.1


@dataclass(frozen=True)
class GovernorLadder:
    """One delta's ladder per object key, in the governor's terms.

    t0 : client time from which it governs (the delta's switch)
    key : (n,) sorted unique object keys with at least one step
    down_cost, up_cost : (n,) model seconds saved / spent by the step (0 where there is none)
    has_down, has_up : (n,) bool
    rank_down, rank_up : (n,) each key's step's place among all steps, highest value first (int64 max: none)
    cum : (k + 1,) running cost of the steps in that order (cum[m]: the first m taken)
    fixed : model seconds of the all-coarse state (the selection less every step down)
    base : model seconds of the selection as planned
    lo, hi : (n,) the levels the key's steps reach (the selected level less its step down, plus its step up)
    """

    t0: float
    key: np.ndarray
    down_cost: np.ndarray
    up_cost: np.ndarray
    has_down: np.ndarray
    has_up: np.ndarray
    rank_down: np.ndarray
    rank_up: np.ndarray
    cum: np.ndarray
    fixed: float
    base: float
    lo: np.ndarray
    hi: np.ndarray

    @classmethod
    def build(cls, t0: float, key: np.ndarray, step: np.ndarray, cost: np.ndarray, value: np.ndarray,
              base: float, level: np.ndarray | None = None) -> "GovernorLadder":
        """From a delta's steps: ``key`` (k,) object keys, ``step`` (k,) −1 down / +1 up, ``cost`` and ``value``;
        ``level`` (k,) the selected level each starts from (None: the levels are not bounded)."""
        key = np.asarray(key, np.int64)
        step = np.asarray(step, np.int64)
        cost = np.asarray(cost, np.float64)
        value = np.asarray(value, np.float64)
        keys = np.unique(key)
        n = keys.size
        idx = np.searchsorted(keys, key)
        down, up = step < 0, step > 0
        has_down, has_up = np.zeros(n, bool), np.zeros(n, bool)
        down_cost, up_cost = np.zeros(n), np.zeros(n)
        down_value, up_value = np.full(n, np.inf), np.zeros(n)
        has_down[idx[down]], down_cost[idx[down]], down_value[idx[down]] = True, cost[down], value[down]
        has_up[idx[up]], up_cost[idx[up]], up_value[idx[up]] = True, cost[up], value[up]
        # Concave per object: its step up is worth at most its step down, so a prefix never takes it first.
        up_value = np.minimum(up_value, down_value)
        ki = np.concatenate([np.nonzero(has_down)[0], np.nonzero(has_up)[0]])
        is_up = np.concatenate([np.zeros(int(has_down.sum()), bool), np.ones(int(has_up.sum()), bool)])
        v = np.where(is_up, up_value[ki], down_value[ki])
        c = np.where(is_up, up_cost[ki], down_cost[ki])
        order = np.lexsort((is_up, -v))
        rank = np.empty(order.size, np.int64)
        rank[order] = np.arange(order.size)
        big = np.iinfo(np.int64).max
        rank_down, rank_up = np.full(n, big), np.full(n, big)
        rank_down[ki[~is_up]] = rank[~is_up]
        rank_up[ki[is_up]] = rank[is_up]
        cum = np.concatenate([[0.0], np.cumsum(c[order])])
        fixed = float(base) - float(down_cost.sum())
        if level is None:
            lo, hi = np.full(n, -np.inf), np.full(n, np.inf)
        else:
            sel = np.zeros(n)
            sel[idx] = np.asarray(level, np.float64)
            lo, hi = sel - has_down, sel + has_up
        return cls(float(t0), keys, down_cost, up_cost, has_down, has_up, rank_down, rank_up, cum, fixed,
                   float(base), lo, hi)

    def offsets(self, m: int) -> np.ndarray:
        """(n,) level offset from the plan of each key in the state that takes the first ``m`` steps."""
        return np.where(self.has_down, (self.rank_down < m).astype(np.float64) - 1.0, 0.0) + (self.rank_up < m)

    @property
    def plan_steps(self) -> int:
        """The prefix closest in cost to the plan (every step down taken, none up)."""
        target = self.base - self.fixed
        return int(np.clip(np.searchsorted(self.cum, target + 1e-12, side="right") - 1, 0, self.cum.size - 1))


class Governor:
    """Per-frame correction of the drawn levels along the current ladder.

    target : frame time to hold (s); ramp : seconds a change of one level takes (≤ 0.25 s);
    aim : share of the target the predicted frame is steered to (below 1: a frame's own noise is then
    less often over the target); slack : the band around the aim within which the state is kept
    (± slack × aim), so noise does not make it chatter.
    """

    def __init__(self, target: float, ramp: float = RAMP, aim: float = 0.97, slack: float = 0.03,
                 tail: float = 1.05, window: int = 32) -> None:
        if not (target > 0 and 0 < ramp <= 0.25 and 0 < aim <= 1 and 0 <= slack < 1 and aim * (1 + slack) <= 1
                and 1.0 <= tail <= 1.5 and window >= 8):
            raise ValueError(f"bad governor settings target={target} ramp={ramp} aim={aim} slack={slack} "
                             f"tail={tail} window={window}")
        self.target, self.ramp, self.aim, self.slack = float(target), float(ramp), float(aim), float(slack)
        # The aim follows the predictor's measured error: measured ÷ predicted time of the last ``window``
        # frames; steering to tail ÷ their 95th percentile keeps the 95th-percentile frame near tail × target
        # on a machine whose frames scatter, and to ``aim`` where they do not.
        self.tail = float(tail)
        self.ratios = np.full(int(window), np.nan)
        self.seen = 0
        self.rates = np.zeros(0)
        self.pending: list[GovernorLadder] = []
        self.ladder: GovernorLadder | None = None
        self.m = 0
        self.rate: float | None = None  # measured seconds per unit of drawn model cost (the predictor)
        self.units = 0.0  # model seconds of what the last ``apply`` drew
        self.predicted = 0.0  # its predicted time
        self.down = self.up = 0  # objects the last ``apply`` drew coarser / finer than the plan
        self.gkey = np.zeros(0, np.int64)  # keys with an offset, sorted
        self.g = np.zeros(0)  # their drawn offsets (continuous levels)
        self.goal = np.zeros(0)  # the offsets they ramp to
        self.speed = np.zeros(0)  # levels per second of their ramps: each change takes ``ramp`` seconds
        self.lo = np.zeros(0)  # the levels their steps reach: a governed level stays within them, or within
        self.hi = np.zeros(0)  # where the schedule's own ramp has it
        self.t: float | None = None

    # ------------------------------------------------------------------ inputs

    def take(self, ladder: GovernorLadder, reset: bool = False) -> None:
        """A delta's ladder, governing from its ``t0`` (a reset one replaces what is pending)."""
        if reset:
            self.pending = []
        self.pending = [p for p in self.pending if p.t0 < ladder.t0] + [ladder]

    def observe(self, time: float) -> None:
        """The measured time of the frame the last ``apply`` drew."""
        if self.units > 0 and time > 0 and np.isfinite(time):
            if self.predicted > 0:
                self.ratios[self.seen % self.ratios.size] = float(time) / self.predicted
                self.seen += 1
            # The predictor: the median of the last three frames' time per unit drawn — one slow frame alone
            # does not move it, two in a row do (a machine that slowed is followed within three frames).
            self.rates = np.concatenate([self.rates[-2:], [float(time) / self.units]])
            self.rate = float(np.median(self.rates))

    @property
    def steer(self) -> float:
        """The share of the target the predicted frame is steered to now."""
        if self.seen < 8:
            return self.aim
        q = float(np.nanquantile(self.ratios, 0.95))
        return float(np.clip(self.tail / max(q, 1e-9), 0.5, self.aim))

    # ------------------------------------------------------------------ per frame

    def _switch(self, t: float) -> None:
        while self.pending and self.pending[0].t0 <= t:
            lad = self.pending.pop(0)
            keep = self.g != 0
            keys = np.union1d(lad.key, self.gkey[keep])
            g, goal, speed = np.zeros(keys.size), np.zeros(keys.size), np.full(keys.size, 1.0 / self.ramp)
            lo, hi = np.full(keys.size, -np.inf), np.full(keys.size, np.inf)
            at = np.searchsorted(keys, self.gkey[keep])
            g[at], goal[at], speed[at] = self.g[keep], self.goal[keep], self.speed[keep]
            lo[at], hi[at] = self.lo[keep], self.hi[keep]
            new = np.searchsorted(keys, lad.key)
            # A key still off its plan keeps the levels its old steps reached until it is back (they stay
            # resident that long): a bound that shrank at once would make its level jump.
            moving = g[new] != 0
            lo[new] = np.where(moving, np.minimum(lo[new], lad.lo), lad.lo)
            hi[new] = np.where(moving, np.maximum(hi[new], lad.hi), lad.hi)
            self.gkey, self.g, self.goal, self.speed, self.ladder = keys, g, goal, speed, lad
            self.lo, self.hi = lo, hi
            self.m = lad.plan_steps

    def _decide(self, lad: GovernorLadder, ramping_down: bool) -> int:
        """The number of steps to take: shrink to the aim when the prediction is above its band, grow to it
        when below (and no decrement is still ramping), else stay."""
        if self.rate is None or self.rate <= 0:
            return self.m
        cap = self.target / self.rate  # model seconds that fit in the target
        cum, m = lad.cum, min(self.m, lad.cum.size - 1)
        now = lad.fixed + cum[m]
        aim = self.steer
        fit = int(max(np.searchsorted(cum, aim * cap - lad.fixed, side="right") - 1, 0))
        if now > (1.0 + self.slack) * aim * cap:
            return fit
        if now < (1.0 - self.slack) * aim * cap and not ramping_down:
            return max(fit, m)
        return m

    def apply(self, t: float, key: np.ndarray, level: np.ndarray) -> np.ndarray:
        """(s,) the levels to draw at client time ``t`` for the schedule's ``key`` (s,) at ``level`` (s,)."""
        dt = 0.0 if self.t is None else max(float(t) - self.t, 0.0)
        self.t = float(t)
        self._switch(t)
        lad = self.ladder
        key = np.asarray(key, np.int64)
        level = np.asarray(level, np.float64)
        if lad is None or self.gkey.size == 0:
            self.units, self.down, self.up = (lad.base if lad is not None else 0.0), 0, 0
            self.predicted = 0.0 if self.rate is None else self.rate * self.units
            return level
        # Target offset of every key with one: the state's for the ladder's keys, 0 for the rest.
        li = np.searchsorted(lad.key, self.gkey)
        li_c = np.minimum(li, max(lad.key.size - 1, 0))
        if lad.key.size:
            on = (li < lad.key.size) & (lad.key[li_c] == self.gkey)
            planned = np.where(on, lad.offsets(self.m)[li_c], 0.0)
        else:  # an empty ladder: every key ramps back to the plan
            on, li_c, planned = np.zeros(self.gkey.size, bool), np.zeros(self.gkey.size, np.int64), 0.0
        ramping_down = bool((self.g > planned + 1e-9).any())
        self.m = self._decide(lad, ramping_down)
        # Until a frame is measured there is nothing to correct the plan with: it is drawn as it is.
        goal = np.zeros(self.g.size)
        if self.rate is not None and lad.key.size:
            goal = np.where(on, lad.offsets(self.m)[li_c], 0.0)
        # A new goal starts a ramp that takes ``ramp`` seconds: two levels at once go as a chain of adjacent
        # morphs at twice the speed (Zach's chains), so a shrink is drawn within one ramp whatever it undoes.
        moved = goal != self.goal
        self.speed = np.where(moved, np.maximum(np.abs(goal - self.g), 1.0) / self.ramp, self.speed)
        self.goal = goal
        step = dt * self.speed
        self.g = self.g + np.clip(goal - self.g, -step, step)
        near = np.abs(self.g - goal) < 1e-9
        self.g[near] = goal[near]
        # What is drawn: a key partly down still draws its selected level, partly up the finer one.
        g_on = self.g[on]
        idx = li[on]
        full_down = g_on <= -1.0 + 1e-9
        some_up = g_on > 1e-9
        self.units = lad.base - float(lad.down_cost[idx][full_down].sum()) + float(lad.up_cost[idx][some_up].sum())
        self.down = int((g_on < -1e-9).sum() + (self.g[~on] < -1e-9).sum())
        self.up = int((g_on > 1e-9).sum() + (self.g[~on] > 1e-9).sum())
        self.predicted = 0.0 if self.rate is None else self.rate * self.units
        settled = self.g == 0
        if settled.any() and not on[settled].all():  # forget keys that left the ladder and came back to plan
            drop = settled & ~on
            self.gkey, self.g, self.goal, self.speed, self.lo, self.hi = (
                a[~drop] for a in (self.gkey, self.g, self.goal, self.speed, self.lo, self.hi))
        pos = np.searchsorted(self.gkey, key)
        pos_c = np.minimum(pos, max(self.gkey.size - 1, 0))
        if not self.gkey.size:
            return level
        hit = (pos < self.gkey.size) & (self.gkey[pos_c] == key)
        # Within the levels the steps reach (resident, with their morph targets), or the schedule's own level
        # where its ramp lies outside them: a bound that moves with the level, so nothing jumps.
        lo = np.minimum(level, np.where(hit, self.lo[pos_c], -np.inf))
        hi = np.maximum(level, np.where(hit, self.hi[pos_c], np.inf))
        drawn = np.maximum(np.clip(level + np.where(hit, self.g[pos_c], 0.0), lo, hi), 0.0)
        # The offset is what was drawn, not what the bound cut off: a bound that widens later (a new ladder
        # reaching a level further down) then starts a ramp from here instead of showing the rest at once.
        self.g[pos_c[hit]] = drawn[hit] - level[hit]
        return drawn

    def hold(self, key: np.ndarray, offset: np.ndarray) -> None:
        """The rows of ``key`` were drawn at ``offset`` from the plan instead (what the caller could draw):
        their ramps go on from there."""
        pos = np.searchsorted(self.gkey, np.asarray(key, np.int64))
        pos_c = np.minimum(pos, max(self.gkey.size - 1, 0))
        hit = (pos < self.gkey.size) & (self.gkey[pos_c] == key) if self.gkey.size else np.zeros(pos.size, bool)
        self.g[pos_c[hit]] = np.asarray(offset, np.float64)[hit]
