"""The online cost model's choice among its three rungs, compiled (numba) for ``fold``.

``OnlineCostModel._select`` is the reference: the rung whose recent held-out error
is within ``within`` of the best, the simplest first, a step up only when the
current rung is worse beyond the noise, and a regime change (the chosen rung far
off on each of the last frames) switching at once. The errors are the deques
``err`` (3, window) with their counts ``err_n``; ``mi`` and ``mp`` are the fold's
state and parameters (see ``fold``).

Pure functions of arrays (no clock, no I/O).
"""

from __future__ import annotations

import math

import numpy as np

from .jit import jit

__all__ = ["choose", "REGIME"]

#: REGIME_FRAMES, REGIME_ERROR, REGIME_RATIO (checked equal to ``cost_online``'s by the tests).
REGIME = (2, 0.3, 3.0)


@jit()
def _fsum(a, lo, hi):
    """math.fsum(a[lo:hi]): the correctly rounded sum (Shewchuk's partials, as CPython)."""
    p = np.empty(max(hi - lo, 1) + 1)
    n = 0
    for idx in range(lo, hi):
        x = a[idx]
        i = 0
        for j in range(n):
            y = p[j]
            if abs(x) < abs(y):
                x, y = y, x
            h = x + y
            lo_ = y - (h - x)
            if lo_ != 0.0:
                p[i] = lo_
                i += 1
            x = h
        n = i
        if x != 0.0:
            p[n] = x
            n += 1
    h = 0.0
    if n > 0:
        n -= 1
        h = p[n]
        lo_ = 0.0
        while n > 0:
            x = h
            n -= 1
            y = p[n]
            h = x + y
            lo_ = y - (h - x)
            if lo_ != 0.0:
                break
        if n > 0 and ((lo_ < 0.0 and p[n - 1] < 0.0) or (lo_ > 0.0 and p[n - 1] > 0.0)):
            y = lo_ * 2.0
            x = h + y
            if y == x - h:
                h = x
    return h


@jit()
def _scores(err, err_n, n, out):
    for j in range(3):
        m = err_n[j]
        if m == 0:
            out[j] = np.inf
        else:
            use = min(n, m)
            out[j] = _fsum(err[j], m - use, m) / use


@jit()
def _worse(a, b, err, err_n, recent):
    """``OnlineCostModel._worse``: a's recent held-out errors above b's beyond the noise (paired t > 1.5)."""
    n = min(recent, err_n[a])
    if n < 2:
        return True
    d = np.empty(n)
    for i in range(n):
        d[i] = err[a, err_n[a] - n + i] - err[b, err_n[b] - n + i]
    return d.mean() > 1.5 * d.std() * math.sqrt(n / (n - 1.0)) / math.sqrt(n)


@jit()
def choose(err, err_n, mi, mp, window):
    """``OnlineCostModel._select``."""
    within, min_frames, recent, hold = mp[1], int(mp[2]), int(mp[3]), int(mp[4])
    chosen = mi[0]
    sc = np.empty(3)
    if mi[3] < min_frames:
        target = 0
    else:
        frames, error, ratio = REGIME
        regime = False
        if err_n[chosen] >= frames:
            lowest = np.inf
            for i in range(frames):
                lowest = min(lowest, err[chosen, err_n[chosen] - frames + i])
            if lowest > error:
                for o in range(3):
                    if o != chosen and err_n[o] >= frames:
                        every = True
                        for i in range(frames):
                            every &= err[chosen, err_n[chosen] - frames + i] > ratio * err[o, err_n[o] - frames + i]
                        if every:
                            regime = True
        if regime:
            _scores(err, err_n, frames, sc)
            best = 0
            for o in range(1, 3):
                if sc[o] < sc[best]:
                    best = o
            mi[0] = best
            mi[2] = 0
            return
        _scores(err, err_n, recent, sc)
        limit = (1.0 + within) * sc.min()
        # The whole window's scores only judge a step down: summed (exactly, as math.fsum) only when one is asked.
        whole = np.empty(3)
        down = False
        for o in range(chosen):
            down |= sc[o] <= limit
        if down:
            _scores(err, err_n, window, whole)
        limit_whole = (1.0 + within) * whole.min() if down else np.inf
        target = -1
        for o in range(3):
            if sc[o] <= limit and (o >= chosen or whole[o] <= limit_whole):
                target = o
                break
        if target < 0:
            target = 0
            for o in range(1, 3):
                if sc[o] < sc[target]:
                    target = o
        if target > chosen and not _worse(chosen, target, err, err_n, recent):
            target = chosen
    if target == chosen:
        mi[2] = 0
        return
    mi[2] = mi[2] + 1 if target == mi[1] else 1
    mi[1] = target
    if mi[2] >= hold:
        mi[0] = target
        mi[2] = 0
