"""The online cost model's frame reports folded in one compiled pass (numba).

``OnlineCostModel.observe`` folds one frame into three robust RLS estimators and
picks the model to use; it is a few dozen numpy calls on vectors of at most
3R + 3 entries, so a frame costs far more in calls than in arithmetic. A session
keeps the reports that arrive between two selections and folds them all at once
(``cost_fold.fold``): the same steps, frame by frame and rung by rung in the same
order, on the model's state packed into arrays — which this module updates in
place. The Python methods (``rls.RobustRLS.update``, ``cost_online._Rung`` and
``OnlineCostModel.observe``) stay the reference, and the tests fold the same
frames both ways. The choice among the rungs after each frame is ``choose``'s.

Layout (R algorithms, K = 3R + 3, rung j = 0 vertex, 1 draw, 2 stages, of k_j =
1, R + 3 and K coefficients; arrays are padded to K):

    phi, scale, lower, upper (3, K); cov (3, K, K); seen (3, K) uint8
    rs (3, 8): hi, lo, updates, changes, num, den, geometry-side frames, fill-side frames
    rp (3, 8): forgetting, huber, floor, reopen, slack, threshold, clip, cap
    res, up, down, err (3, ·) with counts (3,) each: the deques, oldest first
    fill (3, window) uint8 with its count
    mi (4,) int64: chosen, pending, count, frames; mf (3,): least, faces, verts
    ratios (100,) and its count (1,)
    mp (8,): lam, within, min_frames, recent, hold, tail_min_time, least_slack, least_rise
    alg (R,): ALGORITHM_SCALE per algorithm
    times (F,), z (F, K), only_least (F,) uint8: the frames, in order

Pure functions of arrays (no clock, no I/O).
"""

from __future__ import annotations

import math

import numpy as np

from ..rls import BOX_TIE
from .choose import choose
from .jit import jit

__all__ = ["fold", "compile_all", "RESCALE_SHARE", "SECONDARY", "YOUNG", "TIE"]

#: The constants of ``rls`` and ``cost_online`` (checked equal by the tests).
RESCALE_SHARE = 0.05
SECONDARY = 0.25
YOUNG = 10
TIE = 1e-9
_EPS = np.finfo(np.float64).eps


@jit()
def _push(buf, n, v):
    """Append v to the deque buf[:n] (oldest first), dropping the oldest when full; the new count."""
    m = buf.shape[0]
    if m == 0:
        return 0
    if n < m:
        buf[n] = v
        return n + 1
    for i in range(m - 1):
        buf[i] = buf[i + 1]
    buf[m - 1] = v
    return m


@jit()
def _k(j, r):
    return 1 if j == 0 else (r + 3 if j == 1 else 3 * r + 3)


@jit()
def _col(j, r, i):
    """The z-layout column of rung j's coefficient i (rung 0 has no column of its own)."""
    if j == 2:
        return i
    if i == 0:
        return 0
    if i <= r:
        return r + i
    return 3 * r + 3 - (r + 3 - i)


@jit()
def _theta(j, r, phi, scale, seen, alg, th):
    """``_Rung.theta``: coefficients in force, an algorithm never drawn following those drawn."""
    k = _k(j, r)
    for i in range(k):
        th[i] = phi[j, i] * scale[j, i]
    blocks = 0 if j == 0 else (1 if j == 1 else 3)
    for b in range(blocks):
        first = 1 + b * r
        n_seen = 0
        for a in range(r):
            n_seen += seen[j, first + a] != 0
        if 0 < n_seen < r:
            m = 0.0
            for a in range(r):
                if seen[j, first + a] != 0:
                    m += th[first + a] / alg[a]
            m /= n_seen
            for a in range(r):
                if seen[j, first + a] == 0:
                    th[first + a] = m * alg[a]


@jit()
def _full(j, r, phi, scale, seen, alg, th, c):
    """``_Rung.full``: the rung's coefficients in the z layout, into c (K,)."""
    _theta(j, r, phi, scale, seen, alg, th)
    c[:] = 0.0
    if j == 0:
        for a in range(r):
            c[1 + r + a] = th[0]
        c[3 * r + 2] = th[0]
    else:
        for i in range(_k(j, r)):
            c[_col(j, r, i)] = th[i]


@jit()
def _sides(c, z, r):
    """The geometry side C1·F + C2·V and the fill side C3·P of a z-layout frame."""
    g = 0.0
    for i in range(1, 1 + 2 * r):
        g += c[i] * z[i]
    f = 0.0
    for i in range(1 + 2 * r, 1 + 3 * r):
        f += c[i] * z[i]
    return g, f


@jit()
def _frame(c, z, r):
    """Frame seconds for one z-layout frame: c0 + max(C1·F + C2·V, C3·P) + C0·D + c_splat·S."""
    g, f = _sides(c, z, r)
    return c[0] + max(g, f) + c[3 * r + 1] * z[3 * r + 1] + c[3 * r + 2] * z[3 * r + 2]


@jit()
def _solve_small(m, rhs, na):
    """lstsq(m, rhs, rcond=eps·na) for ``_project``'s symmetric m (a principal block of the covariance, a few
    rows): its singular values are |eigenvalues|, so cyclic Jacobi rotations give the same minimum-norm answer
    (directions under rcond × the largest dropped) without LAPACK's workspace and SVD setup."""
    a = m.copy()
    v = np.eye(na)
    for _ in range(50):
        off, diag = 0.0, 0.0
        for p in range(na):
            diag += a[p, p] * a[p, p]
            for q in range(p + 1, na):
                off += a[p, q] * a[p, q]
        if not off > 1e-32 * diag:
            break
        for p in range(na - 1):
            for q in range(p + 1, na):
                apq = a[p, q]
                if apq == 0.0:
                    continue
                theta = (a[q, q] - a[p, p]) / (2.0 * apq)
                t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + math.sqrt(theta * theta + 1.0))
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for r in range(na):  # columns p, q of a·J
                    arp, arq = a[r, p], a[r, q]
                    a[r, p], a[r, q] = c * arp - s * arq, s * arp + c * arq
                for r in range(na):  # rows p, q of Jᵀ·a
                    apr, aqr = a[p, r], a[q, r]
                    a[p, r], a[q, r] = c * apr - s * aqr, s * apr + c * aqr
                for r in range(na):
                    vrp, vrq = v[r, p], v[r, q]
                    v[r, p], v[r, q] = c * vrp - s * vrq, s * vrp + c * vrq
    top = 0.0
    for i in range(na):
        top = max(top, abs(a[i, i]))
    x = np.zeros(na)
    for i in range(na):
        lam = a[i, i]
        if abs(lam) > _EPS * na * top:
            d = 0.0
            for r in range(na):
                d += v[r, i] * rhs[r]
            d /= lam
            for r in range(na):
                x[r] += v[r, i] * d
    return x


@jit()
def _project(j, k, phi, cov, scale, lower, upper):
    """``RobustRLS._project``: θ into its box, the free coordinates moved by their conditional mean."""
    lo = np.empty(k)
    hi = np.empty(k)
    for i in range(k):
        lo[i] = max(lower[j, i], 0.0) / scale[j, i]
        hi[i] = upper[j, i] / scale[j, i]
    active = np.zeros(k, np.bool_)
    bound = np.zeros(k)
    for _ in range(k):
        anyout = False
        for i in range(k):
            if phi[j, i] < lo[i] - BOX_TIE:
                bound[i] = lo[i]
                active[i] = True
                anyout = True
            elif phi[j, i] > hi[i] + BOX_TIE:
                bound[i] = hi[i]
                active[i] = True
                anyout = True
        if not anyout:
            break
        a = np.flatnonzero(active)
        na = a.size
        m = np.empty((na, na))
        rhs = np.empty(na)
        for p in range(na):
            rhs[p] = phi[j, a[p]] - bound[a[p]]
            for q in range(na):
                m[p, q] = cov[j, a[p], a[q]]
        shift = _solve_small(m, rhs, na)
        for i in range(k):
            s = 0.0
            for q in range(na):
                s += cov[j, i, a[q]] * shift[q]
            phi[j, i] -= s
        for p in range(na):
            phi[j, a[p]] = bound[a[p]]
    for i in range(k):
        phi[j, i] = min(max(phi[j, i], lo[i]), max(hi[i], lo[i]))


@jit()
def _median_abs(buf, n):
    """statistics.median of |buf[:n]|, by an insertion sort (n is the residual window: a dozen or two)."""
    a = np.empty(n)
    for i in range(n):
        x = abs(buf[i])
        p = i
        while p > 0 and a[p - 1] > x:
            a[p] = a[p - 1]
            p -= 1
        a[p] = x
    h = n // 2
    return a[h] if n % 2 == 1 else (a[h - 1] + a[h]) / 2


@jit()
def _update(j, k, x, y, rescale, has_rescale, phi, cov, scale, lower, upper, rs, rp, res, res_n, up, up_n, down,
            down_n, ws, wc):
    """``RobustRLS.update``: fold one row (x, y); returns its relative residual before the update (nan: dropped).
    ws (≥ 6, K), wc (K, K): scratch."""
    forgetting, huber, floor, reopen = rp[j, 0], rp[j, 1], rp[j, 2], rp[j, 3]
    slack, threshold, clip, cap = rp[j, 4], rp[j, 5], rp[j, 6], rp[j, 7]
    b = ws[0, :k]
    finite = True
    dot = 0.0
    for i in range(k):
        b[i] = x[i] * scale[j, i] / y
        finite &= math.isfinite(b[i])
        dot += b[i] * phi[j, i]
    e0 = e = 1.0 - dot
    if not (math.isfinite(e) and finite):
        return np.nan
    saved_phi = ws[5, :k]
    saved_cov = wc[:k, :k]
    saved_phi[:] = phi[j, :k]
    saved_cov[:, :] = cov[j, :k, :k]
    saved_hi, saved_lo = rs[j, 0], rs[j, 1]
    sigma = np.inf if res_n[j] < 5 else max(floor, 1.4826 * _median_abs(res[j], res_n[j]))
    c = huber * sigma
    w = min(1.0, c / abs(e)) if e != 0.0 else 1.0
    u = min(max(e / sigma, -clip), clip) if math.isfinite(sigma) else 0.0
    rs[j, 0] = max(0.0, rs[j, 0] + u - slack)
    rs[j, 1] = max(0.0, rs[j, 1] - u - slack)
    ratio = 1.0 / max(1.0 - e, 1e-3)
    if rs[j, 0] <= 0:
        up_n[j] = 0
    elif e > c:
        up_n[j] = _push(up[j], up_n[j], ratio)
    if rs[j, 1] <= 0:
        down_n[j] = 0
    elif e < -c:
        down_n[j] = _push(down[j], down_n[j], ratio)
    change = max(rs[j, 0], rs[j, 1]) > threshold
    share = ws[1, :k]
    for i in range(k):
        share[i] = min(abs(b[i]) * max(phi[j, i], 1.0), 1.0)
    if change:
        if rs[j, 0] > rs[j, 1]:
            rat, nr = up[j], up_n[j]
        else:
            rat, nr = down[j], down_n[j]
        if nr > 0:
            best = 0
            for i in range(1, nr):
                if abs(math.log(rat[i])) < abs(math.log(rat[best])):
                    best = i
            ratio = min(max(rat[best], 0.1), 10.0)
            if not has_rescale:
                bphi = 0.0
                for i in range(k):
                    bphi += b[i] * phi[j, i]
                for i in range(k):
                    rescale[i] = b[i] * max(phi[j, i], 1.0) >= RESCALE_SHARE * max(bphi, 1e-300)
            for i in range(k):
                if rescale[i]:
                    phi[j, i] *= ratio
        rs[j, 0] = rs[j, 1] = 0.0
        up_n[j] = down_n[j] = 0
        dot = 0.0
        for i in range(k):
            dot += b[i] * phi[j, i]
        e = 1.0 - dot
        w = 1.0
        rs[j, 3] += 1
    inflate = ws[2, :k]
    for i in range(k):
        inflate[i] = 1.0 / math.sqrt(1.0 - (1.0 - forgetting) * share[i])
    for p in range(k):
        for q in range(k):
            cov[j, p, q] *= inflate[p] * inflate[q]
    pb = ws[3, :k]
    bpb = 0.0
    for p in range(k):
        s = 0.0
        for q in range(k):
            s += cov[j, p, q] * b[q]
        pb[p] = s
        bpb += b[p] * s
    den = 1.0 + w * bpb
    g = ws[4, :k]
    for p in range(k):
        g[p] = w * pb[p] / den
        phi[j, p] += g[p] * e
    for p in range(k):
        for q in range(k):
            cov[j, p, q] -= g[p] * pb[q]
    for p in range(k):
        for q in range(p + 1, k):
            s = (cov[j, p, q] + cov[j, q, p]) * 0.5
            cov[j, p, q] = cov[j, q, p] = s
    if change:
        for p in range(k):
            cov[j, p, p] += reopen * cap
    over = False
    for p in range(k):
        over |= cov[j, p, p] > cap
    if over:
        f = np.empty(k)
        for p in range(k):
            f[p] = math.sqrt(cap / max(cov[j, p, p], cap))
        for p in range(k):
            for q in range(k):
                cov[j, p, q] *= f[p] * f[q]
    out = False
    for i in range(k):
        t = phi[j, i] * scale[j, i]
        out |= (t < lower[j, i]) | (t > upper[j, i])
    if out:
        _project(j, k, phi, cov, scale, lower, upper)
    ok = True
    for p in range(k):
        ok &= math.isfinite(phi[j, p])
        for q in range(k):
            ok &= math.isfinite(cov[j, p, q])
    if not ok:
        phi[j, :k] = saved_phi
        cov[j, :k, :k] = saved_cov
        rs[j, 0], rs[j, 1] = saved_hi, saved_lo
        return np.nan
    res_n[j] = _push(res[j], res_n[j], e0)
    rs[j, 2] += 1
    return e0


@jit()
def _rung(j, r, t, z, least, light, phi, cov, scale, lower, upper, seen, rs, rp, res, res_n, up, up_n, down,
          down_n, fill, fill_n, alg, mp, ws, wc):
    """``_Rung.observe``: fold frame (t, z) into rung j. ws (10, K), wc (K, K): scratch."""
    k = _k(j, r)
    big = 3 * r + 3
    th = ws[6]
    if j > 0:
        upper[j, 0] = least
    first_held = 1 if j > 0 else 0
    if light:
        for i in range(first_held, k):
            lower[j, i] = upper[j, i] = phi[j, i] * scale[j, i]
    x = ws[7, :k]
    if j == 0:
        s = 0.0
        for a in range(r):
            s += z[1 + r + a]
        x[0] = s + z[big - 1]
    else:
        for i in range(k):
            x[i] = z[_col(j, r, i)]
    fresh = np.zeros(k, np.bool_)
    any_fresh = False
    for i in range(k):
        fresh[i] = x[i] > 0 and seen[j, i] == 0
        any_fresh |= fresh[i]
    if any_fresh:  # ``_Rung._first``
        _theta(j, r, phi, scale, seen, alg, th)
        mean = th[:k].copy()
        spread = np.full(k, SECONDARY)
        mains = 1 if j < 2 else 2
        for m in range(mains):
            first = 0 if j == 0 else (1 if j == 1 else 1 + (m + 1) * r)
            width = 1 if j == 0 else r
            any_f, any_s, xs = False, False, 0.0
            for a in range(width):
                spread[first + a] = 1.0
                any_f |= fresh[first + a]
                any_s |= seen[j, first + a] != 0
                xs += x[first + a]
            if any_f and not any_s:
                for a in range(width):
                    mean[first + a] = t / xs
        cap = rp[j, 7]
        for i in range(k):
            if fresh[i]:
                scale[j, i] = max(spread[i] * t / x[i], 1e-300)
                phi[j, i] = max(mean[i], 0.0) / scale[j, i]
        for i in range(k):
            if fresh[i]:
                for q in range(k):
                    cov[j, i, q] = 0.0
                    cov[j, q, i] = 0.0
        for i in range(k):
            if fresh[i]:
                cov[j, i, i] = cap
                seen[j, i] = 1
    is_fill = False
    rescale = np.zeros(k, np.bool_)
    has_rescale = False
    if j == 2:
        c = ws[8]
        _full(j, r, phi, scale, seen, alg, th, c)
        g, f = _sides(c, z, r)
        is_fill = f > g * (1.0 + TIE)
        side = 7 if is_fill else 6
        rs[j, side] += 1
        if rs[j, side] <= YOUNG and max(g, f) > t:
            lo_, hi_ = (1 + 2 * r, 1 + 3 * r) if is_fill else (1, 1 + 2 * r)
            for i in range(lo_, hi_):
                phi[j, i] *= t / max(g, f)
        whole = 0.0
        for i in range(big):
            if i < 1 + 2 * r or i >= 3 * r + 1:
                whole += x[i] * c[i]
        for i in range(k):
            rescale[i] = x[i] * max(c[i], scale[j, i]) >= RESCALE_SHARE * max(whole, 1e-300)
        has_rescale = True
        lo_, hi_ = (1, 1 + 2 * r) if is_fill else (1 + 2 * r, 1 + 3 * r)
        for i in range(lo_, hi_):
            x[i] = 0.0
    fill_n[j] = _push(fill[j], fill_n[j], 1 if is_fill else 0)
    _update(j, k, x, t, rescale, has_rescale, phi, cov, scale, lower, upper, rs, rp, res, res_n, up, up_n, down,
            down_n, ws, wc)
    c = ws[9]
    _full(j, r, phi, scale, seen, alg, th, c)
    lam = mp[0]
    rs[j, 4] = lam * rs[j, 4] + _frame(c, z, r) - c[0]
    vs = 0.0
    for a in range(r):
        vs += z[1 + r + a]
    rs[j, 5] = lam * rs[j, 5] + vs + z[big - 1]
    if light:
        for i in range(first_held, k):
            lower[j, i] = 0.0
            upper[j, i] = np.inf


@jit()
def fold(r, times, z, only_least, phi, cov, scale, lower, upper, seen, rs, rp, res, res_n, up, up_n, down, down_n,
         err, err_n, fill, fill_n, mi, mf, ratios, ratios_n, mp, alg):
    """``OnlineCostModel.observe`` for every frame in order (frames already checked and laid out as z rows);
    ``only_least`` frames drew nothing and only lower the lightest-frame bound."""
    big = 3 * r + 3
    th = np.empty(big)
    c = np.empty(big)
    ws, wc = np.empty((10, big)), np.empty((big, big))  # the rungs' scratch, allocated once per fold
    tail_min, slack, rise = mp[5], mp[6], mp[7]
    window = err.shape[1]
    for f in range(times.shape[0]):
        t = times[f]
        zf = z[f]
        mf[0] = min(t, mf[0] * (1.0 + rise))
        if only_least[f]:
            continue
        _full(mi[0], r, phi, scale, seen, alg, th, c)
        predicted = _frame(c, zf, r)
        if predicted > 0 and max(predicted, t) >= tail_min:
            ratios_n[0] = _push(ratios, ratios_n[0], t / predicted)
        for j in range(3):
            _full(j, r, phi, scale, seen, alg, th, c)
            guess = _frame(c, zf, r)
            err_n[j] = _push(err[j], err_n[j], abs(guess - t) / t)
            _rung(j, r, t, zf, slack * mf[0], max(guess, t) < tail_min, phi, cov, scale, lower, upper, seen, rs,
                  rp, res, res_n, up, up_n, down, down_n, fill, fill_n, alg, mp, ws, wc)
        fs = 0.0
        vs = 0.0
        for a in range(r):
            fs += zf[1 + a]
            vs += zf[1 + r + a]
        mf[1] = mp[0] * mf[1] + fs
        mf[2] = mp[0] * mf[2] + vs
        mi[3] += 1
        choose(err, err_n, mi, mp, window)


def compile_all() -> None:
    """Fold two frames into a fresh three-algorithm state, with the types ``cost_fold`` packs."""
    r, big = 3, 12
    phi, scale, lower, upper = np.zeros((3, big)), np.ones((3, big)), np.zeros((3, big)), np.full((3, big), np.inf)
    cov = np.zeros((3, big, big))
    for j in range(3):
        cov[j] = np.eye(big) * 400.0
    rp = np.tile(np.array([0.97, 1.345, 0.005, 0.05, 0.5, 8.0, 2.5, 400.0]), (3, 1))
    z = np.zeros((2, big))
    z[:, 0], z[:, 1], z[:, 4], z[:, 10] = 1.0, 2000.0, 1200.0, 10.0
    n3 = np.zeros(3, np.int64)
    fold(r, np.array([0.004, 0.005]), z, np.zeros(2, np.uint8), phi, cov, scale, lower, upper,
         np.zeros((3, big), np.uint8), np.zeros((3, 8)), rp, np.zeros((3, 15)), n3.copy(), np.zeros((3, 4)), n3.copy(),
         np.zeros((3, 4)), n3.copy(), np.zeros((3, 60)), n3.copy(), np.zeros((3, 60), np.uint8), n3.copy(),
         np.zeros(4, np.int64), np.array([np.inf, 0.0, 0.0]), np.zeros(100), np.zeros(1, np.int64),
         np.array([0.97, 0.3, 10.0, 20.0, 5.0, 0.0, 2.0, 1e-3]), np.array([1.0, 1.25, 1.5]))
