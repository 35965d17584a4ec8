"""The path predictor's fit in one compiled pass (numba).

``predict.Predictor._refit`` fits a recency-weighted line to the last second of
poses (eye, forward, up: nine columns), reweights it against outliers for a few
rounds (Huber, per eye / forward / up) and shrinks each rate by its noise. On a
dozen samples that is a few dozen small numpy calls; here it is a loop over the
samples per round. ``predict`` keeps the numpy code as the reference (the tests
compare, to rounding: the sums run in another order).

Pure functions of arrays (no clock, no I/O).
"""

from __future__ import annotations

import numpy as np

from .jit import jit

__all__ = ["refit", "compile_all"]


@jit()
def _line(s, x, w, a, b):
    """``predict._line``: weighted least-squares line x ≈ a + b·s per column, into a, b (9,)."""
    n = s.shape[0]
    for c in range(9):
        s0 = s1 = ss = sy = sxy = 0.0
        for i in range(n):
            wi = w[i, c]
            s0 += wi
            s1 += wi * s[i]
            ss += wi * s[i] * s[i]
            sy += wi * x[i, c]
            sxy += s[i] * wi * x[i, c]
        det = s0 * ss - s1 * s1
        if det > 1e-10 * s0 * s0:
            b[c] = (s0 * sxy - s1 * sy) / det
            a[c] = (ss * sy - s1 * sxy) / det
        else:
            b[c] = 0.0
            a[c] = sy / max(s0, 1e-300)


@jit()
def refit(t, x, half_life, rounds, huber, shrink, floor):
    """(a, b) (9,) each: the line the predictor extrapolates, fitted to times t (n,) and poses x (n, 9).

    floor : (3,) the least robust scale of eye, forward and up residuals."""
    n = t.shape[0]
    s = t - t[n - 1]
    recency = np.empty(n)
    for i in range(n):
        recency[i] = 0.5 ** (-s[i] / half_life)
    w = np.empty((n, 9))
    for i in range(n):
        for c in range(9):
            w[i, c] = recency[i]
    a, b = np.empty(9), np.empty(9)
    _line(s, x, w, a, b)
    res = np.empty((n, 3))
    col = np.empty(n)
    for _ in range(rounds if n > 2 else 0):
        for i in range(n):
            for g in range(3):
                q = 0.0
                for c in range(3 * g, 3 * g + 3):
                    r = x[i, c] - a[c] - b[c] * s[i]
                    q += r * r
                res[i, g] = np.sqrt(q)
        for g in range(3):
            for i in range(n):
                col[i] = res[i, g]
            scale = max(huber * np.sort(col)[(n - 1) // 2], floor[g])  # the lower median
            for i in range(n):
                f = recency[i] * min(1.0, scale / max(res[i, g], 1e-300))
                for c in range(3 * g, 3 * g + 3):
                    w[i, c] = f
        _line(s, x, w, a, b)
    if n > 2 and shrink > 0:
        keep = np.empty(3)
        for g in range(3):
            var_g = 0.0
            b2 = 0.0
            for c in range(3 * g, 3 * g + 3):
                sw = 0.0
                sws = 0.0
                for i in range(n):
                    sw += w[i, c]
                    sws += w[i, c] * s[i]
                s_bar = sws / sw
                sxx = 0.0
                num = 0.0
                for i in range(n):
                    d = s[i] - s_bar
                    r = x[i, c] - a[c] - b[c] * s[i]
                    sxx += w[i, c] * d * d
                    num += w[i, c] * w[i, c] * d * d * r * r
                var_g += num / max(sxx * sxx, 1e-300)
                b2 += b[c] * b[c]
            keep[g] = min(max(1.0 - shrink * var_g / max(b2, 1e-300), 0.0), 1.0) if b2 > 0 else 1.0
        for c in range(9):
            b[c] *= keep[c // 3]
    return a, b


def compile_all() -> None:
    """Fit three samples once, with the types the predictor passes."""
    t = np.array([0.0, 0.1, 0.2])
    x = np.zeros((3, 9))
    x[:, 0] = t
    x[:, 3] = x[:, 8] = 1.0
    refit(t, x, 0.5, 3, 2.5, 4.0, np.array([1e-4, 1e-6, 1e-6]))
