"""A delta's bookkeeping in compiled passes (numba): Zach's morph marking, the morph schedule's step, and the
expansion of a schedule's level ranges into representations with the client-cache mirror's update.

Each is a handful of numpy calls per level of a hierarchy, per range or per set
operation (``np.unique``, ``union1d``, ``isin``, ``lexsort``) on a few thousand
ids — calls that cost more than their arithmetic. Here each is one pass over the
ids with a scratch flag per representation. ``morph.mark``, ``MorphScheduler.schedule``,
``pipeline._expand`` and ``mirror.CacheMirror.plan`` stay the references, and the tests compare.

Pure functions of arrays (no clock, no I/O).
"""

from __future__ import annotations

import math

import numpy as np

from .jit import jit

__all__ = ["mark", "plan", "union_ranges", "schedule", "compile_all"]


@jit()
def mark(parent, black, new):
    """``morph.mark``: (kind (s,) int8 — +1 up-morph, −1 down-morph, 0 none —, source (s,) int64)."""
    m = parent.shape[0]
    flags = np.zeros(m, np.uint8)  # 1 black, 2 grey (an ancestor of black)
    for b in black:
        flags[b] |= 1
    for b in black:
        p = parent[b]
        while p >= 0 and not (flags[p] & 2):
            flags[p] |= 2
            p = parent[p]
    s = new.shape[0]
    kind = np.zeros(s, np.int8)
    source = np.full(s, -1, np.int64)
    for i in range(s):
        r = new[i]
        a = parent[r]
        while a >= 0:
            if flags[a] & 1:
                source[i] = a
                kind[i] = 1
                break
            a = parent[a]
        if (flags[r] & 2) and not (flags[r] & 1):
            kind[i] = -1
    return kind, source


@jit()
def _stable_by(ids, values):
    order = np.argsort(values, kind="mergesort")
    return ids[order]


@jit()
def plan(selected, key, lo, hi, extra, rep_bytes, rep_level, rep_mix, budget, resident, sent, last_used, seq, resync,
         held_bytes):
    """``CacheMirror.plan`` with the schedule's level ranges expanded (``pipeline._expand``) on the way.

    selected : reps the selection draws; key, lo, hi : (q,) each object key's lowest and highest level the
    schedule draws (reps key + l for every whole l between); extra : further reps the delta needs
    resident, sent, last_used : the mirror's arrays, updated in place; held_bytes : the bytes it holds now
    Returns (new, drop, Δcount, Δbytes, Δdigest, evicted, over_budget).
    """
    m = resident.shape[0]
    state = np.zeros(m, np.uint8)  # 1 needed, 2 selected, 4 kept
    total = selected.shape[0] + extra.shape[0]
    first = np.empty(key.shape[0], np.int64)
    count = np.empty(key.shape[0], np.int64)
    for i in range(key.shape[0]):
        first[i] = np.int64(math.floor(lo[i] + 1e-9))
        count[i] = max(np.int64(math.ceil(hi[i] - 1e-9)) - first[i] + 1, 1)
        total += count[i]
    touched = np.empty(total, np.int64)
    t = 0
    for r in selected:
        if state[r] == 0:
            touched[t] = r
            t += 1
        state[r] = 2
    for i in range(key.shape[0]):
        for c in range(count[i]):
            r = key[i] + first[i] + c
            if state[r] == 0:
                touched[t] = r
                t += 1
                state[r] = 1
    for r in extra:
        if state[r] == 0:
            touched[t] = r
            t += 1
            state[r] = 1
    want = np.sort(touched[:t])
    # The reference's lexsort((bytes, level, later)) over ids in order. Where the keys fit one int64 (levels
    # under 64, payloads under 2**56 bytes: every real scene) that is one stable sort of the packed key;
    # otherwise three stable sorts, last key last.
    packed = np.empty(t, np.int64)
    fits = True
    for i in range(t):
        r = want[i]
        lv, nb = rep_level[r], rep_bytes[r]
        fits = fits and 0 <= lv < 32 and 0 <= nb < (np.int64(1) << 56)
        packed[i] = ((np.int64(1) if state[r] == 1 else np.int64(0)) << 61) | (np.int64(lv) << 56) | np.int64(nb)
    if fits:
        want = _stable_by(want, packed)
    else:
        want = _stable_by(want, rep_bytes[want])
        want = _stable_by(want, rep_level[want])
        later = np.empty(t, np.int64)
        for i in range(t):
            later[i] = 1 if state[want[i]] == 1 else 0
        want = _stable_by(want, later)
    keep_n = t
    sizes = 0
    for i in range(t):
        sizes += rep_bytes[want[i]]
    if sizes > budget:
        acc = 0
        keep_n = 0
        for i in range(t):
            acc += rep_bytes[want[i]]
            if acc > budget:
                break
            keep_n += 1
    d_count, d_bytes, d_digest = 0, 0, np.uint64(0)
    if resync:
        for r in range(m):
            if resident[r]:
                resident[r] = False
                d_count -= 1
                d_bytes -= rep_bytes[r]
                d_digest ^= rep_mix[r]
    new = np.empty(keep_n, np.int64)
    n_new = 0
    for i in range(keep_n):
        r = want[i]
        state[r] |= 4
        if not resident[r]:
            new[n_new] = r
            n_new += 1
            resident[r] = True
            sent[r] = True
            d_count += 1
            d_bytes += rep_bytes[r]
            d_digest ^= rep_mix[r]
    for i in range(t):
        last_used[want[i]] = seq
    drop = np.zeros(0, np.int64)
    evicted = 0
    held_bytes += d_bytes  # what the mirror holds after the adds, to compare with the budget
    if held_bytes > budget:
        n_cand = 0
        for r in range(m):
            if resident[r] and not (state[r] & 4):
                n_cand += 1
        cand = np.empty(n_cand, np.int64)
        j = 0
        for r in range(m):
            if resident[r] and not (state[r] & 4):
                cand[j] = r
                j += 1
        cand = _stable_by(cand, last_used[cand])
        need = held_bytes - budget
        freed = 0
        n = 0
        while n < n_cand:
            freed += rep_bytes[cand[n]]
            n += 1
            if freed >= need:
                break
        drop = cand[:n].copy()
        for r in drop:
            resident[r] = False
            d_count -= 1
            d_bytes -= rep_bytes[r]
            d_digest ^= rep_mix[r]
        evicted = n
    if resync:
        n_drop = 0
        for r in range(m):
            if sent[r] and not resident[r]:
                n_drop += 1
        drop = np.empty(n_drop, np.int64)
        j = 0
        for r in range(m):
            if sent[r] and not resident[r]:
                drop[j] = r
                j += 1
    over = 0
    for i in range(t):
        if not resident[want[i]]:
            over += 1
    return new[:n_new].copy(), drop, d_count, d_bytes, d_digest, evicted, over


@jit()
def union_ranges(k1, lo1, hi1, k2, lo2, hi2):
    """``MorphScheduler._union`` of two (key, lo, hi) tables, each sorted by key without repeats: per key the
    widest range, by one merge."""
    n1, n2 = k1.shape[0], k2.shape[0]
    key = np.empty(n1 + n2, np.int64)
    lo = np.empty(n1 + n2)
    hi = np.empty(n1 + n2)
    i = j = t = 0
    while i < n1 or j < n2:
        if j >= n2 or (i < n1 and k1[i] < k2[j]):
            key[t], lo[t], hi[t] = k1[i], lo1[i], hi1[i]
            i += 1
        elif i >= n1 or k2[j] < k1[i]:
            key[t], lo[t], hi[t] = k2[j], lo2[j], hi2[j]
            j += 1
        else:
            key[t], lo[t], hi[t] = k1[i], min(lo1[i], lo2[j]), max(hi1[i], hi2[j])
            i += 1
            j += 1
        t += 1
    return key[:t].copy(), lo[:t].copy(), hi[:t].copy()


@jit()
def schedule(key, level, kind, has_kind, p_key, p_from, p_to, p_t0, p_t1, start, switch, tau, k_key, k_lo, k_hi,
             stats):
    """``MorphScheduler.schedule`` after a previous plan (not a reset): key, level (s,) the new solution sorted by
    key, kind its marking (used iff ``has_kind``); p_* the previous plan (sorted by key); k_* what the last
    schedule kept needed. Writes stats = [up, down, collapsed, switches, appear, vanish, steady]; returns the
    ramps (key, from, to, t0, t1), the new plan's level_from and t1, and the needed (key, lo, hi) before and
    after the union with k_*."""
    s, p = key.shape[0], p_key.shape[0]
    t_up = switch + tau
    pos = np.empty(s, np.int64)
    both = np.zeros(s, np.bool_)
    up = np.zeros(s, np.bool_)
    down = np.zeros(s, np.bool_)
    p_level = np.empty(s)
    a_level = np.empty(s)
    n_up = n_down = collapsed = switches = appear = steady = 0
    j = 0
    for i in range(s):
        while j < p and p_key[j] < key[i]:  # searchsorted, left: key and p_key both sorted
            j += 1
        pos[i] = j
        if j < p and p_key[j] == key[i]:
            both[i] = True
            p_level[i] = p_to[j]
            span = p_t1[j] - p_t0[j]  # ``ramp_levels`` at start
            f = (start - p_t0[j]) / span if span > 0 else (1.0 if start >= p_t1[j] else 0.0)
            f = min(max(f, 0.0), 1.0)
            a_level[i] = p_from[j] + (p_to[j] - p_from[j]) * f
            if has_kind:
                up[i] = kind[i] > 0 and level[i] > p_level[i]
                down[i] = kind[i] < 0 and level[i] < p_level[i]
            else:
                up[i] = level[i] > p_level[i]
                down[i] = level[i] < p_level[i]
            ramping = p_from[j] != p_to[j] and p_t1[j] > start
            n_up += up[i]
            n_down += down[i]
            collapsed += down[i] and ramping
            steady += not up[i] and not down[i]
        else:
            p_level[i] = a_level[i] = np.nan
            appear += 1
            if has_kind:
                switches += kind[i] != 0
    stats[0], stats[1], stats[2], stats[3] = n_up, n_down, collapsed, switches
    stats[4], stats[5], stats[6] = appear, p - (s - appear), steady
    m = n_down + n_up
    out_key, out_from, out_to = np.empty(m, np.int64), np.empty(m), np.empty(m)
    out_t0, out_t1 = np.empty(m), np.empty(m)
    plan_from, plan_t1 = np.empty(s), np.empty(s)
    lo_prev, hi_prev = np.empty(p), np.empty(p)
    for q in range(p):
        lo_prev[q] = min(p_from[q], p_to[q])
        hi_prev[q] = max(p_from[q], p_to[q])
    lo_new, hi_new = np.empty(s), np.empty(s)
    d = 0
    u = n_down
    for i in range(s):
        if down[i]:
            # Mesh morphs go between whole levels: from the nearer whole level (``np.round``: half to even).
            out_key[d], out_from[d] = key[i], np.rint(a_level[i]) if has_kind else a_level[i]
            out_to[d], out_t0[d], out_t1[d] = level[i], start, switch
            lo_prev[pos[i]] = min(lo_prev[pos[i]], level[i])
            d += 1
        elif up[i]:
            out_key[u], out_from[u], out_to[u], out_t0[u], out_t1[u] = key[i], p_level[i], level[i], switch, t_up
            u += 1
        plan_from[i] = p_level[i] if up[i] else level[i]
        plan_t1[i] = t_up if up[i] else switch
        lo_new[i] = min(plan_from[i], level[i])
        hi_new[i] = max(plan_from[i], level[i])
    nk, nlo, nhi = union_ranges(p_key, lo_prev, hi_prev, key, lo_new, hi_new)
    ok, olo, ohi = union_ranges(nk, nlo, nhi, k_key, k_lo, k_hi)
    return out_key, out_from, out_to, out_t0, out_t1, plan_from, plan_t1, nk, nlo, nhi, ok, olo, ohi


def _frozen(a):
    a.flags.writeable = False  # as the scene's shared tables are (``SceneTable``): their own specialisation
    return a


def compile_all() -> None:
    """Call each kernel once with the argument types the session passes."""
    parent = _frozen(np.array([-1, 0, 1, -1], np.int64))
    mark(parent, np.array([1], np.int64), np.array([2, 0], np.int64))
    m = 4
    plan(np.array([1], np.int64), np.array([0], np.int64), np.array([0.0]), np.array([1.0]), np.zeros(0, np.int64),
         _frozen(np.ones(m, np.int64)), _frozen(np.zeros(m, np.int64)), _frozen(np.arange(m, dtype=np.uint64)), 10,
         np.zeros(m, np.bool_), np.zeros(m, np.bool_), np.full(m, -1, np.int64), 1, False, 0)
    k, f = np.array([1, 3], np.int64), np.array([0.0, 1.0])
    union_ranges(k, f, f, k, f, f)
    for has_kind in (True, False):
        schedule(k, f, np.array([1, -1], np.int8), has_kind, k, f, f, f, f, 0.0, 0.5, 0.5, k, f, f,
                 np.zeros(7, np.int64))
