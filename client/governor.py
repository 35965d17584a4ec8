"""The frame governor: every frame, the server's selection corrected along the delta's ladder to fit the target.

The server selects every τ for an interval a round trip ahead; between two
selections the view changes, and so does the machine's speed. The client knows
its own frames exactly and at once, so it corrects the plan every frame, F&S's
incremental step run locally: each delta's ladder (``server.select.ladder``)
offers, per selected object, a chain of unit steps down through the coarser
levels it holds and up through the finer ones sent ahead, each with its cost
change (vertices) and its value (benefit per vertex). The steps, sorted by
value (values are made concave along each chain, so a finer increment never
comes before a coarser one of the same object), form one list; a state is a
prefix of it. Each frame the governor predicts the frame's time from the units
(vertices) of a state (``FramePredictor``: the time per unit measured over its
last frames, with the frame's fixed part where that is measured to predict
better) — the units the renderer counts for the last frame's levels from the
camera about to draw (``expect``), changed by what the state's steps add or
remove on the objects in view — then takes decrements of lowest value until the
prediction fits its aim (a share of the target), or increments of highest value
while it fits (outside a band around the aim, so noise does not make it chatter).

A change is never drawn at once: each object's offset from the plan ramps over
``ramp`` seconds (a change of two levels or more as a chain of adjacent morphs,
at most two levels per ramp), drawn as the schedule's geomorph between adjacent
levels, so nothing pops; a new delta's plan starts each object where the last
frame drew it.

Pure numpy, no clocks: the caller passes client times and measured frame times.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .frame_predictor import FramePredictor
from .hold import STRICT, Hold, Ledger

__all__ = ["Governor", "GovernorLadder", "RAMP"]

#: Seconds a governor change takes by default: two frames at a 50 ms target, so a step change of the
#: machine is absorbed within three frames, and well within the quarter second that keeps it from popping.
RAMP = 0.1

#: Frames predicted under this share of the target do not teach the aim. Such a frame goes over the line only by
#: a stall (more than four times its prediction), which no aim prevents, while its time is mostly fixed per-frame
#: costs that scatter more, relatively, than a frame near the target does. (A stretch of cheap frames — a view of almost
#: nothing — filled the window with their ratios and held the aim at its floor until as many frames near the
#: target had replaced them.)
NEAR = 0.25


@dataclass(frozen=True)
class GovernorLadder:
    """One delta's ladder per object key, in the governor's terms.

    Each key's steps are unit increments along its chain, from its coarsest offered level up: a step down of
    depth d is the increment from level L − d to L − d + 1 (``pos`` 1 − d), a step up of depth u the one from
    L + u − 1 to L + u (``pos`` u), L the selected level. A state takes a prefix of all steps by value,
    highest first; values are made non-increasing along each chain, so a prefix takes a key's increments in
    chain order and a key's level is L − (its steps down) + (its steps taken).

    t0 : client time from which it governs (the delta's switch)
    key : (n,) sorted unique object keys with at least one step
    n_down : (n,) steps down each key offers (its chain's depth below the selected level)
    step_key : (k,) the key index of each step; pos : (k,) its place in its chain (above); cost : (k,) vertices
    rank : (k,) its place among all steps, highest value first
    cum : (k + 1,) running cost of the steps in that order (cum[m]: the first m taken)
    fixed : vertices of the all-coarse state (the selection less every step down)
    base : vertices of the selection as planned
    lo, hi : (n,) the levels the key's steps reach (its selected level less its steps down, plus its steps up)
    """

    t0: float
    key: np.ndarray
    n_down: np.ndarray
    step_key: np.ndarray
    pos: np.ndarray
    cost: np.ndarray
    rank: np.ndarray
    cum: np.ndarray
    fixed: float
    base: float
    lo: np.ndarray
    hi: np.ndarray
    _offsets: dict = field(default_factory=dict, compare=False, repr=False)  # m → offsets(m), the last few; tables

    @classmethod
    def build(cls, t0: float, key: np.ndarray, step: np.ndarray, cost: np.ndarray, value: np.ndarray,
              base: float, level: np.ndarray | None = None) -> "GovernorLadder":
        """From a delta's steps: ``key`` (k,) object keys, ``step`` (k,) the signed depth each reaches (−d down,
        +u up; a chain must be contiguous from ±1, a step beyond a gap is left out), ``cost`` and ``value``;
        ``level`` (k,) the selected level its chain starts from (None: the levels are not bounded)."""
        key = np.asarray(key, np.int64)
        step = np.asarray(step, np.int64)
        cost = np.asarray(cost, np.float64)
        value = np.asarray(value, np.float64)
        keys = np.unique(key)
        n = keys.size
        idx = np.searchsorted(keys, key)
        # Contiguous chains only: sorted by (key, direction, depth), the j-th step of a chain has depth j + 1.
        depth = np.abs(step)
        order = np.lexsort((depth, step > 0, idx))
        group = idx[order] * 2 + (step[order] > 0)
        first = np.concatenate([[True], group[1:] != group[:-1]]) if order.size else np.zeros(0, bool)
        start = np.maximum.accumulate(np.where(first, np.arange(order.size), 0)) if order.size else first
        keep = np.zeros(step.size, bool)
        keep[order] = (depth[order] == np.arange(order.size) - start + 1) & (depth[order] > 0)
        idx, step, cost, value = idx[keep], step[keep], cost[keep], value[keep]
        pos = np.where(step < 0, 1 + step, step)
        down = step < 0
        n_down = np.bincount(idx[down], minlength=n).astype(np.int64)
        n_up = np.bincount(idx[~down], minlength=n).astype(np.int64)
        # Concave per key: along its chain from the coarsest increment up, values never rise, so a prefix by
        # value takes a key's increments in order (a finer one never before a coarser).
        if idx.size:
            lo_pos = int(pos.min())
            grid = np.full((n, int(pos.max()) - lo_pos + 1), np.inf)
            grid[idx, pos - lo_pos] = value
            value = np.minimum.accumulate(grid, axis=1)[idx, pos - lo_pos]
        order = np.lexsort((pos, -value))
        rank = np.empty(order.size, np.int64)
        rank[order] = np.arange(order.size)
        cum = np.concatenate([[0.0], np.cumsum(cost[order])])
        fixed = float(base) - float(cost[down].sum())
        if level is None:
            lo, hi = np.full(n, -np.inf), np.full(n, np.inf)
        else:
            sel = np.zeros(n)
            sel[np.searchsorted(keys, key)] = np.asarray(level, np.float64)
            lo, hi = sel - n_down, sel + n_up
        return cls(float(t0), keys, n_down, idx, pos, cost, rank, cum, fixed, float(base), lo, hi)

    def offsets(self, m: int) -> np.ndarray:
        """(n,) level offset from the plan of each key in the state that takes the first ``m`` steps."""
        got = self._offsets.get(m)
        if got is None:
            taken = np.bincount(self.step_key[self.rank < m], minlength=self.key.size)
            got = (taken - self.n_down).astype(np.float64)
            if len(self._offsets) > 8:
                for k in [k for k in self._offsets if isinstance(k, int)]:
                    del self._offsets[k]
            self._offsets[m] = got
        return got

    def _chains(self) -> tuple[int, np.ndarray]:
        """(lowest pos, (n, P + 1) running units of each key's chain: column j holds its steps with
        pos < lowest + j), made once per ladder."""
        got = self._offsets.get("chains")
        if got is None:
            if self.pos.size:
                low = int(self.pos.min())
                grid = np.zeros((self.key.size, int(self.pos.max()) - low + 2))
                np.add.at(grid, (self.step_key, self.pos - low + 1), self.cost)
                got = (low, np.cumsum(grid, axis=1))
            else:
                got = (0, np.zeros((self.key.size, 1)))
            self._offsets["chains"] = got
        return got

    def step_units(self, g: np.ndarray, vis: np.ndarray | None = None) -> float:
        """Units the steps add above the all-coarse state when each key is drawn at offset ``g`` (n,) (−inf: not
        drawn), counting only keys with ``vis`` (n,) set (None: all). A key partly down still draws its finer
        level, so a step's increment counts while the drawn level (``ceil``) is at or above it."""
        low, chains = self._chains()
        drawn = np.ceil(np.maximum(g, low - 1.0) - 1e-9)
        col = np.clip(drawn - low + 1, 0, chains.shape[1] - 1).astype(np.intp)
        per_key = chains[np.arange(self.key.size), col]
        return float(per_key.sum() if vis is None else per_key[vis].sum())

    def units(self, g: np.ndarray) -> float:
        """Units (vertices) of drawing each key at offset ``g`` (n,) from the plan."""
        return self.fixed + self.step_units(g)

    def visible_cum(self, vis: np.ndarray) -> np.ndarray:
        """(k + 1,) running units of the first m steps by value, counting only keys with ``vis`` (n,) set, made
        non-decreasing for the search (a step that saves units never makes a longer prefix fit)."""
        if vis.all():
            got = self._offsets.get("cum")
            if got is None:
                got = self._offsets["cum"] = np.maximum.accumulate(self.cum)
            return got
        order = self._offsets.get("order")
        if order is None:
            order = self._offsets["order"] = np.argsort(self.rank)
        c = np.concatenate([[0.0], np.cumsum(np.where(vis[self.step_key[order]], self.cost[order], 0.0))])
        return np.maximum.accumulate(c)

    @property
    def plan_steps(self) -> int:
        """The prefix closest in cost to the plan (every step down taken, none up)."""
        target = self.base - self.fixed
        return int(np.clip(np.searchsorted(self.cum, target + 1e-12, side="right") - 1, 0, self.cum.size - 1))


class Governor:
    """Per-frame correction of the drawn levels along the current ladder.

    target : frame time to hold (s); ramp : seconds a change of one level takes (≤ 0.25 s);
    aim : share of the target the predicted frame is steered to at most (below 1: a frame's own noise is then
    less often over the target); slack : the band around the aim within which the state is kept
    (± slack × aim), so noise does not make it chatter; hold : the line to hold (``Hold``); window : frames
    (of those predicted at ``NEAR`` × the target or more) whose measured ÷ predicted times estimate the
    scatter; ledger : frames over which the line's allowance is counted (``Ledger``: frames the budget does
    not bind leave theirs to the frames it does).
    """

    def __init__(self, target: float, ramp: float = RAMP, aim: float = 0.97, slack: float = 0.03,
                 hold: Hold = STRICT, window: int = 256, ledger: int = 4096) -> None:
        if not (target > 0 and 0 < ramp <= 0.25 and 0 < aim <= 1 and 0 <= slack < 1 and aim * (1 + slack) <= 1
                and isinstance(hold, Hold) and window >= 8 and ledger >= window):
            raise ValueError(f"bad governor settings target={target} ramp={ramp} aim={aim} slack={slack} "
                             f"hold={hold!r} window={window} ledger={ledger}")
        self.target, self.ramp, self.aim, self.slack = float(target), float(ramp), float(aim), float(slack)
        # The aim follows the predictor's measured error: measured ÷ predicted time of the last ``window``
        # frames (enough that a 99th percentile rests on a few frames, not on the largest one); steering to
        # bound ÷ their ``share`` quantile keeps that share of frames within bound × target
        # on a machine whose frames scatter, and to ``aim`` where they do not. Where the scatter is wide this
        # gives up mean frame time for the tail, never the other way round.
        self.line = hold  # (``hold`` is the method that keeps rows where the caller drew them)
        self.tail, self.quantile = hold.bound, hold.share
        self.ratios = np.full(int(window), np.nan)
        self.measured = 0  # frames whose ratio was recorded
        # The line is a share of all frames, and a frame the budget does not bind (everything offered fits below
        # the aim) is almost never over it: the allowance those frames leave unused is spent on the bound ones,
        # which may then be steered to a lower quantile of the ratios (``Ledger``).
        self.ledger = Ledger(hold, int(ledger), least=min(256, int(ledger)))
        self.binding = True  # the last ``apply`` held back a step that did not fit (or had no ladder to act on)
        self._steer: float | None = None  # ``steer`` as of the last ratio recorded
        self.pending: list[GovernorLadder] = []
        self.ladder: GovernorLadder | None = None
        self.m = 0
        self.predictor = FramePredictor()  # a frame's seconds from the units it draws, measured here
        self.units = 0.0  # vertices (the ladder's units) of what the last ``apply`` drew
        self.predicted = 0.0  # its predicted time
        self.down = self.up = 0  # objects the last ``apply`` drew coarser / finer than the plan
        self.gkey = np.zeros(0, np.int64)  # keys with an offset, sorted
        self.g = np.zeros(0)  # their drawn offsets (continuous levels)
        self.goal = np.zeros(0)  # the offsets they ramp to
        self.speed = np.zeros(0)  # levels per second of their ramps
        self.lo = np.zeros(0)  # the levels their steps reach: a governed level stays within them, or within
        self.hi = np.zeros(0)  # where the schedule's own ramp has it
        self.t: float | None = None
        # The last frame as the renderer counted it: its vertices anchor the prediction, so objects outside the
        # view (which the ladder's units count) and objects without steps are priced as drawn, not as planned.
        self.anchor: float | None = None
        self.seen: np.ndarray | None = None  # sorted keys it drew inside the view (None: take all as seen)
        self.last_key = np.zeros(0, np.int64)  # the schedule's keys the last ``apply`` returned levels for ...
        self.last_level = np.zeros(0)  # ... and those levels
        self.switched = False  # the last ``_switch`` took a new ladder
        self.expected = False  # the anchor is the frame about to be drawn (``expect``), not the last one
        self._lookups: dict = {}  # ``_memo``'s lookups
        self._row_cache: tuple | None = None  # (ladder, schedule keys, rows of the ladder's keys in them)

    # ------------------------------------------------------------------ inputs

    def take(self, ladder: GovernorLadder, reset: bool = False) -> None:
        """A delta's ladder, governing from its ``t0`` (a reset one replaces what is pending)."""
        if reset:
            self.pending = []
        self.pending = [p for p in self.pending if p.t0 < ladder.t0] + [ladder]

    def expect(self, vertices: float, seen: np.ndarray) -> None:
        """Before a frame: the ``vertices`` the last frame's levels draw from the camera about to draw (a key
        new in the view at its planned level), and the keys ``seen`` in its view. The prediction then starts
        from the frame about to be drawn, not the one before: objects entering or leaving the view as the
        camera moves are most of what a frame changes by."""
        if self.anchor is not None and vertices > 0 and np.isfinite(vertices):
            self.anchor = float(vertices)
            self.seen = np.unique(np.asarray(seen, np.int64))
            self.expected = True

    def observe(self, time: float, vertices: float | None = None, seen: np.ndarray | None = None) -> None:
        """The measured time of the frame the last ``apply`` drew, with the ``vertices`` the renderer drew
        (None: the ladder's count of them) and the object keys it drew inside the view (None: all)."""
        drawn = self.units if vertices is None else float(vertices)
        if self.units > 0 and drawn > 0 and time > 0 and np.isfinite(time) and np.isfinite(drawn):
            if self.predicted > 0:
                if self.predicted >= NEAR * self.target:
                    self.ratios[self.measured % self.ratios.size] = float(time) / self.predicted
                    self.measured += 1
                    self._steer = None
                self.ledger.record(self.binding, float(time) > self.tail * self.target)
            self.predictor.observe(float(time), drawn)
            self.anchor = drawn
            self.seen = None if seen is None else np.unique(np.asarray(seen, np.int64))
            self.expected = False

    def report(self) -> dict:
        """The predictors' figures (``FramePredictor.report``) and the line's (``Ledger.report``: the share of
        frames the budget bound and the share over the line, and the quantile of the ratios in force)."""
        return {**self.predictor.report(), "hold": self.ledger.report()}

    @property
    def steer(self) -> float:
        """The share of the target the predicted frame is steered to now (updated as frames are measured)."""
        if self.measured < 8:
            return self.aim
        if self._steer is None:
            # A quantile is only as high as the frames above it: early in a run the 99th percentile of twenty
            # ratios is their largest, and one stall (an upload, the first draws of a level) held the aim at
            # half the target for seconds. Until the window holds enough frames, the quantile that lies a frame
            # below their largest stands in (with n frames, the one at 1 − 1/n).
            n = min(self.measured, self.ratios.size)
            q = float(np.nanquantile(self.ratios, min(self.ledger.quantile(), 1.0 - 1.0 / n)))
            # The state is kept while its prediction lies within the band, so a frame is predicted up to
            # (1 + slack) × the aim: the tail is steered from the band's top, not its middle.
            self._steer = float(np.clip(self.tail / (max(q, 1e-9) * (1.0 + self.slack)), 0.5, self.aim))
        return self._steer

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
            self.switched = True

    def _decide(self, lad: GovernorLadder, cum: np.ndarray, rest: float) -> int:
        """The number of steps to take: shrink to the aim when the prediction for the state is above its band,
        grow to it when below, else stay. A state of m steps is predicted to draw ``rest + cum[m]`` units:
        ``cum`` the visible running units of the steps, ``rest`` the last frame's drawn units less what its
        steps added. The prediction is of the state the levels ramp to, at the rate the drawn frames measured,
        so a decrement still ramping does not hold growth back: with hundreds of keys one always is, and the
        frames stayed a fifth under the aim."""
        aim = self.steer * self.target
        fits = self.predictor.units_for(aim)  # units a frame at the aim may draw
        if fits is None or self.anchor is None:
            self.binding = True
            return self.m
        m = min(self.m, cum.size - 1)
        now = self.predictor.predict(rest + cum[m])
        fit = int(max(np.searchsorted(cum, fits - rest, side="right") - 1, 0))
        # Bound: a step the aim leaves out (every step taken and still under the aim: the budget does not bind).
        self.binding = fit < cum.size - 1
        if now > (1.0 + self.slack) * aim:
            return fit
        if now < (1.0 - self.slack) * aim:
            return max(fit, m)
        return m

    def _rows(self, key: np.ndarray, lad: GovernorLadder) -> np.ndarray:
        """(n,) the row of ``key`` (the schedule's) holding each ladder key, −1 where none; kept while the
        schedule's keys and the ladder stay the same (most frames)."""
        c = self._row_cache
        if c is not None and c[0] is lad and c[1].size == key.size and np.array_equal(c[1], key):
            return c[2]
        order = np.argsort(key, kind="stable")
        k = key[order]
        p = np.searchsorted(k, lad.key)
        pc = np.minimum(p, max(k.size - 1, 0))
        rows = np.where((p < k.size) & (k[pc] == lad.key), order[pc] if k.size else -1, -1) if k.size \
            else np.full(lad.key.size, -1)
        self._row_cache = (lad, key.copy(), rows)
        return rows

    def _last_offsets(self, lad: GovernorLadder, sel: np.ndarray, key: np.ndarray, rows: np.ndarray,
                      li: np.ndarray, on: np.ndarray) -> np.ndarray:
        """(n,) each ladder key's level in the last frame less its selected level (−inf: not drawn then)."""
        # A key the last frame did not draw: nothing of it in the anchor, or (``expect``) its planned level.
        g = np.full(lad.key.size, 0.0 if self.expected else -np.inf)
        bounded = np.isfinite(sel)
        last_key, last_level = self.last_key, self.last_level
        if last_key.size == key.size and np.array_equal(last_key, key):  # the same rows as the last frame
            found = (rows >= 0) & bounded
            g[found] = last_level[rows[found]] - sel[found]
        elif last_key.size:
            order = np.argsort(last_key, kind="stable")
            k = last_key[order]
            p = np.searchsorted(k, lad.key)
            pc = np.minimum(p, k.size - 1)
            found = (p < k.size) & (k[pc] == lad.key) & bounded
            g[found] = last_level[order][pc[found]] - sel[found]
        if not bounded.all():  # a ladder without levels: the offsets the governor kept are all it knows
            free = np.zeros(lad.key.size, bool)
            free[li[on]] = True
            free &= ~bounded
            g_gov = np.zeros(lad.key.size)
            g_gov[li[on]] = self.g[on]
            g[free] = g_gov[free]
        return g

    def apply(self, t: float, key: np.ndarray, level: np.ndarray) -> np.ndarray:
        """(s,) the levels to draw at client time ``t`` for the schedule's ``key`` (s,) at ``level`` (s,)."""
        dt = 0.0 if self.t is None else max(float(t) - self.t, 0.0)
        self.t = float(t)
        self._switch(t)
        lad = self.ladder
        key = np.asarray(key, np.int64)
        level = np.asarray(level, np.float64)
        if lad is None or self.gkey.size == 0:
            self.binding = True
            self.units, self.down, self.up = (lad.base if lad is not None else 0.0), 0, 0
            self.predicted = self.predictor.predict(self.anchor if self.anchor is not None else self.units) or 0.0
            self._remember(key, level)
            return level
        # Target offset of every key with one: the state's for the ladder's keys, 0 for the rest.
        li = self._memo(("li", id(lad), id(self.gkey)), lambda: np.searchsorted(lad.key, self.gkey),
                        refs=(lad, self.gkey))
        li_c = np.minimum(li, max(lad.key.size - 1, 0))
        if lad.key.size:
            on = (li < lad.key.size) & (lad.key[li_c] == self.gkey)
        else:  # an empty ladder: every key ramps back to the plan
            on, li_c = np.zeros(self.gkey.size, bool), np.zeros(self.gkey.size, np.int64)
        # The last frame in this ladder's terms: which keys it drew in view and at which levels.
        sel = lad.lo + lad.n_down
        rows = self._rows(key, lad)
        g_last = self._last_offsets(lad, sel, key, rows, li, on)
        vis = np.ones(lad.key.size, bool)
        if self.seen is not None:
            vis = np.isin(lad.key, self.seen, assume_unique=True) | ~np.isfinite(g_last)
        cum = lad.visible_cum(vis)
        rest = (self.anchor if self.anchor is not None else 0.0) - lad.step_units(g_last, vis)
        self.m = self._decide(lad, cum, rest)
        # Until a frame is measured there is nothing to correct the plan with: it is drawn as it is.
        goal = np.zeros(self.g.size)
        if self.predictor.rate is not None and lad.key.size:
            goal = np.where(on, lad.offsets(self.m)[li_c], 0.0)
        moved = goal != self.goal
        if self.switched:
            # A new plan starts where the last frame was: a key ramps from the level it was drawn at to its goal,
            # so a heavier plan is reached at the governor's pace, never at once, and nothing pops either way.
            self.switched = False
            here = self._level_of(key, level, self.gkey)
            last = np.full(self.gkey.size, -np.inf)
            last[on] = g_last[li_c[on]] + sel[li_c[on]]
            drew = on & np.isfinite(last) & np.isfinite(here)
            start = np.where(drew, last - here, np.minimum(goal, 0.0))
            self.g = np.where(on, start, self.g)
            moved |= on
        # A new goal starts a ramp of ``ramp`` seconds: two levels or more go as a chain of adjacent morphs at
        # twice the speed (Zach's chains), so a shrink that first undoes a step up is drawn within one ramp —
        # never faster, so a level moves at most two levels per ramp.
        self.speed = np.where(moved, np.clip(np.abs(goal - self.g), 1.0, 2.0) / self.ramp, self.speed)
        self.goal = goal
        step = dt * self.speed
        self.g = self.g + np.clip(goal - self.g, -step, step)
        near = np.abs(self.g - goal) < 1e-9
        self.g[near] = goal[near]
        settled = self.g == 0
        if settled.any() and not on[settled].all():  # forget keys that left the ladder and came back to plan
            drop = settled & ~on
            self.gkey, self.g, self.goal, self.speed, self.lo, self.hi = (
                a[~drop] for a in (self.gkey, self.g, self.goal, self.speed, self.lo, self.hi))
            li, on = li[~drop], on[~drop]
        drawn = level
        if self.gkey.size:
            pos = self._memo(("pos", id(self.gkey)), lambda: np.searchsorted(self.gkey, key), key,
                             refs=(self.gkey,))
            pos_c = np.minimum(pos, self.gkey.size - 1)
            hit = (pos < self.gkey.size) & (self.gkey[pos_c] == key)
            # Within the levels the steps reach (resident, with their morph targets), or the schedule's own level
            # where its ramp lies outside them: a bound that moves with the level, so nothing jumps.
            lo = np.minimum(level, np.where(hit, self.lo[pos_c], -np.inf))
            hi = np.maximum(level, np.where(hit, self.hi[pos_c], np.inf))
            drawn = np.maximum(np.clip(level + np.where(hit, self.g[pos_c], 0.0), lo, hi), 0.0)
            # The offset is what was drawn, not what the bound cut off: a bound that widens later (a new ladder
            # reaching a level further down) then starts a ramp from here instead of showing the rest at once.
            self.g[pos_c[hit]] = drawn[hit] - level[hit]
        # What is drawn, in the ladder's units: a key partly down still draws its finer level, partly up the finer.
        g_lad = np.zeros(lad.key.size)
        g_lad[li[on]] = self.g[on]
        self.units = lad.units(g_lad)
        self.down = int((self.g < -1e-9).sum())
        self.up = int((self.g > 1e-9).sum())
        g_now = np.where(rows >= 0, drawn[np.maximum(rows, 0)] - sel, -np.inf) if drawn.size else np.full(rows.size, -np.inf)
        g_now = np.where(np.isfinite(g_now), g_now, np.where(np.isfinite(sel), -np.inf, g_lad))
        self.predicted = (self.predictor.predict(rest + lad.step_units(g_now, vis)) or 0.0) \
            if self.anchor is not None else (self.predictor.predict(self.units) or 0.0)
        self._remember(key, drawn)
        return drawn

    def _memo(self, name: tuple, make, key: np.ndarray | None = None, refs: tuple = ()) -> np.ndarray:
        """A lookup between key arrays, kept while the arrays stay the same (most frames): by identity for the
        governor's own arrays (replaced, never changed in place; ``refs`` keeps them alive while cached, so
        their ids are not reused), by value for the caller's ``key``."""
        got = self._lookups.get(name)
        if got is not None and (key is None or (got[0].size == key.size and np.array_equal(got[0], key))):
            return got[1]
        value = make()
        if len(self._lookups) > 8:
            self._lookups.clear()
        self._lookups[name] = (None if key is None else key.copy(), value, refs)
        return value

    def _remember(self, key: np.ndarray, drawn: np.ndarray) -> None:
        self.last_key, self.last_level = key.copy(), np.asarray(drawn, np.float64).copy()

    @staticmethod
    def _level_of(key: np.ndarray, level: np.ndarray, want: np.ndarray) -> np.ndarray:
        """(w,) the level the rows ``key``/``level`` give each of ``want`` (w,), NaN where it has no row."""
        out = np.full(want.size, np.nan)
        if not key.size or not want.size:
            return out
        order = np.argsort(key, kind="stable")
        k = key[order]
        p = np.searchsorted(k, want)
        pc = np.minimum(p, k.size - 1)
        found = (p < k.size) & (k[pc] == want)
        out[found] = level[order][pc[found]]
        return out

    def hold(self, key: np.ndarray, offset: np.ndarray) -> None:
        """The rows of ``key`` were drawn at ``offset`` from the plan instead (what the caller could draw):
        their ramps go on from there, and the last frame's levels say so."""
        key = np.asarray(key, np.int64)
        offset = np.asarray(offset, np.float64)
        pos = np.searchsorted(self.gkey, key)
        pos_c = np.minimum(pos, max(self.gkey.size - 1, 0))
        hit = (pos < self.gkey.size) & (self.gkey[pos_c] == key) if self.gkey.size else np.zeros(pos.size, bool)
        moved = np.zeros(key.size)
        moved[hit] = offset[hit] - self.g[pos_c[hit]]
        self.g[pos_c[hit]] = offset[hit]
        if self.last_key.size:
            order = np.argsort(self.last_key, kind="stable")
            k = self.last_key[order]
            p = np.searchsorted(k, key)
            pc = np.minimum(p, k.size - 1)
            found = (p < k.size) & (k[pc] == key)
            self.last_level[order[pc[found]]] += moved[found]
