"""The greedy's cut of every hull increment at the budget, its fill rounds and totals (numba).

The cut of all increments at the value where the budget runs out is a radix
selection: ``kernels.hull.hull`` sums the increments' Δcost into bins of their
value's float64 bit pattern, the bin where the running cost from the top crosses
the budget holds the threshold, and only that bin's increments are sorted. No
sample, no threshold guess, O(n·K). Fill rounds then add, in falling value, each
object's next increment while it still fits.

Pure functions of arrays over the (K, n) hull layout of ``kernels.hull`` (no clock,
no I/O); ``solvers.greedy.cut`` and ``fill_numpy`` stay the vectorised reference.
"""

from __future__ import annotations

import numpy as np

from .hull import hull, radix_bin, warm_up_inputs
from .jit import jit

__all__ = ["radix_cut", "ready", "fill_round", "finish", "moves", "clamp", "compile_all"]


@jit()
def radix_cut(value, bits, d_cost, count, begin, keep, capacity, hist, total, steps, ready):
    """The greedy cut of every hull increment: the longest prefix in falling value that fits ``capacity``.

    bits   : ``value.view(np.int64)`` (the bins are read from the bit pattern)
    begin  : (n,) increments taken at the start; they win ties in the threshold's bin (their
             value counts ``keep`` times more: a swap must gain). Zeros and keep = 1 for the greedy.
    hist, total : the radix histogram of the increments' Δcost and its sum (``hull``)
    steps  : (n,) out: increments taken per object (a prefix of each hull: values fall strictly)
    ready  : (n,) out: the objects whose next increment still fits after the cut (first ``n_ready``)
    Returns (spent, band, stop, n_ready): Σ Δcost taken, how many objects had increments in the
    threshold's bin (those were sorted), the value of the first increment left out (−inf:
    everything fits or nothing may be taken), how many objects are ready for a fill round.
    """
    k, n = value.shape
    if not capacity >= 0.0:
        for i in range(n):
            steps[i] = 0
        return 0.0, 0, -np.inf, 0
    if total <= capacity:  # everything fits
        spent = 0.0
        for i in range(n):
            steps[i] = count[i]
            for j in range(count[i]):
                spent += d_cost[j, i]
        if spent <= capacity:
            return spent, 0, -np.inf, 0
    acc = 0.0
    cross = 0
    for b in range(hist.size - 1, -1, -1):
        if acc + hist[b] > capacity:
            cross = b
            break
        acc += hist[b]
    # Branch-free: the increments above the threshold's bin are taken (a prefix: bins fall along
    # a hull); the objects with increments in it are listed in ``ready`` meanwhile (scratch).
    nb = 0
    above = 0.0
    for i in range(n):
        cn = count[i]
        s = 0
        for j in range(k):
            gt = (j < cn) & (radix_bin(bits[j, i]) > cross)
            s += gt
            above += d_cost[j, i] if gt else 0.0
        steps[i] = s
        ready[nb] = i
        nb += (s < cn) & (radix_bin(bits[min(s, k - 1), i]) == cross)
    m = 0
    for q in range(nb):
        i = ready[q]
        j = steps[i]
        while j < count[i] and radix_bin(bits[j, i]) == cross:
            m += 1
            j += 1
    idx = np.empty(m, np.int64)
    keys = np.empty(m)
    vals = np.empty(m)
    wts = np.empty(m)
    t = 0
    for q in range(nb):
        i = ready[q]
        j = steps[i]
        while j < count[i] and radix_bin(bits[j, i]) == cross:
            v = value[j, i]
            idx[t] = i
            vals[t] = v
            keys[t] = -(v * keep) if j < begin[i] else -v
            wts[t] = d_cost[j, i]
            t += 1
            j += 1
    srt = np.argsort(keys, kind="mergesort")
    spent = above
    stop = -np.inf
    for t in range(m):
        q = srt[t]
        if spent + wts[q] > capacity:
            stop = vals[q]
            break
        spent += wts[q]
        steps[idx[q]] += 1
    # The objects whose next increment fits what is left (branch-free: most do not).
    remaining = capacity - spent
    r = 0
    for i in range(n):
        s = steps[i]
        ok = (s < count[i]) & (d_cost[min(s, k - 1), i] <= remaining)
        ready[r] = i
        r += ok
    return spent, nb, stop, r


@jit()
def ready(value, d_cost, count, steps, remaining):
    """Objects whose next increment exists and fits ``remaining``: the first fill round's candidates."""
    k, n = value.shape
    m = 0
    for i in range(n):
        s = steps[i]
        if s < count[i] and d_cost[s, i] <= remaining:
            m += 1
    out = np.empty(m, np.int64)
    m = 0
    for i in range(n):
        s = steps[i]
        if s < count[i] and d_cost[s, i] <= remaining:
            out[m] = i
            m += 1
    return out


@jit()
def fill_round(value, d_cost, count, steps, idx, remaining):
    """One fill round: the objects ``idx`` whose next increment still fits, in falling value (stable),
    each take their next increment while the sum fits (at least the first: it fits alone).

    Updates ``steps``; returns (the objects that were ready, remaining budget, increments taken).
    """
    m = 0
    live = np.empty(idx.size, np.int64)
    for t in range(idx.size):
        i = idx[t]
        s = steps[i]
        if s < count[i] and d_cost[s, i] <= remaining:
            live[m] = i
            m += 1
    live = live[:m]
    if m == 0:
        return live, remaining, 0
    keys = np.empty(m)
    for t in range(m):
        i = live[t]
        keys[t] = -value[steps[i], i]
    srt = np.argsort(keys, kind="mergesort")
    added = 0.0
    took = 0
    for t in range(m):
        i = live[srt[t]]
        w = d_cost[steps[i], i]
        if t > 0 and added + w > remaining:
            break
        added += w
        took += 1
    for t in range(took):
        steps[live[srt[t]]] += 1
    return live, remaining - added, took


@jit()
def finish(benefit, cost, opt, value, count, steps):
    """The options after ``steps`` increments (−1: none), their Σ cost and Σ benefit, Σ steps, Σ count,
    and the value of the best increment left out (−inf: none)."""
    k, n = value.shape
    level = np.empty(n, np.int64)
    c_sum, b_sum, left = 0.0, 0.0, -np.inf
    incs, cands = 0, 0
    for i in range(n):
        s = steps[i]
        cn = count[i]
        incs += s
        cands += cn
        o = np.int64(opt[max(s - 1, 0), i])
        drawn = s > 0
        level[i] = o if drawn else -1
        oo = o if drawn else 0
        c_sum += cost[i, oo] if drawn else 0.0
        b_sum += benefit[i, oo] if drawn else 0.0
        nv = value[min(s, k - 1), i] if s < cn else -np.inf
        left = max(left, nv)
    return level, c_sum, b_sum, incs, cands, left


@jit()
def moves(a, b):
    """Σ |a − b|: the increments and decrements between two step vectors."""
    total = 0
    for i in range(a.size):
        d = a[i] - b[i]
        total += d if d >= 0 else -d
    return total


@jit()
def clamp(begin, value, d_cost, count, capacity):
    """A feasible selection reached from ``begin`` by decrements only: while over ``capacity``,
    drop the increments of lowest value (a cut of the taken increments); returns (steps, spent)."""
    k, n = value.shape
    spent = 0.0
    total_taken = 0
    for i in range(n):
        for j in range(begin[i]):
            spent += d_cost[j, i]
            total_taken += 1
    steps = begin.copy()
    if spent <= capacity:
        return steps, spent
    vals = np.empty(total_taken)
    wts = np.empty(total_taken)
    own = np.empty(total_taken, np.int64)
    t = 0
    for i in range(n):
        for j in range(begin[i]):
            vals[t] = -value[j, i]
            wts[t] = d_cost[j, i]
            own[t] = i
            t += 1
    srt = np.argsort(vals, kind="mergesort")
    for i in range(n):
        steps[i] = 0
    s = 0.0
    for t in range(total_taken):
        q = srt[t]
        if s + wts[q] > capacity:
            break
        s += wts[q]
        steps[own[q]] += 1
    return steps, s


def compile_all() -> None:
    """Call every kernel here once, with the argument types the solvers pass (on hulls from ``hull``)."""
    for b, c, ok, value, d_cost, opt, count, begin, hist in warm_up_inputs():
        n = count.size
        _, total = hull(b, c, ok.view(np.uint8), np.inf, np.array([0, 1, -1]), value, value.view(np.int64),
                        d_cost, opt, count, begin, hist)
        steps, ready_ = np.empty(n, np.int64), np.empty(n, np.int64)
        spent, _, _, nr = radix_cut(value, value.view(np.int64), d_cost, count, begin, 1.0, 3.0, hist, total,
                                    steps, ready_)
        ready(value, d_cost, count, steps, 3.0 - spent)
        fill_round(value, d_cost, count, steps, ready_[:nr], 3.0 - spent)
        finish(b, c, opt, value, count, steps)
        moves(steps, begin)
        clamp(begin, value, d_cost, count, 1.0)
