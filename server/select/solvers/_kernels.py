"""Compiled per-object loops of the greedy and the incremental solver (numba).

Each object's upper hull, its start on the hull and the weighted cut of all
increments at a value threshold are short loops per object: numpy needs many
passes and temporaries over (n, K) for them, a compiled loop needs one. The
kernels are pure functions of arrays (no clock, no I/O); ``greedy.upper_hull_numpy``
and the other ``*_numpy`` functions stay as the vectorised reference the tests
compare the kernels with.

Layout: hull arrays are (K, n), row j holding every object's j-th increment
(value = Δbenefit / Δcost, −inf in padding; Δcost, 0 in padding; opt = option
index of the j-th hull point, −1 in padding).

The cut of all increments at the value where the budget runs out is a radix
selection: one pass sums the increments' Δcost into bins of their value's
float64 bit pattern (exponent and the top ``RADIX_BITS`` mantissa bits, which
order positive floats), the bin where the running cost from the top crosses the
budget holds the threshold, and only that bin's increments are sorted. No
sample, no threshold guess, O(n·K).

The incremental solver's coherent step needs no stored hulls: ``coherent`` builds each
object's hull in a few registers, decides it outright unless it has increments in the
value band around the threshold, and keeps only the band's increments.

Compiling: ``cache=True`` keeps the machine code next to the module (or in the
user's cache directory when the package is read-only, or in memory when numba finds no
usable cache: then every process compiles once, ~10–25 s on a small machine). ``warm_up()``
compiles (or loads, ~0.5 s) every kernel with the types the solvers use, on tiny arrays.
"""

from __future__ import annotations

import math
import threading
import time

import numba
import numpy as np


def _jit(**options):
    """``numba.njit(cache=True, ...)``, without the cache when numba finds nowhere to keep it."""

    def wrap(fn):
        try:
            return numba.njit(cache=True, nogil=True, error_model="numpy", **options)(fn)
        except RuntimeError:  # "cannot cache function ...: no locator available" (read-only everywhere)
            return numba.njit(cache=False, nogil=True, error_model="numpy", **options)(fn)

    return wrap


#: Radix bins of an increment's value: the float64 bit pattern's exponent and top RADIX_BITS mantissa
#: bits (2**RADIX_BITS bins per octave, ~2 % wide each), over values in [2**-RADIX_OCTAVES, 2**RADIX_OCTAVES);
#: values outside share the end bins (still exact, only their bin is sorted whole).
RADIX_BITS = 5
RADIX_OCTAVES = 64
RADIX_SHIFT = 52 - RADIX_BITS
RADIX_LOW = (1023 - RADIX_OCTAVES) << RADIX_BITS
RADIX_BINS = (2 * RADIX_OCTAVES) << RADIX_BITS  # 4096 bins: 32 KB, a cache-resident histogram


@_jit(inline="always")
def _bin(bits):
    """Radix bin of a positive float64 from its bit pattern (monotone; 0 for 0 and below the range)."""
    return min(max((bits >> RADIX_SHIFT) - RADIX_LOW, 0), RADIX_BINS - 1)


@_jit()
def hull(benefit, cost, valid, cap, previous, value, bits, d_cost, opt, count, begin, hist):
    """Each object's upper concave hull of its usable options from (0, 0); fills the (K, n) outputs.

    Usable: valid, finite benefit, 0 < cost ≤ cap and cost finite. Options are sorted by
    cost (stable; skipped when already sorted), then a monotone chain drops options that
    cost no less and give no more, and options on or under the chord of their neighbours
    (the slope test of the numpy reference, on the same slopes).

    bits     : ``value.view(np.int64)``
    previous : (n,) option drawn last (−1: none) → ``begin``: the hull points costing no
               more than it (``start``); size 0 skips it
    hist     : (RADIX_BINS,) Σ Δcost of the increments per radix bin of their value
               (zeroed here); size 0 skips it
    Returns (flat index i·K + o of the usable option of highest benefit, first in flat
    order: the best single option, −1: none; Σ Δcost of every increment).
    """
    n, k = benefit.shape
    kk = cost.shape[1]
    order = np.empty(k, np.int64)
    sc = np.empty(k + 1)
    sb = np.empty(k + 1)
    ss = np.empty(k + 1)
    so = np.empty(k + 1, np.int64)
    best, best_b = -1, -np.inf
    do_prev = previous.size == n and n > 0
    do_hist = hist.size > 0
    for t in range(hist.size):
        hist[t] = 0.0
    total = 0.0
    for i in range(n):
        # Fast path, branch-free: every option usable, cost rising, value Δb/Δc positive and falling
        # (then the hull is every option in order). NaN and ±inf fail one of the tests.
        bad = 0
        pc, pb, pv = 0.0, 0.0, np.inf
        for o in range(k):
            c = cost[i, o]
            b = benefit[i, o]
            dc = c - pc
            v = (b - pb) / dc
            bad += (valid[i, o] == 0) + (not c <= cap) + (not c < np.inf) + (not dc > 0.0) + (not v > 0.0) \
                + (not v < pv)
            value[o, i] = v
            d_cost[o, i] = dc
            opt[o, i] = o
            pc, pb, pv = c, b, v
        if bad == 0:
            count[i] = k
            if pb > best_b:  # benefit rises along the options: the last is the object's best
                best, best_b = i * k + k - 1, pb
            for j in range(k):
                total += d_cost[j, i]
                if do_hist:
                    hist[_bin(bits[j, i])] += d_cost[j, i]
            if do_prev:
                p = previous[i]
                pp = min(max(p, 0), kk - 1)
                usable = (p >= 0) & (p < kk) & (valid[i, pp] != 0)
                c_prev = cost[i, pp] * (1.0 + 1e-12) if usable else -np.inf
                st = 0
                point = 0.0
                for j in range(k):
                    point += d_cost[j, i]
                    st += point <= c_prev
                begin[i] = st
            continue
        # Options unusable or out of cost order: the general hull (numba inlines it).
        top, bo, bb = _object_hull(benefit, cost, valid, cap, i, order, sc, sb, ss, so)
        if bb > best_b:
            best, best_b = i * k + bo, bb
        count[i] = top
        for j in range(top):
            dc = sc[j + 1] - sc[j]
            value[j, i] = ss[j + 1]
            d_cost[j, i] = dc
            opt[j, i] = so[j + 1]
            total += dc
            if do_hist:
                hist[_bin(bits[j, i])] += dc
        for j in range(top, k):
            value[j, i] = -np.inf
            d_cost[j, i] = 0.0
            opt[j, i] = -1
        if do_prev:
            p = previous[i]
            st = 0
            if p >= 0 and p < kk and valid[i, p]:
                c_prev = cost[i, p]
                if c_prev == c_prev:
                    c_prev *= 1.0 + 1e-12
                    point = 0.0
                    for j in range(top):
                        point += d_cost[j, i]
                        if point <= c_prev:
                            st = j + 1
                        else:
                            break
            begin[i] = st
    return best, total


@_jit()
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
            gt = (j < cn) & (_bin(bits[j, i]) > cross)
            s += gt
            above += d_cost[j, i] if gt else 0.0
        steps[i] = s
        ready[nb] = i
        nb += (s < cn) & (_bin(bits[min(s, k - 1), i]) == cross)
    m = 0
    for q in range(nb):
        i = ready[q]
        j = steps[i]
        while j < count[i] and _bin(bits[j, i]) == cross:
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
        while j < count[i] and _bin(bits[j, i]) == cross:
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


@_jit()
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


@_jit()
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


@_jit()
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


@_jit()
def start(cost, valid, previous, d_cost, count):
    """(n,) hull increments taken at the start: the hull points costing no more than the previous option.

    A previous option off the hull is clamped to the hull point below it; −1, an invalid
    index or option, or a NaN cost starts the object undrawn. (``hull`` does the same while
    it builds the hulls; this one is for a hull already built.)
    """
    k, n = d_cost.shape
    kk = cost.shape[1]
    steps = np.zeros(n, np.int64)
    for i in range(n):
        p = previous[i]
        if p < 0 or p >= kk or not valid[i, p]:
            continue
        c_prev = cost[i, p]
        if not c_prev == c_prev:
            continue
        c_prev *= 1.0 + 1e-12
        point = 0.0
        s = 0
        for j in range(count[i]):
            point += d_cost[j, i]
            if point <= c_prev:
                s = j + 1
            else:
                break
        steps[i] = s
    return steps


@_jit()
def moves(a, b):
    """Σ |a − b|: the increments and decrements between two step vectors."""
    total = 0
    for i in range(a.size):
        d = a[i] - b[i]
        total += d if d >= 0 else -d
    return total


@_jit()
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


# ----------------------------------------------------------------------------- the coherent step in one pass
#
# With a threshold θ known (last frame's, or estimated on a sample of objects), the incremental
# solver needs no hull arrays: one pass builds each object's hull in a few registers, takes its
# increments of value above θ·(1 + w), and lists the object if it has increments in the band
# (θ·(1 − w), θ·(1 + w)]; objects outside the band are final (but for fill rounds) and their
# option, totals and next increment are written at once. The band's increments are then sorted
# and cut (those taken at the start win ties). If the cut does not stop inside the band the pass
# says so and the caller runs the full path.


@_jit(inline="always")
def _object_hull(benefit, cost, valid, cap, i, order, sc, sb, ss, so):
    """Object i's hull in (sc, sb, ss, so)[0..top] (point 0 = (0, 0); ss[j] = value of the increment to
    point j; so[j] = its option); returns (top, option of highest usable benefit (first), that benefit)."""
    k = benefit.shape[1]
    bad = 0
    pc, pb, pv = 0.0, 0.0, np.inf
    sc[0], sb[0], ss[0], so[0] = 0.0, 0.0, np.inf, -1
    for o in range(k):
        c = cost[i, o]
        b = benefit[i, o]
        dc = c - pc
        v = (b - pb) / dc
        bad += (valid[i, o] == 0) + (not c <= cap) + (not c < np.inf) + (not dc > 0.0) + (not v > 0.0) \
            + (not v < pv)
        sc[o + 1], sb[o + 1], ss[o + 1], so[o + 1] = c, b, v, o
        pc, pb, pv = c, b, v
    if bad == 0:
        return k, k - 1, pb
    best_o, best_b = -1, -np.inf
    m = 0
    ascending = True
    last = -np.inf
    for o in range(k):
        c = cost[i, o]
        b = benefit[i, o]
        if valid[i, o] and c > 0.0 and c <= cap and c < np.inf and math.isfinite(b):
            if b > best_b:
                best_o, best_b = o, b
            if c < last:
                ascending = False
            last = max(last, c)
            order[m] = o
            m += 1
    if not ascending:
        for q in range(1, m):
            o = order[q]
            c = cost[i, o]
            p = q
            while p > 0 and cost[i, order[p - 1]] > c:
                order[p] = order[p - 1]
                p -= 1
            order[p] = o
    top = 0
    for q in range(m):
        o = order[q]
        c, b = cost[i, o], benefit[i, o]
        if b <= sb[top]:
            continue
        s = np.inf
        while True:
            if c == sc[top]:
                top -= 1
                continue
            s = (b - sb[top]) / (c - sc[top])
            if top >= 1 and ss[top] <= s:
                top -= 1
                continue
            break
        top += 1
        sc[top], sb[top], ss[top], so[top] = c, b, s, o
    return top, best_o, best_b


@_jit()
def _begin(cost, valid, previous, i, sc, top):
    """Object i's start on its hull (``start``), the hull in sc[0..top]."""
    kk = cost.shape[1]
    if previous.size == 0:
        return 0
    p = previous[i]
    pp = min(max(p, 0), kk - 1)
    usable = (p >= 0) & (p < kk) & (valid[i, pp] != 0)
    c_prev = cost[i, pp] * (1.0 + 1e-12) if usable else -np.inf
    st = 0
    point = 0.0
    for j in range(top):
        point += sc[j + 1] - sc[j]
        st += point <= c_prev
    return st


@_jit()
def estimate(benefit, cost, valid, cap, capacity, stride):
    """The value where the greedy's cut would stop, from the hulls of every ``stride``-th object
    (weights scaled by ``stride``), to a radix bin (~2 %); −1 when the sample fits whole."""
    n, k = benefit.shape
    order = np.empty(k, np.int64)
    sc, sb, ss = np.empty(k + 1), np.empty(k + 1), np.empty(k + 1)
    so = np.empty(k + 1, np.int64)
    hist = np.zeros(RADIX_BINS)
    fb = np.empty(1)
    ib = fb.view(np.int64)
    for i in range(0, n, stride):
        top, _, _ = _object_hull(benefit, cost, valid, cap, i, order, sc, sb, ss, so)
        for j in range(1, top + 1):
            fb[0] = ss[j]
            hist[_bin(ib[0])] += (sc[j] - sc[j - 1]) * stride
    acc = 0.0
    for q in range(RADIX_BINS - 1, -1, -1):
        acc += hist[q]
        if acc > capacity:
            ib[0] = (q + RADIX_LOW) << RADIX_SHIFT  # the bin's lower edge; its middle is 1/64 octave above
            return fb[0] * (1.0 + 1.0 / (2 << RADIX_BITS))
    return -1.0


@_jit()
def coherent(benefit, cost, valid, cap, previous, theta, width, capacity, keep, level, steps, nxt_v, nxt_c,
             band_f, band_i, acc):
    """The coherent step's pass and band cut (see above). Writes ``level``, ``steps``, each object's next
    increment (``nxt_v``, ``nxt_c``; −inf, 0: none) and acc = [Σ cost, Σ benefit, moves, increments,
    hull points]. band_f (6, cap), band_i (3, cap): scratch for the band's increments (more than cap:
    not settled). Returns (settled, objects in the band, stop value, best single option (flat), spent)."""
    n, k = benefit.shape
    order = np.empty(k, np.int64)
    sc, sb, ss = np.empty(k + 1), np.empty(k + 1), np.empty(k + 1)
    so = np.empty(k + 1, np.int64)
    lo, hi = theta * (1.0 - width), theta * (1.0 + width)
    fixed, band_w, rest_w = 0.0, 0.0, 0.0
    c_sum, b_sum, moves, incs, cands = 0.0, 0.0, 0, 0, 0
    m, nb = 0, 0
    cap_items = band_f.shape[1]
    best, best_b = -1, -np.inf
    kk = k
    do_prev = previous.size == n
    for i in range(n):
        # The usual concave object inline (branch-free, as in ``hull``); the others in _object_hull.
        bad_u, bad_c = 0, 0
        pc, pb, pv = 0.0, 0.0, np.inf
        bo, bb = -1, -np.inf
        sc[0], sb[0], ss[0], so[0] = 0.0, 0.0, np.inf, -1
        for o in range(k):
            c = cost[i, o]
            b = benefit[i, o]
            dc = c - pc
            v = (b - pb) / dc
            bad_u += (valid[i, o] == 0) + (not c <= cap) + (not c < np.inf) + (not dc > 0.0) + (not abs(b) < np.inf)
            bad_c += (not v > 0.0) + (not v < pv)
            bo = o if b > bb else bo
            bb = max(bb, b)
            sc[o + 1], sb[o + 1], ss[o + 1], so[o + 1] = c, b, v, o
            pc, pb, pv = c, b, v
        if bad_u + bad_c == 0:
            top = k
        elif bad_u == 0:
            # Every option usable, cost rising, but not concave (say the coarsest level lies under the
            # chord): the chain runs in place over the points as they are.
            top = 0
            for q in range(1, k + 1):
                c, b, o = sc[q], sb[q], so[q]
                if b <= sb[top]:
                    continue
                sl = np.inf
                while True:
                    sl = (b - sb[top]) / (c - sc[top])
                    if top >= 1 and ss[top] <= sl:
                        top -= 1
                        continue
                    break
                top += 1
                sc[top], sb[top], ss[top], so[top] = c, b, sl, o
        else:  # options unusable or out of cost order: the general hull (inlined by numba)
            top, bo, bb = _object_hull(benefit, cost, valid, cap, i, order, sc, sb, ss, so)
        if bb > best_b:
            best, best_b = i * k + bo, bb
        cands += top
        s_hi, s_lo = 0, 0
        for j in range(1, top + 1):
            s_hi += ss[j] > hi
            s_lo += ss[j] > lo
        steps[i] = s_hi
        fixed += sc[s_hi]
        rest_w += sc[top] - sc[s_lo]
        level[i] = so[s_hi]
        c_sum += sc[s_hi]
        b_sum += sb[s_hi]
        incs += s_hi
        st = 0
        if do_prev:
            p = previous[i]
            pp = min(max(p, 0), kk - 1)
            usable = (p >= 0) & (p < kk) & (valid[i, pp] != 0)
            c_prev = cost[i, pp] * (1.0 + 1e-12) if usable else -np.inf
            for j in range(1, top + 1):
                st += sc[j] <= c_prev  # (``start`` sums the Δcosts: the same up to the 1e-12 slack)
        moves += abs(s_hi - st)
        more = s_hi < top
        nxt_v[i] = ss[min(s_hi + 1, k)] if more else -np.inf
        nxt_c[i] = sc[min(s_hi + 1, k)] - sc[s_hi] if more else 0.0
        nb += s_lo > s_hi
        if s_lo > s_hi:
            # The band's increments, with what taking each changes (its object's hull is gone after this).
            band_w += sc[s_lo] - sc[s_hi]
            for j in range(s_hi + 1, s_lo + 1):
                if m < cap_items:
                    nx = j < top
                    band_f[0, m] = -(ss[j] * keep) if j <= st else -ss[j]
                    band_f[1, m] = ss[j]
                    band_f[2, m] = sc[j] - sc[j - 1]
                    band_f[3, m] = sb[j] - sb[j - 1]
                    band_f[4, m] = ss[min(j + 1, k)] if nx else -np.inf
                    band_f[5, m] = sc[min(j + 1, k)] - sc[j] if nx else 0.0
                    band_i[0, m] = i
                    band_i[1, m] = so[j]
                    band_i[2, m] = st
                m += 1
    room = capacity - fixed
    acc[0], acc[1], acc[2], acc[3], acc[4] = c_sum, b_sum, moves, incs, cands
    if m > cap_items or not (room >= 0.0 and (room < band_w or rest_w == 0.0)):
        return False, nb, -np.inf, best, 0.0
    srt = np.argsort(band_f[0, :m], kind="mergesort")
    spent = fixed
    stop = -np.inf
    for q in range(m):
        r = srt[q]
        w = band_f[2, r]
        if spent + w > capacity:
            stop = band_f[1, r]
            break
        spent += w
        i = band_i[0, r]
        s = steps[i]
        acc[0] += w
        acc[1] += band_f[3, r]
        acc[2] += 1 if s >= band_i[2, r] else -1
        acc[3] += 1
        steps[i] = s + 1
        level[i] = band_i[1, r]
        nxt_v[i] = band_f[4, r]
        nxt_c[i] = band_f[5, r]
    return True, nb, stop, best, spent


@_jit()
def coherent_ready(nxt_v, nxt_c, remaining, out):
    """The objects whose next increment exists and fits ``remaining`` into ``out``; how many."""
    r = 0
    for i in range(nxt_v.size):
        out[r] = i
        r += (nxt_v[i] > -np.inf) & (nxt_c[i] <= remaining)
    return r


@_jit()
def coherent_fill_round(benefit, cost, valid, cap, previous, steps, level, nxt_v, nxt_c, idx, remaining, acc):
    """``fill_round`` on the one-pass state: the taken objects' hulls are built again for their new
    option, totals and next increment. Returns (objects that were ready, remaining, increments taken)."""
    n, k = benefit.shape
    order = np.empty(k, np.int64)
    sc, sb, ss = np.empty(k + 1), np.empty(k + 1), np.empty(k + 1)
    so = np.empty(k + 1, np.int64)
    m = 0
    live = np.empty(idx.size, np.int64)
    for t in range(idx.size):
        i = idx[t]
        if nxt_v[i] > -np.inf and nxt_c[i] <= remaining:
            live[m] = i
            m += 1
    live = live[:m]
    if m == 0:
        return live, remaining, 0
    keys = np.empty(m)
    for t in range(m):
        keys[t] = -nxt_v[live[t]]
    srt = np.argsort(keys, kind="mergesort")
    added = 0.0
    took = 0
    for t in range(m):
        w = nxt_c[live[srt[t]]]
        if t > 0 and added + w > remaining:
            break
        added += w
        took += 1
    for t in range(took):
        i = live[srt[t]]
        top, _, _ = _object_hull(benefit, cost, valid, cap, i, order, sc, sb, ss, so)
        s = steps[i]
        beg = _begin(cost, valid, previous, i, sc, top)
        acc[0] += sc[s + 1] - sc[s]
        acc[1] += sb[s + 1] - sb[s]
        acc[2] += 1 if s >= beg else -1
        acc[3] += 1
        steps[i] = s + 1
        level[i] = so[s + 1]
        more = s + 1 < top
        nxt_v[i] = ss[min(s + 2, k)] if more else -np.inf
        nxt_c[i] = sc[min(s + 2, k)] - sc[s + 1] if more else 0.0
    return live, remaining - added, took


# ----------------------------------------------------------------------------- warming up

_warm_lock = threading.Lock()
_warm_seconds: float | None = None


def warm_up() -> float:
    """Compile (or load from the cache) every kernel for the solvers' argument types; seconds taken.

    Idempotent and thread-safe: later calls return the first call's time at once.
    """
    global _warm_seconds
    with _warm_lock:
        if _warm_seconds is not None:
            return _warm_seconds
        t0 = time.perf_counter()
        try:
            _compile_all()
        except OSError:
            # The cache numba chose cannot be read or written (e.g. a path under a file): compile in memory.
            from numba.core.caching import NullCache

            for fn in list(globals().values()):
                if isinstance(fn, numba.core.registry.CPUDispatcher):
                    fn._cache = NullCache()
            _compile_all()
        _warm_seconds = time.perf_counter() - t0
        return _warm_seconds


def _compile_all() -> None:
    """Call every kernel once, with the argument types the solvers pass."""
    b = np.array([[1.0, 1.5], [2.0, 2.2], [1.0, 0.5]])
    c = np.array([[1.0, 3.0], [1.0, 2.0], [2.0, 1.0]])
    ok = np.ones(b.shape, bool)
    k, n = 2, 3
    for opt_dtype in (np.int16, np.int64):
        value, d_cost = np.empty((k, n)), np.empty((k, n))
        opt, count = np.empty((k, n), opt_dtype), np.empty(n, np.int64)
        begin, hist = np.empty(n, np.int64), np.empty(RADIX_BINS)
        for prev, h in ((np.array([0, 1, -1]), hist), (np.empty(0, np.int64), np.empty(0))):
            _, total = hull(b, c, ok.view(np.uint8), np.inf, prev, value, value.view(np.int64), d_cost, opt,
                            count, begin, h)
        _, total = hull(b, c, ok.view(np.uint8), np.inf, np.array([0, 1, -1]), value, value.view(np.int64),
                        d_cost, opt, count, begin, hist)
        steps, ready_ = np.empty(n, np.int64), np.empty(n, np.int64)
        spent, _, _, nr = radix_cut(value, value.view(np.int64), d_cost, count, begin, 1.0, 3.0, hist, total,
                                    steps, ready_)
        fill_round(value, d_cost, count, steps, ready_[:nr], 3.0 - spent)
        finish(b, c, opt, value, count, steps)
        moves(steps, begin)
        start(c, ok, np.array([0, 1, -1]), d_cost, count)
        clamp(begin, value, d_cost, count, 1.0)
    u8 = ok.view(np.uint8)
    prev = np.array([0, 1, -1])
    theta = estimate(b, c, u8, np.inf, 3.0, 1)
    level, steps, nv, nc, band = (np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n), np.empty(n),
                                  np.empty(n, np.int64))
    acc = np.zeros(5)
    _, _, _, _, spent = coherent(b, c, u8, 3.0, prev, max(theta, 1.0), 0.1, 3.0, 1.0, level, steps, nv, nc,
                                 np.empty((6, 8)), np.empty((3, 8), np.int64), acc)
    r = coherent_ready(nv, nc, 3.0 - spent, band)
    coherent_fill_round(b, c, u8, 3.0, prev, steps, level, nv, nc, band[:r], 3.0 - spent, acc)
