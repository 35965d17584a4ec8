"""The incremental solver's coherent step in one compiled pass (numba).

With a threshold θ known (last frame's, or ``estimate``d on a sample of objects),
the incremental solver needs no hull arrays: one pass (``coherent``) builds each
object's hull in a few registers (``kernels.hull.object_hull``), takes its
increments of value above θ·(1 + w), and lists the object if it has increments in
the band (θ·(1 − w), θ·(1 + w)]; objects outside the band are final (but for fill
rounds) and their option, totals and next increment are written at once. The
band's increments are then sorted and cut (those taken at the start win ties). If
the cut does not stop inside the band the pass says so and the caller runs the
full path (stored hulls and ``kernels.cut.radix_cut``).

Pure functions of arrays (no clock, no I/O); ``solvers.incremental.solve_numpy``
stays the vectorised reference.
"""

from __future__ import annotations

import numpy as np

from .hull import RADIX_BINS, RADIX_BITS, RADIX_LOW, RADIX_SHIFT, object_hull, radix_bin
from .jit import jit

__all__ = ["estimate", "coherent", "coherent_ready", "coherent_fill_round", "compile_all"]


@jit()
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


@jit()
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
        top, _, _ = object_hull(benefit, cost, valid, cap, i, order, sc, sb, ss, so)
        for j in range(1, top + 1):
            fb[0] = ss[j]
            hist[radix_bin(ib[0])] += (sc[j] - sc[j - 1]) * stride
    acc = 0.0
    for q in range(RADIX_BINS - 1, -1, -1):
        acc += hist[q]
        if acc > capacity:
            ib[0] = (q + RADIX_LOW) << RADIX_SHIFT  # the bin's lower edge; its middle is 1/64 octave above
            return fb[0] * (1.0 + 1.0 / (2 << RADIX_BITS))
    return -1.0


@jit()
def coherent(benefit, cost, valid, cap, previous, theta, width, capacity, keep, level, steps, nxt_v, nxt_c,
             band_f, band_i, acc):
    """The coherent step's pass and band cut (the module's text). Writes ``level``, ``steps``, each object's next
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
    cap_f = min(cap, 1.7976931348623157e308)  # also ``cost < inf``
    for i in range(n):
        # The usual concave object inline (branch-free, as in ``hull``); the others in _object_hull.
        good, usable = True, True
        f_hi, f_lo = 0, 0
        pc, pb, pv = 0.0, 0.0, np.inf
        sc[0], sb[0], ss[0], so[0] = 0.0, 0.0, np.inf, -1
        for o in range(k):
            c = cost[i, o]
            b = benefit[i, o]
            dc = c - pc
            v = (b - pb) / dc
            # Usable, cost rising, value positive and falling. An infinite or NaN benefit makes v fail a test.
            use = (valid[i, o] != 0) & (c <= cap_f) & (dc > 0.0)
            usable &= use & (abs(b) < np.inf)
            good &= use & (v > 0.0) & (v < pv)
            f_hi += v > hi
            f_lo += v > lo
            sc[o + 1], sb[o + 1], ss[o + 1], so[o + 1] = c, b, v, o
            pc, pb, pv = c, b, v
        if good:
            top, bo, bb = k, k - 1, pb  # benefit rises along the options: the last is the best
        elif usable:
            bo, bb = -1, -np.inf
            for o in range(k):
                bo = o if sb[o + 1] > bb else bo
                bb = max(bb, sb[o + 1])
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
            top, bo, bb = object_hull(benefit, cost, valid, cap, i, order, sc, sb, ss, so)
        if bb > best_b:
            best, best_b = i * k + bo, bb
        cands += top
        if good:
            s_hi, s_lo = f_hi, f_lo
        else:
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


@jit()
def coherent_ready(nxt_v, nxt_c, remaining, out):
    """The objects whose next increment exists and fits ``remaining`` into ``out``; how many."""
    r = 0
    for i in range(nxt_v.size):
        out[r] = i
        r += (nxt_v[i] > -np.inf) & (nxt_c[i] <= remaining)
    return r


@jit()
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
        top, _, _ = object_hull(benefit, cost, valid, cap, i, order, sc, sb, ss, so)
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


def compile_all() -> None:
    """Call every kernel here once, with the argument types the incremental solver passes."""
    b = np.array([[1.0, 1.5], [2.0, 2.2], [1.0, 0.5]])
    c = np.array([[1.0, 3.0], [1.0, 2.0], [2.0, 1.0]])
    u8 = np.ones(b.shape, np.uint8)
    n = 3
    prev = np.array([0, 1, -1])
    theta = estimate(b, c, u8, np.inf, 3.0, 1)
    level, steps, nv, nc, band = (np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n), np.empty(n),
                                  np.empty(n, np.int64))
    acc = np.zeros(5)
    _, _, _, _, spent = coherent(b, c, u8, 3.0, prev, max(theta, 1.0), 0.1, 3.0, 1.0, level, steps, nv, nc,
                                 np.empty((6, 8)), np.empty((3, 8), np.int64), acc)
    r = coherent_ready(nv, nc, 3.0 - spent, band)
    coherent_fill_round(b, c, u8, 3.0, prev, steps, level, nv, nc, band[:r], 3.0 - spent, acc)
