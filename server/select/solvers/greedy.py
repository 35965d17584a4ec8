"""Greedy multiple-choice knapsack by value = benefit / cost (Funkhouser & Séquin 1993, section 4.3).

Each object offers its options (level × rendering algorithm tuples) or nothing.
Options that no mix of cheaper ones beats are removed first: what remains is the
upper concave hull of the object's (cost, benefit) points, starting at (0, 0) =
not drawn. Along a hull the *increments* (steps to the next hull point) have
strictly falling values Δbenefit / Δcost, so the greedy "take the increment of
highest value while the budget holds" is a cut of all increments at a value
threshold. The threshold is found by a weighted selection (a sample brackets
it, only the increments inside the bracket are sorted), not a full sort. Fill
rounds then add the best increments that still fit, and the answer is compared
with the best single option, which keeps the factor-two guarantee.

>>> import numpy as np
>>> from server.select.solvers.candidates import Candidates
>>> from server.select.solvers.greedy import solve
>>> cand = Candidates.of([[1.0, 1.5], [2.0, 2.2]], [[1.0, 3.0], [1.0, 2.0]])
>>> solve(cand, budget=3.0).level.tolist()
[0, 1]
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from .. import kernels
from .candidates import NO_LIMIT, Candidates, TimeLimit
from .result import Result

__all__ = ["Hull", "upper_hull", "cut", "fill", "threshold", "solve", "upper_hull_numpy", "fill_numpy",
           "solve_numpy"]

_SAMPLE = 8192  # sample size that brackets the value threshold
_MARGIN = 128  # sample positions either side of the estimated threshold (about 3 standard deviations)


@dataclass
class Hull:
    """Each object's upper concave hull as increments, in (K, n) arrays (row j: every object's j-th increment).

    Rows are contiguous, so per-increment work over all objects is a few passes over (n,) rows.

    value  : Δbenefit / Δcost of the increment to hull point j (−inf: padding); strictly falling along j
    d_cost : Δcost of the increment (0 in padding)
    count  : (n,) hull points per object
    opt    : option index of the j-th hull point (−1: padding); None when every object's
             hull is all its options in order (the fast path), i.e. opt[j] = j
    """

    value: np.ndarray
    d_cost: np.ndarray
    count: np.ndarray
    opt: np.ndarray | None
    cand: Candidates
    ok: np.ndarray | None = None  # (n, K) the usable options the hull was built from (None: not kept)
    best: int | None = None  # flat index i·K + o of the best single usable option (−1: none; None: unknown)

    @property
    def shape(self) -> tuple[int, int]:
        return self.value.shape

    def chosen(self, steps: np.ndarray) -> np.ndarray:
        """(n,) option index after taking the first ``steps`` increments of each object (−1: none)."""
        k, n = self.shape
        steps = np.asarray(steps, np.int64)
        if self.opt is None:
            return steps - 1
        level = self.opt.ravel()[np.maximum(steps - 1, 0) * n + np.arange(n)].astype(np.int64)
        level[steps <= 0] = -1
        return level

    def d_benefit(self) -> np.ndarray:
        """(K, n) Δbenefit of each increment (0 in padding)."""
        with np.errstate(invalid="ignore"):
            return np.where(self.value > -np.inf, self.value * self.d_cost, 0.0)


def _usable(cand: Candidates, cap: float | None) -> np.ndarray:
    """(n, K) bool: valid options with a finite benefit and a cost in (0, cap]."""
    ok = cand.valid & (cand.cost > 0) & np.isfinite(cand.benefit)
    ok &= cand.cost <= cap if cap is not None else cand.cost < np.inf
    return ok


def upper_hull(cand: Candidates, cap: float | None = None) -> Hull:
    """The hull of every object's usable options (valid, cost > 0, cost ≤ ``cap`` if given).

    One compiled pass per object when the kernels are ready (``hull.ok`` is then None and
    ``hull.best`` the best single option), else ``upper_hull_numpy``.
    """
    k_ = kernels.compiled()
    if k_ is None:
        return upper_hull_numpy(cand, cap)
    return _hull_compiled(k_, cand, cap)


def _hull_compiled(k_, cand: Candidates, cap: float | None, *, scratch: bool = False,
                   previous: np.ndarray | None = None) -> Hull:
    """The compiled hull; with ``scratch`` its arrays are this thread's reusable buffers (valid until the
    next scratch hull: for a solver's own use) and it carries ``begin`` (the start on the hull of
    ``previous``), ``hist`` and ``total`` for the radix cut."""
    b, c = _c64(cand.benefit), _c64(cand.cost)
    valid = np.ascontiguousarray(cand.valid, bool).view(np.uint8)
    n, k = b.shape
    opt_dtype = np.int16 if k < 2**15 else np.int64
    if scratch:
        sp = _scratch(n, k, opt_dtype, k_.hull.RADIX_BINS)
        value, d_cost, opt, count = sp["value"], sp["d_cost"], sp["opt"], sp["count"]
        begin, hist = sp["begin"], sp["hist"]
    else:
        value, d_cost = np.empty((k, n)), np.empty((k, n))
        opt, count = np.empty((k, n), opt_dtype), np.empty(n, np.int64)
        begin, hist = np.empty(0, np.int64), np.empty(0)
    prev = _NO_PREVIOUS if previous is None else previous
    best, total = k_.hull.hull(b, c, valid, np.inf if cap is None else float(cap), prev, value,
                               value.view(np.int64), d_cost, opt, count, begin, hist)
    h = Hull(value, d_cost, count, opt, cand, None, int(best))
    if scratch:
        h.begin, h.hist, h.total = begin, hist, float(total)
        h.steps, h.ready = sp["steps"], sp["ready"]
    return h


_NO_PREVIOUS = np.empty(0, np.int64)
_pool = threading.local()


def _scratch(n: int, k: int, opt_dtype, bins: int) -> dict:
    """This thread's scratch arrays for n objects × k options, grown as needed and reused: touching fresh
    pages costs more than the arithmetic of a solve."""
    have = getattr(_pool, "arrays", None)
    if have is None or have["n"] < n or have["k"] < k or have["opt"].dtype != opt_dtype:
        cap_n = max(n, have["n"] if have is not None else 0)
        cap_k = max(k, have["k"] if have is not None else 0)
        have = {"n": cap_n, "k": cap_k, "value": np.empty(cap_n * cap_k), "d_cost": np.empty(cap_n * cap_k),
                "opt": np.empty(cap_n * cap_k, opt_dtype), "count": np.empty(cap_n, np.int64),
                "begin": np.empty(cap_n, np.int64), "steps": np.empty(cap_n, np.int64),
                "ready": np.empty(cap_n, np.int64), "hist": np.empty(bins), "nxt_v": np.empty(cap_n),
                "nxt_c": np.empty(cap_n), "band_f": np.empty((6, max(1024, cap_n // 4))),
                "band_i": np.empty((3, max(1024, cap_n // 4)), np.int64)}
        _pool.arrays = have
    out = {name: have[name][: k * n].reshape(k, n) for name in ("value", "d_cost", "opt")}
    out.update({name: have[name][:n] for name in ("count", "begin", "steps", "ready", "nxt_v", "nxt_c")},
               hist=have["hist"], band_f=have["band_f"], band_i=have["band_i"])
    if n == 0 or k == 0:
        out["begin"] = np.zeros(n, np.int64)
    return out


def _c64(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, np.float64)


def upper_hull_numpy(cand: Candidates, cap: float | None = None) -> Hull:
    """The vectorised reference of ``upper_hull`` (same hulls; ``ok`` kept).

    Objects whose options are already sorted by cost with falling values (the usual
    concave levels) take a fast path of a few passes per column; the others are
    sorted by cost and pruned in at most K vectorised passes. Few large
    temporaries: fresh pages cost more than the arithmetic.
    """
    b, c = cand.benefit, cand.cost
    n, k = b.shape
    ok = _usable(cand, cap)
    value = np.empty((k, n))
    d_cost = np.empty((k, n))
    fast = ok.all(axis=1) if k <= 1 else None
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for j in range(k):
            if j == 0:
                d_cost[0] = c[:, 0]
                np.divide(b[:, 0], d_cost[0], out=value[0])
                fast = ok[:, 0] & (d_cost[0] > 0)
            else:
                np.subtract(c[:, j], c[:, j - 1], out=d_cost[j])
                np.subtract(b[:, j], b[:, j - 1], out=value[j])
                value[j] /= d_cost[j]
                fast &= ok[:, j]
                fast &= d_cost[j] > 0
                fast &= value[j - 1] > value[j]
        fast &= value[k - 1] > 0
    count = np.full(n, k, dtype=np.int64)
    opt = None
    slow = np.flatnonzero(~fast)
    if slow.size:
        s_opt, s_val, s_dc, s_count = _hull_general(b[slow], c[slow], ok[slow])
        opt = np.empty((k, n), np.int16 if k < 2**15 else np.int64)
        opt[:] = np.arange(k, dtype=opt.dtype)[:, None]
        opt[:, slow], value[:, slow], d_cost[:, slow] = s_opt.T, s_val.T, s_dc.T
        count[slow] = s_count
    return Hull(value, d_cost, count, opt, cand, ok)


def _hull_general(b: np.ndarray, c: np.ndarray, ok: np.ndarray):
    """Hull of arbitrary rows: sort by cost, then drop dominated points and points on or under a chord.

    Removing every such point of a pass at once is safe: a point dominated by, or
    under the chord of, points of the set is never a vertex of the hull.
    Returns (opt, value, d_cost, count), each (m, K) left-aligned but count (m,).
    """
    m, k = b.shape
    base = (np.arange(m) * k)[:, None]
    key = np.where(ok, c, np.inf)
    if (key[:, 1:] >= key[:, :-1]).all():  # the usual case: cost already rises along the options
        order = np.broadcast_to(np.arange(k), (m, k))
        B, C, alive = b, c, ok.copy()
    else:
        order = np.argsort(key, axis=1, kind="stable")
        flat = (order + base).ravel()
        B = b.ravel().take(flat).reshape(m, k)
        C = c.ravel().take(flat).reshape(m, k)
        alive = ok.ravel().take(flat).reshape(m, k)
    # Points are padded with the origin (0, 0) at flat index m·k: "no previous point".
    Bx = np.append(B.ravel(), 0.0)
    Cx = np.append(C.ravel(), 0.0)
    origin = m * k
    row = base[:, 0]
    prev = np.empty((m, k), np.int64)
    nxt = np.empty((m, k), np.int64)
    with np.errstate(divide="ignore", invalid="ignore"):
        for _ in range(k + 1):
            # The nearest alive point before and after each column (column scans: K is small).
            cur = np.full(m, origin)
            for j in range(k):
                prev[:, j] = cur
                cur = np.where(alive[:, j], row + j, cur)
            cur = np.full(m, origin)
            for j in range(k - 1, -1, -1):
                nxt[:, j] = cur
                cur = np.where(alive[:, j], row + j, cur)
            bp, cp = Bx.take(prev), Cx.take(prev)
            s_in = (B - bp) / (C - cp)
            s_out = np.append(s_in.ravel(), -np.inf).take(nxt)
            remove = alive & ((B <= bp) | (s_in <= s_out))
            if not remove.any():
                break
            alive &= ~remove
    # Left-align the alive columns, in cost order: alive column j goes to slot (alive before j).
    count = alive.sum(axis=1)
    src = np.flatnonzero(alive.ravel())
    dst = (np.cumsum(alive, axis=1) - 1 + base).ravel()[src]
    value = np.full(m * k, -np.inf)
    value[dst] = s_in.ravel()[src]
    dc = np.zeros(m * k)
    dc[dst] = (C - cp).ravel()[src]
    opt = np.full(m * k, -1, np.int64)
    opt[dst] = np.ascontiguousarray(order).ravel()[src]
    return opt.reshape(m, k), value.reshape(m, k), dc.reshape(m, k), count


def cut(value: np.ndarray, weight: np.ndarray, capacity: float) -> np.ndarray:
    """(N,) bool: the longest prefix of items in falling value whose weights fit ``capacity``.

    Items of value −inf are never taken and must weigh 0. A strided sample
    estimates the threshold value; one pass counts the weight above a bracket
    around it and only the items inside the bracket are sorted (O(N) instead of
    O(N log N)). Ties may be broken either way.
    """
    if not capacity >= 0:
        return np.zeros(value.size, bool)
    total = float(weight.sum())
    if total <= capacity:
        return value > -np.inf
    n = value.size
    if n > 8 * _SAMPLE:
        stride = n // _SAMPLE
        sv, sw = value[::stride], weight[::stride]
        so = np.argsort(-sv, kind="stable")
        scale = total / max(float((sw * (sv > -np.inf)).sum()), 1e-300)
        pos = int(np.searchsorted(np.cumsum(sw[so]) * scale, capacity))
        for margin in (_MARGIN, 4 * _MARGIN, 16 * _MARGIN):
            hi_t = sv[so[pos - margin]] if pos - margin >= 0 else np.inf
            lo_t = sv[so[pos + margin]] if pos + margin < so.size else -np.inf
            above = value > hi_t
            s_above = float((weight * above).sum())
            if s_above > capacity:
                continue
            mid = value > lo_t
            mid &= ~above
            if lo_t > -np.inf and s_above + float((weight * mid).sum()) <= capacity:
                continue
            return _sorted_cut(value, weight, capacity, above, s_above, np.flatnonzero(mid))
    return _sorted_cut(value, weight, capacity, np.zeros(n, bool), 0.0, np.flatnonzero(value > -np.inf))


def _sorted_cut(value, weight, capacity, taken, base, idx):
    idx = idx[np.argsort(-value[idx])]
    added = base + np.cumsum(weight[idx])
    m = int(np.searchsorted(added, capacity, side="right"))
    taken[idx[:m]] = True
    return taken


def fill(hull: Hull, steps: np.ndarray, remaining: float, limit: TimeLimit, max_rounds: int):
    """Rounds adding, in falling value, each object's next increment while it still fits.

    Returns (rounds, stopped); ``steps`` is updated in place. Only objects whose
    next increment fits are looked at, and the remaining budget only shrinks, so
    the set shrinks every round. The limit is checked before every round.
    """
    k_ = kernels.compiled()
    if k_ is None or steps.dtype != np.int64 or not steps.flags.c_contiguous:
        return fill_numpy(hull, steps, remaining, limit, max_rounds)
    return _fill_compiled(k_, hull, steps, float(remaining), limit, max_rounds)


def _fill_compiled(k_, hull: Hull, steps: np.ndarray, remaining: float, limit: TimeLimit, max_rounds: int,
                   idx: np.ndarray | None = None):
    """``fill`` on a compiled hull; ``idx``: the objects ready for the first round, if known."""
    value, d_cost, count = hull.value, hull.d_cost, np.ascontiguousarray(hull.count, np.int64)
    if idx is None:
        idx = k_.cut.ready(value, d_cost, count, steps, remaining)
    rounds = 0
    while idx.size and rounds < max_rounds:
        if limit.expired():
            return rounds, "limit"
        idx, remaining, took = k_.cut.fill_round(value, d_cost, count, steps, idx, remaining)
        if took == 0:
            break
        rounds += 1
    return rounds, "done"


def fill_numpy(hull: Hull, steps: np.ndarray, remaining: float, limit: TimeLimit, max_rounds: int):
    """The vectorised reference of ``fill`` (same rounds, same increments)."""
    k, n = hull.shape
    vflat, cflat = hull.value.ravel(), hull.d_cost.ravel()
    at = np.minimum(steps, k - 1) * n + np.arange(n)
    idx = np.flatnonzero((steps < hull.count) & (cflat[at] <= remaining))
    rounds = 0
    while idx.size and rounds < max_rounds:
        if limit.expired():
            return rounds, "limit"
        at = np.minimum(steps[idx], k - 1) * n + idx
        ready = (steps[idx] < hull.count[idx]) & (cflat[at] <= remaining)
        idx, at = idx[ready], at[ready]
        if idx.size == 0:
            break
        order = np.argsort(-vflat[at], kind="stable")
        added = np.cumsum(cflat[at[order]])
        m = max(1, int(np.searchsorted(added, remaining, side="right")))
        steps[idx[order[:m]]] += 1
        remaining -= float(added[m - 1])
        rounds += 1
    return rounds, "done"


def totals(cand: Candidates, level: np.ndarray) -> tuple[float, float]:
    """(cost, benefit) of a selection of options."""
    rows = np.flatnonzero(level >= 0)
    at = rows * cand.k + level[rows]
    return float(cand.cost.ravel().take(at).sum()), float(cand.benefit.ravel().take(at).sum())


def best_single(cand: Candidates, budget: float, level: np.ndarray, cost: float, benefit: float,
                ok: np.ndarray | None = None):
    """The better of a selection and the best single option that fits: the factor-two guarantee.

    ok : the usable options (``_usable(cand, budget)``) if already known
    """
    if cand.benefit.size == 0:
        return level, cost, benefit, False
    ok = _usable(cand, budget) if ok is None else ok
    top = float(np.max(cand.benefit, where=ok, initial=-np.inf))
    if top > benefit:
        best = int(np.flatnonzero(ok.ravel() & (cand.benefit.ravel() == top))[0])
        level = np.full(cand.n, -1, dtype=np.int64)
        level[best // cand.k] = best % cand.k
        return level, float(cand.cost.flat[best]), top, True
    return level, cost, benefit, False


def solve(
    cand: Candidates,
    budget: float,
    *,
    limit: TimeLimit = NO_LIMIT,
    state: dict | None = None,
    max_rounds: int = 64,
) -> Result:
    """Choose at most one option per object maximising Σ benefit with Σ cost ≤ budget, from scratch.

    max_rounds : bound on the fill rounds after the cut (anytime: every round is feasible)
    Returns a ``Result`` whose ``level`` is the option index, −1 for objects left undrawn.
    Compiled (one pass for the hulls, one radix cut, the fill rounds, one pass for the
    totals) once the kernels are ready; ``solve_numpy`` until then (the same greedy).
    """
    n = cand.n
    if n == 0 or cand.k == 0 or not budget > 0:
        return _nothing(n)
    k_ = kernels.compiled()
    if k_ is None:
        return solve_numpy(cand, budget, limit=limit, state=state, max_rounds=max_rounds)
    hull = _hull_compiled(k_, cand, budget, scratch=True)
    begin = hull.begin
    begin[:] = 0
    spent, _, _, nr = k_.cut.radix_cut(hull.value, hull.value.view(np.int64), hull.d_cost, hull.count, begin,
                                       1.0, float(budget), hull.hist, hull.total, hull.steps, hull.ready)
    steps = hull.steps
    rounds, stopped = _fill_compiled(k_, hull, steps, float(budget) - spent, limit, max_rounds, hull.ready[:nr])
    return _finish_compiled(k_, cand, budget, hull, steps, {"stopped": stopped, "rounds": rounds})


def _nothing(n: int) -> Result:
    return Result(np.full(n, -1, dtype=np.int64), 0.0, 0.0,
                  {"stopped": "done", "increments": 0, "rounds": 0, "candidates": 0, "threshold": None})


def _finish_compiled(k_, cand: Candidates, budget: float, hull: Hull, steps: np.ndarray, stats: dict) -> Result:
    """The chosen options and their totals, the best-single check, and the stats every greedy reports."""
    level, cost, benefit, incs, cands, left = k_.cut.finish(_c64(cand.benefit), _c64(cand.cost), hull.opt,
                                                             hull.value, hull.count, steps)
    single = False
    if hull.best is not None and hull.best >= 0:
        top = float(cand.benefit.flat[hull.best])
        if top > benefit:
            level = np.full(cand.n, -1, dtype=np.int64)
            level[hull.best // cand.k] = hull.best % cand.k
            cost, benefit, single = float(cand.cost.flat[hull.best]), top, True
    stats.update(increments=int(incs), candidates=int(cands), single=single,
                 threshold=float(left) if np.isfinite(left) and left > 0 else None)
    return Result(level, float(cost), float(benefit), stats)


def solve_numpy(
    cand: Candidates,
    budget: float,
    *,
    limit: TimeLimit = NO_LIMIT,
    state: dict | None = None,
    max_rounds: int = 64,
) -> Result:
    """The vectorised reference of ``solve``: the same greedy in numpy passes."""
    n = cand.n
    if n == 0 or cand.k == 0 or not budget > 0:
        return _nothing(n)
    hull = upper_hull_numpy(cand, budget)
    taken = cut(hull.value.ravel(), hull.d_cost.ravel(), budget)
    # Along an object the values fall strictly, so the taken increments are a prefix of its hull.
    steps = taken.reshape(hull.shape).sum(axis=0)
    spent = float((hull.d_cost.ravel() * taken).sum())
    rounds, stopped = fill_numpy(hull, steps, budget - spent, limit, max_rounds)
    level = hull.chosen(steps)
    cost, benefit = totals(cand, level)
    level, cost, benefit, single = best_single(cand, budget, level, cost, benefit, hull.ok)
    return Result(level, cost, benefit, {
        "stopped": stopped, "increments": int(steps.sum()), "rounds": rounds,
        "candidates": int(hull.count.sum()), "single": single, "threshold": threshold(hull, steps),
    })


def threshold(hull: Hull, steps: np.ndarray) -> float | None:
    """The value of the best increment left out: where the cut stopped.

    The next frame's incremental solver starts its search around it (state["threshold"]).
    """
    k, n = hull.shape
    nxt = hull.value.ravel().take(np.minimum(steps, k - 1) * n + np.arange(n))
    nxt = nxt[steps < hull.count]
    top = float(nxt.max()) if nxt.size else -np.inf
    return top if np.isfinite(top) and top > 0 else None
