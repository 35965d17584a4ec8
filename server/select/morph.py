"""Geomorph schedules: Zach's three-stage pipeline, one scheduler per session.

A selection made during [t, t + τ) is for the target interval [s, s + τ),
s = t + 2τ. Between it and the solution P drawn before it the levels change by
morphing, never by popping (Zach 2002, 3.4):

- a down-morph (finer → coarser) runs during [s − τ, s) and ends at s, so the
  cheaper level is in place for the whole target interval;
- an up-morph runs during [s, s + τ) and ends at s + τ, so the finer level never
  breaks the budget of the interval before it;
- an up-morph P planned last time for [s − τ, s) that the new selection
  overrides by a down-morph collapses into one transition from the level at
  s − τ to the new one;
- a change across d levels is one ramp of the object's level, that is d
  adjacent morphs in a row within τ.

Every object's level is a continuous, piecewise-linear function of time: a
whole number is a level drawn as is, a fraction k − 1 + w draws level k morphed
a fraction w of the way from level k − 1 (``client.schedule`` evaluates it).
Vegetation uses the same functions over its resolution x ∈ [0, 1].

Transitions are found by Zach's marking (4.4): the representations of the
previous solution are black, their ancestors grey; a new representation with a
black ancestor is an up-morph from it, a grey one a down-morph from its black
descendants, anything else needs no morph. Marking is done over the arrays of
both solutions at once rather than inside the solver's increments: the result
depends only on the two solutions. A transition between different objects (an
HLOD node and its children) has no vertex correspondence; it is a switch at s,
counted but not morphed.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from proto.morph import LevelRamps

from . import kernels

__all__ = ["Transitions", "MorphScheduler", "mark", "rep_parents"]


def rep_parents(rep_level: np.ndarray, rep_object: np.ndarray, object_parent: np.ndarray,
                rep_first: np.ndarray, rep_count: np.ndarray) -> np.ndarray:
    """(m,) int64 — each representation's parent in the forest of every hierarchy, −1 at a root.

    Level k's parent is level k − 1 of the same object; an object's level 0 hangs
    below the finest level of its parent object (HLOD, terrain quadtree).
    """
    level = np.asarray(rep_level, np.int64)
    obj = np.asarray(rep_object, np.int64)
    up = np.asarray(object_parent, np.int64)[obj]
    finest_of_parent = np.where(up >= 0, np.asarray(rep_first, np.int64)[np.maximum(up, 0)]
                                + np.asarray(rep_count, np.int64)[np.maximum(up, 0)] - 1, -1)
    return np.where(level > 0, np.arange(level.size) - 1, finest_of_parent)


def mark(rep_parent: np.ndarray, black: np.ndarray, new: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Zach's black/grey marking: how each new representation relates to the previous solution.

    rep_parent : (m,) int — ``rep_parents``
    black      : (p,) int — the previous solution's representations
    new        : (s,) int — the new solution's
    Returns ``kind`` (s,) int8 — +1 up-morph (a black ancestor), −1 down-morph
    (grey: ancestor of black), 0 none — and ``source`` (s,) int64: for an
    up-morph the black ancestor, else −1. One vectorised pass per hierarchy level (the reference), or one
    compiled pass once the kernels are ready (``kernels.delta.mark``).
    """
    parent = np.asarray(rep_parent, np.int64)
    new = np.asarray(new, np.int64)
    ready = kernels.compiled()
    if ready is not None:
        return ready.delta.mark(parent, np.asarray(black, np.int64), new)
    is_black = np.zeros(parent.size, bool)
    is_black[np.asarray(black, np.int64)] = True
    grey = np.zeros(parent.size, bool)
    cur = parent[np.asarray(black, np.int64)]
    while cur.size:  # duplicates are harmless (marking is idempotent) and cheaper than np.unique's sort
        cur = cur[cur >= 0]
        cur = cur[~grey[cur]]
        grey[cur] = True
        cur = parent[cur]
    source = np.full(new.size, -1, np.int64)
    anc = parent[new]
    idx = np.flatnonzero(anc >= 0)  # the new reps still climbing, and their current ancestors
    anc = anc[idx]
    while idx.size:
        hit = is_black[anc]
        source[idx[hit]] = anc[hit]
        idx, anc = idx[~hit], parent[anc[~hit]]
        up = anc >= 0
        idx, anc = idx[up], anc[up]
    kind = np.zeros(new.size, np.int8)
    kind[source >= 0] = 1
    kind[grey[new] & ~is_black[new]] = -1
    return kind, source


@dataclass(frozen=True)
class Transitions:
    """One schedule: the ramps a delta carries and what the client must keep resident for it.

    key, level_from, level_to, t0, t1 : (e,) — the ramps (``proto.messages.Morphs`` columns, by object key)
    needed : per object key (q,) with the lowest and highest level drawn from the window start on
    stats  : counts of up-morphs, down-morphs, collapsed transitions, switches, appearing and vanishing objects
    """

    key: np.ndarray
    level_from: np.ndarray
    level_to: np.ndarray
    t0: np.ndarray
    t1: np.ndarray
    needed_key: np.ndarray
    needed_lo: np.ndarray
    needed_hi: np.ndarray
    stats: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.key.size)


class MorphScheduler:
    """The morph half of a session's pipeline: one ``schedule`` call per delta.

    tau : seconds per stage (Zach's τ); every morph chain fits in one τ
    morph : False gives the two-stage pipeline without morphing (levels switch at s)
    """

    def __init__(self, tau: float, morph: bool = True) -> None:
        if not tau > 0:
            raise ValueError(f"tau must be positive, got {tau}")
        self.tau = float(tau)
        self.morph = bool(morph)
        self.plan = LevelRamps.empty()  # what the last schedule draws from its switch s on
        self.switch: float | None = None
        self._kept = (np.zeros(0, np.int64), np.zeros(0), np.zeros(0))

    def schedule(self, key: np.ndarray, level: np.ndarray, start: float, switch: float, reset: bool = False,
                 kind: np.ndarray | None = None) -> Transitions:
        """Plan the transitions from what is drawn now to the solution (key, level) for [switch, switch + τ).

        key   : (s,) int — the new solution's objects (unique), level : (s,) float — their levels
        start : when the schedule takes over (switch − τ with morphing; switch without)
        kind  : (s,) int8 from ``mark`` (discrete levels); None compares levels (vegetation)
        reset : nothing to morph from (first delta, teleport): the solution replaces what is drawn at once
        """
        key = np.asarray(key, np.int64)
        level = np.asarray(level, np.float64)
        order = np.argsort(key, kind="stable")
        key, level = key[order], level[order]
        if kind is not None:
            kind = np.asarray(kind, np.int8)[order]
        prev = self.plan
        empty = np.zeros(0)
        stats = {"up": 0, "down": 0, "collapsed": 0, "switches": 0, "appear": 0, "vanish": 0, "steady": 0}
        if reset or not self.morph or prev.key.size == 0:
            self.plan = LevelRamps(key, level, level, np.full(key.size, switch), np.full(key.size, switch))
            stats["appear"] = int(key.size)
            needed = (key, level, level)
            out_needed = self._union(needed, self._kept if not reset else None)
            self._kept, self.switch = needed, switch
            return Transitions(np.zeros(0, np.int64), empty, empty, empty, empty, *out_needed, stats)

        ready = kernels.compiled()
        if ready is not None and _sorted_unique(key):  # the usual case: one compiled pass, the same numbers
            return self._schedule_compiled(ready.delta.schedule, key, level, kind, start, switch, stats)
        at_start = prev.at(start)
        pos = np.searchsorted(prev.key, key)
        pos_c = np.minimum(pos, max(prev.key.size - 1, 0))
        both = (pos < prev.key.size) & (prev.key[pos_c] == key)
        p_level = np.where(both, prev.level_to[pos_c], np.nan)
        a_level = np.where(both, at_start[pos_c], np.nan)
        if kind is None:
            up = both & (level > p_level)
            down = both & (level < p_level)
        else:
            # The marking decides; within one object it agrees with comparing levels.
            up = both & (kind > 0) & (level > p_level)
            down = both & (kind < 0) & (level < p_level)
            stats["switches"] = int(((kind != 0) & ~both).sum())
        ramping = both & (prev.level_from[pos_c] != prev.level_to[pos_c]) & (prev.t1[pos_c] > start)
        stats.update(up=int(up.sum()), down=int(down.sum()), collapsed=int((down & ramping).sum()),
                     appear=int((~both).sum()), vanish=int(prev.key.size - both.sum()),
                     steady=int((both & ~up & ~down).sum()))

        # Down-morphs (and collapses) during [start, switch), from the level drawn at start.
        d = np.nonzero(down)[0]
        # Up-morphs during [switch, switch + τ), from the previous solution's level.
        u = np.nonzero(up)[0]
        t_up = switch + self.tau
        out_key = np.concatenate([key[d], key[u]])
        a_from = a_level[d]
        if kind is not None:
            # Mesh morphs go between whole levels. The level drawn at start is whole unless the previous
            # up-morph is still under way there — by float noise in the switch times (found by fuzzing), or
            # truly when a late delta shifted the grid: then start from the nearer whole level (a blend of
            # at most half a level jumps, rather than a delta the client must refuse).
            a_from = np.round(a_from)
        out_from = np.concatenate([a_from, p_level[u]])
        out_to = np.concatenate([level[d], level[u]])
        out_t0 = np.concatenate([np.full(d.size, start), np.full(u.size, switch)])
        out_t1 = np.concatenate([np.full(d.size, switch), np.full(u.size, t_up)])

        self.plan = LevelRamps(
            key,
            np.where(up, p_level, level),
            level,
            np.full(key.size, float(switch)),
            np.where(up, t_up, switch).astype(np.float64),
        )
        # What is drawn from start on: the previous plan's objects until switch (as overridden), then the new.
        lo_prev = np.minimum(prev.level_from, prev.level_to)
        hi_prev = np.maximum(prev.level_from, prev.level_to)
        if d.size:
            pd = pos[d]
            lo_prev = lo_prev.copy()
            hi_prev = hi_prev.copy()
            lo_prev[pd] = np.minimum(lo_prev[pd], level[d])
        lo_new = np.minimum(self.plan.level_from, level)
        hi_new = np.maximum(self.plan.level_from, level)
        needed = self._union((prev.key, lo_prev, hi_prev), (key, lo_new, hi_new))
        out_needed = self._union(needed, self._kept)
        self._kept, self.switch = needed, switch
        return Transitions(out_key, out_from, out_to, out_t0, out_t1, *out_needed, stats)

    def _schedule_compiled(self, kernel, key, level, kind, start, switch, stats) -> Transitions:
        prev, f64 = self.plan, np.float64
        counts = np.zeros(7, np.int64)
        k_key, k_lo, k_hi = self._kept
        (out_key, out_from, out_to, out_t0, out_t1, plan_from, plan_t1, n_key, n_lo, n_hi, o_key, o_lo,
         o_hi) = kernel(key, level, np.zeros(0, np.int8) if kind is None else kind, kind is not None,
                        np.asarray(prev.key, np.int64), np.asarray(prev.level_from, f64),
                        np.asarray(prev.level_to, f64), np.asarray(prev.t0, f64), np.asarray(prev.t1, f64),
                        float(start), float(switch), self.tau,
                        np.asarray(k_key, np.int64), np.asarray(k_lo, f64), np.asarray(k_hi, f64), counts)
        stats.update(zip(("up", "down", "collapsed", "switches", "appear", "vanish", "steady"), counts.tolist()))
        self.plan = LevelRamps(key, plan_from, level, np.full(key.size, float(switch)), plan_t1)
        self._kept, self.switch = (n_key, n_lo, n_hi), switch
        return Transitions(out_key, out_from, out_to, out_t0, out_t1, o_key, o_lo, o_hi, stats)

    @staticmethod
    def _union(a, b):
        """Per key, the widest [lo, hi] level range over two (key, lo, hi) tables."""
        if b is None:
            return a
        ready = kernels.compiled()
        if ready is not None and _sorted_unique(a[0]) and _sorted_unique(b[0]):  # the usual case: one merge
            return ready.delta.union_ranges(np.asarray(a[0], np.int64), np.asarray(a[1], np.float64),
                                            np.asarray(a[2], np.float64), np.asarray(b[0], np.int64),
                                            np.asarray(b[1], np.float64), np.asarray(b[2], np.float64))
        key = np.concatenate([a[0], b[0]])
        lo = np.concatenate([a[1], b[1]])
        hi = np.concatenate([a[2], b[2]])
        if key.size == 0:
            return key.astype(np.int64), lo, hi
        # Sort (two sorted runs in practice: the stable sort merges them) and reduce each run of equal keys;
        # ~10× faster than np.unique(return_inverse) with ufunc.at, the same minima and maxima.
        order = np.argsort(key, kind="stable")
        key = key[order]
        first = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1]]))
        return (key[first].astype(np.int64), np.minimum.reduceat(lo[order], first),
                np.maximum.reduceat(hi[order], first))


def _sorted_unique(key: np.ndarray) -> bool:
    return bool(key.size < 2 or (np.diff(key) > 0).all())
