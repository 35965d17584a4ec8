"""Each object's upper concave hull of its options, in one compiled pass per object (numba).

The greedy and the incremental solver walk each object's hull from (0, 0) = not
drawn: numpy needs many passes and temporaries over (n, K) to build them, a compiled
loop needs one. Pure functions of arrays (no clock, no I/O);
``solvers.greedy.upper_hull_numpy`` stays the vectorised reference the tests compare
``hull`` with, ``solvers.incremental.start_numpy`` the one of ``start``.

Layout: hull arrays are (K, n), row j holding every object's j-th increment
(value = Δbenefit / Δcost, −inf in padding; Δcost, 0 in padding; opt = option
index of the j-th hull point, −1 in padding).

``hull`` also fills the radix histogram of the increments' values that the cut
(``kernels.cut.radix_cut``) reads: bins of the value's float64 bit pattern
(exponent and the top ``RADIX_BITS`` mantissa bits, which order positive floats).
``object_hull`` is one object's hull in a few registers, for objects whose options
are unusable or out of cost order here and for every object in the coherent step.
"""

from __future__ import annotations

import math

import numpy as np

from .jit import jit

__all__ = ["RADIX_BITS", "RADIX_OCTAVES", "RADIX_SHIFT", "RADIX_LOW", "RADIX_BINS", "radix_bin", "hull",
           "start", "object_hull", "general_hull", "warm_up_inputs", "compile_all"]


#: Radix bins of an increment's value: the float64 bit pattern's exponent and top RADIX_BITS mantissa
#: bits (2**RADIX_BITS bins per octave, ~2 % wide each), over values in [2**-RADIX_OCTAVES, 2**RADIX_OCTAVES);
#: values outside share the end bins (still exact, only their bin is sorted whole).
RADIX_BITS = 5
RADIX_OCTAVES = 64
RADIX_SHIFT = 52 - RADIX_BITS
RADIX_LOW = (1023 - RADIX_OCTAVES) << RADIX_BITS
RADIX_BINS = (2 * RADIX_OCTAVES) << RADIX_BITS  # 4096 bins: 32 KB, a cache-resident histogram


@jit(inline="always")
def radix_bin(bits):
    """Radix bin of a positive float64 from its bit pattern (monotone; 0 for 0 and below the range)."""
    return min(max((bits >> RADIX_SHIFT) - RADIX_LOW, 0), RADIX_BINS - 1)


@jit()
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
                    hist[radix_bin(bits[j, i])] += d_cost[j, i]
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
        top, bo, bb = general_hull(benefit, cost, valid, cap, i, order, sc, sb, ss, so)
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
                hist[radix_bin(bits[j, i])] += dc
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


@jit()
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


@jit(inline="always")
def object_hull(benefit, cost, valid, cap, i, order, sc, sb, ss, so):
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
    return general_hull(benefit, cost, valid, cap, i, order, sc, sb, ss, so)


@jit(inline="always")
def general_hull(benefit, cost, valid, cap, i, order, sc, sb, ss, so):
    """``object_hull`` for an object known not to be the usual concave one (options unusable, duplicated or
    out of cost order): usable options sorted by cost, then the monotone chain."""
    k = benefit.shape[1]
    sc[0], sb[0], ss[0], so[0] = 0.0, 0.0, np.inf, -1
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


def warm_up_inputs():
    """A tiny instance and empty hull arrays, once per option dtype the solvers use: what the compile
    passes of this module and of ``cut`` call their kernels with."""
    b = np.array([[1.0, 1.5], [2.0, 2.2], [1.0, 0.5]])
    c = np.array([[1.0, 3.0], [1.0, 2.0], [2.0, 1.0]])
    ok = np.ones(b.shape, bool)
    k, n = 2, 3
    for opt_dtype in (np.int16, np.int64):
        value, d_cost = np.empty((k, n)), np.empty((k, n))
        opt, count = np.empty((k, n), opt_dtype), np.empty(n, np.int64)
        begin, hist = np.empty(n, np.int64), np.empty(RADIX_BINS)
        yield b, c, ok, value, d_cost, opt, count, begin, hist


def compile_all() -> None:
    """Call every kernel here once, with the argument types the solvers pass."""
    for b, c, ok, value, d_cost, opt, count, begin, hist in warm_up_inputs():
        for prev, h in ((np.array([0, 1, -1]), hist), (np.empty(0, np.int64), np.empty(0))):
            hull(b, c, ok.view(np.uint8), np.inf, prev, value, value.view(np.int64), d_cost, opt, count, begin, h)
        start(c, ok, np.array([0, 1, -1]), d_cost, count)
