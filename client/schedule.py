"""The schedule executor: for any time t, which representation of each object to draw and its morph weight.

Each delta defines every drawn object's level as a continuous function of
time from its ``start`` on (``proto.messages.Delta``): until ``t0`` (the switch)
the previous delta's objects, as its ``morphs`` with t0 before the switch
override them (down-morphs and collapses); from the switch the new selection,
with the up-morphs. A level is a ramp: a whole number k draws level k as is; a
fraction k − 1 + w draws level k morphed a fraction w of the way from level
k − 1 (weight w ∈ (0, 1]). For vegetation the level is the resolution itself.

Objects are keyed by their level-0 representation id (a representation id
minus its level: an object's representations are consecutive ids, coarsest
first), so the executor needs no object table. Everything is arrays: one
``at(t)`` costs a few vectorised passes over the drawn objects.

A delta that arrives after its ``start`` (late) would make levels jump; the
executor then starts its ramps from the level drawn at arrival instead, so
nothing pops, and counts it in ``late``; a catch-up still under way at the
switch carries on into the new selection rather than being cut there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from proto.morph import LevelRamps

__all__ = ["Drawn", "Schedule"]


@dataclass(frozen=True)
class _Generation:
    start: float
    switch: float
    before: LevelRamps  # governs [start, switch)
    after: LevelRamps  # governs [switch, ∞)

    def phase(self, t: float) -> LevelRamps:
        return self.before if t < self.switch else self.after


@dataclass(frozen=True)
class Drawn:
    """What to draw at one instant, one row per object.

    key : object keys; level : continuous levels; rep : representation to draw;
    weight : its morph weight in (0, 1] (1: no morph; vegetation: the resolution)
    """

    key: np.ndarray
    level: np.ndarray
    rep: np.ndarray
    weight: np.ndarray

    def __len__(self) -> int:
        return int(self.key.size)


_EMPTY = LevelRamps.empty()


class Schedule:
    """Generations of level functions, newest last; ``at(t)`` reads the one governing t.

    continuous : levels are resolutions (vegetation), not whole levels of a chain
    min_ramp : seconds a late delta's catch-up ramp takes at least
    """

    def __init__(self, continuous: bool = False, min_ramp: float = 0.1) -> None:
        self.continuous = continuous
        self.min_ramp = float(min_ramp)
        self.generations: list[_Generation] = []
        self.late = 0

    def apply(
        self,
        start: float,
        switch: float,
        key: np.ndarray,
        level: np.ndarray,
        ramps: tuple = (),
        *,
        reset: bool = False,
        now: float | None = None,
    ) -> bool:
        """Take one delta's schedule; returns True if it came late (after ``start``) and was rebased.

        key, level : the selection drawn from ``switch`` on (object keys, levels)
        ramps : (key, level_from, level_to, t0, t1) arrays; a ramp starting before
                ``switch`` overrides the previous selection's object in [start, switch)
        reset : replace what is drawn at once (no previous generation to morph from)
        now : the client's time of arrival, for the late check
        """
        if not np.isfinite(start) or not np.isfinite(switch) or switch < start:
            raise ValueError(f"bad schedule window start={start} switch={switch}")
        rk, r0, r1, rt0, rt1 = (np.asarray(a) for a in ramps) if len(ramps) else (np.zeros(0, np.int64),) + (np.zeros(0),) * 4
        rk = rk.astype(np.int64)
        if reset and now is not None and now < switch:
            # At once, as the protocol says: the server's switch is its estimate of the client's clock, which can
            # run ahead of this clock before the clock sync settles; waiting for it would draw nothing meanwhile.
            switch = now
        after = LevelRamps.steady(key, level, switch)
        down = rt0 < switch
        up = ~down
        if np.isin(rk[up], after.key, invert=True).any():
            raise ValueError("an up-morph names an object that is not in the selection")
        after = after.override(rk[up], r0[up], r1[up], rt0[up], rt1[up])
        if reset or not self.generations:
            before = _EMPTY
            start = switch if reset else start
        else:
            base = self.generations[-1]
            before = base.after if start >= base.switch else base.before
            before = before.override(rk[down], r0[down], r1[down], rt0[down], rt1[down])
        gen = _Generation(float(start), float(switch), before, after)
        late = False
        if now is not None and now > start and not reset and self.generations:
            gen, late = self._rebase(gen, now)
        self.generations.append(gen)
        self.late += int(late)
        return late

    def _rebase(self, gen: _Generation, now: float) -> tuple[_Generation, bool]:
        """Start the new generation's ramps from what is drawn at ``now``, where they differ."""
        old = self.at(now)
        phase = gen.phase(now)
        new_level = phase.at(now)
        pos = np.searchsorted(old.key, phase.key)
        pos_c = np.minimum(pos, max(old.key.size - 1, 0))
        shared = (pos < old.key.size) & (old.key[pos_c] == phase.key) if old.key.size else np.zeros(phase.key.size, bool)
        jump = shared & (np.abs(old.level[pos_c] - new_level) > 1e-9) if old.key.size else shared
        if not jump.any():
            return gen, True
        level_to = phase.level_to
        t1 = np.where(jump, np.maximum(np.where(phase.t1 > now, phase.t1, now), now + self.min_ramp), phase.t1)
        fixed = LevelRamps(phase.key, np.where(jump, old.level[pos_c], phase.level_from), level_to,
                       np.where(jump, now, phase.t0), t1)
        if now < gen.switch:
            return _Generation(gen.start, gen.switch, fixed, self._carry(fixed, gen.after, gen.switch)), True
        return _Generation(gen.start, gen.switch, gen.before, fixed), True

    def _carry(self, before: LevelRamps, after: LevelRamps, switch: float) -> LevelRamps:
        """``after`` with each object whose catch-up ramp in ``before`` is still under way at ``switch`` ramped
        on from where that leaves it.

        A catch-up ramp takes at least ``min_ramp``, so one begun just before the switch runs past it, while the
        after phase starts from the level the server planned for the switch: cut there, the object would pop.
        It goes on to its planned level by the later of the two ramps' ends, at the catch-up's pace or slower.
        (The server's own ramps before a switch end by it, and a switch it plans without a morph stays one.)
        """
        if not before.key.size or not after.key.size:
            return after
        b_level, a_level = before.at(switch), after.at(switch)
        pos = np.minimum(np.searchsorted(before.key, after.key), before.key.size - 1)
        off = ((before.key[pos] == after.key) & (before.t1[pos] > switch)
               & (np.abs(b_level[pos] - a_level) > 1e-9))
        if not off.any():
            return after
        t1 = np.maximum(after.t1[off], before.t1[pos][off])
        return after.override(after.key[off], b_level[pos][off], after.level_to[off],
                              np.full(int(off.sum()), switch), t1)

    def advance(self, t: float) -> None:
        """Forget generations that no longer govern any time from t on."""
        while len(self.generations) > 1 and self.generations[1].start <= t:
            self.generations.pop(0)

    def at(self, t: float) -> Drawn:
        """Every drawn object's level, representation and morph weight at time t."""
        gen = None
        for g in reversed(self.generations):
            if g.start <= t:
                gen = g
                break
        if gen is None:
            z = np.zeros(0)
            return Drawn(np.zeros(0, np.int64), z, np.zeros(0, np.int64), z)
        phase = gen.phase(t)
        level = phase.at(t)
        if self.continuous:
            return Drawn(phase.key, level, phase.key.copy(), level)
        k = np.maximum(np.ceil(level - 1e-9), 0.0)
        weight = np.where(k > 0, np.clip(level - (k - 1.0), 0.0, 1.0), 1.0)
        weight = np.where(weight <= 1e-12, 0.0, weight)
        return Drawn(phase.key, level, phase.key + k.astype(np.int64), weight)
