"""The compiled delta bookkeeping equals its numpy references: Zach's marking (``morph.mark``) and the
mirror's update with the schedule's level ranges expanded (``CacheMirror.plan`` with ``expand``)."""

from __future__ import annotations

import copy

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from server.select import kernels
from server.select.morph import mark
from server.session.mirror import CacheMirror
from server.session.table import SceneTable


def _forest(rng, objects: int):
    """A forest of objects (each a chain of levels; an object's level 0 under its parent's finest level)."""
    count = rng.integers(1, 4, objects)
    first = np.concatenate([[0], np.cumsum(count)[:-1]])
    parent_obj = np.array([-1 if i == 0 or rng.random() < 0.4 else rng.integers(0, i) for i in range(objects)])
    rep_object = np.repeat(np.arange(objects), count)
    level = np.arange(count.sum()) - np.repeat(first, count)
    up = parent_obj[rep_object]
    finest = np.where(up >= 0, first[np.maximum(up, 0)] + count[np.maximum(up, 0)] - 1, -1)
    parent = np.where(level > 0, np.arange(level.size) - 1, finest)
    return parent, rep_object, level, first, count


def _with(flag: bool, fn):
    kernels.use_kernels(flag)
    try:
        return fn()
    finally:
        kernels.use_kernels(None)


@settings(max_examples=100, deadline=None)
@given(seed=st.integers(0, 2**31), objects=st.integers(1, 60))
def test_marking_compiled_equals_the_reference(seed, objects):
    rng = np.random.default_rng(seed)
    parent, *_ = _forest(rng, objects)
    m = parent.size
    black = rng.choice(m, rng.integers(0, m + 1), replace=False)
    new = rng.choice(m, rng.integers(0, m + 1), replace=False)
    ref = _with(False, lambda: mark(parent, black, new))
    got = _with(True, lambda: mark(parent, black, new))
    assert np.array_equal(ref[0], got[0]) and np.array_equal(ref[1], got[1])
    assert got[0].dtype == np.int8 and got[1].dtype == np.int64


class _Index:
    """The part of a scene index a SceneTable reads."""

    def __init__(self, rng, objects: int, huge: bool = False):
        parent, rep_object, level, first, count = _forest(rng, objects)
        self.n_representations = parent.size
        self.n_objects = objects
        self.bounds = np.zeros((2, 3))
        self.rep_bytes = rng.integers(10, 5000, parent.size)
        if huge:  # sizes past the packed sort key's 56 bits: the kernel's three-sort path
            self.rep_bytes[::3] += 1 << 56
        self.object_kind = np.zeros(objects, np.int64)
        self.rep_object, self.rep_level, self.rep_faces = rep_object, level, np.ones(parent.size, np.int64)
        self.rep_morph = np.zeros(parent.size, bool)
        self.rep_first, self.rep_count = first, count
        self.object_parent = np.full(objects, -1)
        self.object_lo = self.object_hi = np.zeros((objects, 3))


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31), objects=st.integers(1, 50),
       budget=st.sampled_from([2_000, 20_000, 10**9, 1 << 60]), deltas=st.integers(1, 8), huge=st.booleans())
def test_mirror_plan_compiled_equals_the_reference(seed, objects, budget, deltas, huge):
    rng = np.random.default_rng(seed)
    table = SceneTable.build(_Index(rng, objects, huge))
    m = table.n_reps
    ref, got = CacheMirror(table, budget), CacheMirror(table, budget)
    for seq in range(1, deltas + 1):
        selected = rng.choice(m, rng.integers(0, m + 1), replace=False)
        extra = rng.integers(0, m, rng.integers(0, 6))
        keys = np.unique(table.rep_first_of[rng.integers(0, m, rng.integers(0, 8))])
        top = np.array([int((table.rep_first_of == k).sum()) - 1 for k in keys], float)
        lo = np.floor(rng.random(keys.size) * (top + 1)) - rng.random(keys.size) * 0.3
        hi = np.minimum(lo + rng.random(keys.size) * 2, top)
        lo = np.clip(np.minimum(lo, hi), 0, None)
        if rng.random() < 0.15:
            ref.resync = got.resync = True
        a = _with(False, lambda: ref.plan(selected, extra, seq, ranges=(keys, lo, hi)))
        b = _with(True, lambda: got.plan(selected, extra, seq, ranges=(keys, lo, hi)))
        assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
        assert ref.held == got.held and np.array_equal(ref.resident, got.resident)
        assert np.array_equal(ref.sent, got.sent) and np.array_equal(ref.last_used, got.last_used)
        assert (ref.evicted, ref.over_budget, ref.resyncs, ref.resync) == (
            got.evicted, got.over_budget, got.resyncs, got.resync)
        assert copy.deepcopy(ref._records[seq].__dict__).keys() == got._records[seq].__dict__.keys()
        assert (ref._records[seq].held, ref._records[seq].bytes, ref._records[seq].digest) == (
            got._records[seq].held, got._records[seq].bytes, got._records[seq].digest)
    ref.recount()
    assert ref.held == got.held  # the incremental totals are the totals


@settings(max_examples=100, deadline=None)
@given(seed=st.integers(0, 2**31), n1=st.integers(0, 30), n2=st.integers(0, 30))
def test_range_union_compiled_equals_the_reference(seed, n1, n2):
    from server.select.morph import MorphScheduler

    rng = np.random.default_rng(seed)

    def table(n):
        key = np.unique(rng.integers(0, 40, n)).astype(np.int64)
        lo = np.floor(rng.random(key.size) * 3)
        return key, lo, lo + np.floor(rng.random(key.size) * 2)

    a, b = table(n1), table(n2)
    ref = _with(False, lambda: MorphScheduler._union(a, b))
    got = _with(True, lambda: MorphScheduler._union(a, b))
    for x, y in zip(ref, got):
        assert np.array_equal(x, y) and x.dtype == y.dtype


@settings(max_examples=100, deadline=None)
@given(seed=st.integers(0, 2**31), steps=st.integers(1, 10), marked=st.booleans(), late=st.booleans())
def test_morph_schedule_compiled_equals_the_reference(seed, steps, marked, late):
    """A run of schedules (solutions of random objects and levels, marked or compared by level, a delta now and
    then late so that ramps are cut mid-way): every output of the compiled step equals the reference's."""
    from server.select.morph import MorphScheduler

    rng = np.random.default_rng(seed)
    tau = 0.5
    ref, got = MorphScheduler(tau), MorphScheduler(tau)
    switch = 0.0
    for step in range(steps):
        key = rng.permutation(rng.choice(60, rng.integers(0, 40), replace=False)).astype(np.int64)
        level = rng.integers(0, 4, key.size).astype(np.float64)
        if not marked:
            level += np.round(rng.random(key.size), 1) * (rng.random(key.size) < 0.3)
        kind = rng.integers(-1, 2, key.size).astype(np.int8) if marked else None
        start = switch - tau + (rng.random() * tau if late and rng.random() < 0.5 else 0.0)
        reset = step == 0 or rng.random() < 0.1
        a = _with(False, lambda: ref.schedule(key, level, start, switch, reset=reset, kind=kind))
        b = _with(True, lambda: got.schedule(key, level, start, switch, reset=reset, kind=kind))
        for name in ("key", "level_from", "level_to", "t0", "t1", "needed_key", "needed_lo", "needed_hi"):
            x, y = getattr(a, name), getattr(b, name)
            assert x.dtype == y.dtype and np.array_equal(x, y, equal_nan=True), name
        assert a.stats == b.stats and list(a.stats) == list(b.stats)
        for name in ("key", "level_from", "level_to", "t0", "t1"):
            assert np.array_equal(getattr(ref.plan, name), getattr(got.plan, name)), name
        for x, y in zip(ref._kept, got._kept):
            assert np.array_equal(x, y)
        switch += tau
