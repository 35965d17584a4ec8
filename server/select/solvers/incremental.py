"""Incremental optimisation with frame coherence (Funkhouser & Séquin 1993, section 4.3, "Optimization").

The solution starts from the options drawn in the last selection (``cand.previous``;
newly visible objects undrawn) instead of from nothing, and only tuples whose
value is near the greedy's stopping value can change: F&S increment the tuple of
highest next value and decrement those of lowest current value until the cost
fits, and stop when the same tuple goes up and down. Here the moves are batched:

1. Threshold θ: last frame's (``state["threshold"]``, handed back in
   ``stats["threshold"]``), else where one batch round would stop (every object
   offers its next increment and last increment; one weighted cut picks them).
2. Band: the objects whose next or last increment has a value within ±10 % of θ.
   Every other object keeps its tuple. The band's objects are re-cut at once
   over all their hull increments, with the budget the others leave.
3. Check: the cut must stop inside the band; then no object outside it would
   move, and the answer is the greedy's (same fill rounds, same best-single
   check). Otherwise the band widens (×2, twice), then the greedy from scratch
   takes over (stats["fallback"] = "unsettled").

Increments follow each object's upper hull, so the answer matches
greedy-from-scratch up to ties in value. The hull is rebuilt every frame
(benefits change), so the coherent step costs the hull plus O(n) gathers.

Compiled path (``server.select.kernels``, once warm; the steps above stay as ``solve_numpy``, the
reference): the same band in one pass. With θ known (last frame's; on a sample of 2048
objects' hulls when missing and there are many objects) one pass builds each object's
hull in registers, takes its increments above θ·(1 + w), writes its option, totals and
next increment, and keeps only the increments inside the band (w = 5 %, 10 % for an
estimated θ); those are sorted and cut (the ones drawn last frame winning ties), then the
fill rounds rebuild the hulls of the few objects they move. No (K, n) hull arrays are
stored. If the cut does not stop inside the band, or without θ on few objects, the
compiled full path runs instead: stored hulls and one radix cut of every increment
(``kernels.cut.radix_cut``), exact wherever the threshold lies. stats["band"] counts the
objects with increments in the band (or in the radix cut's bin).
"""

from __future__ import annotations

import numpy as np

from .. import kernels
from . import greedy
from .candidates import NO_LIMIT, Candidates, TimeLimit
from .result import Result

__all__ = ["solve", "start", "solve_numpy", "start_numpy"]

_KEEP = 1 + 1e-12
_BAND = 0.1  # relative width of the value band around last frame's threshold whose objects may move
_SAMPLE = 2048  # objects whose hulls estimate the threshold when the last frame's is unknown
_ESTIMATE_MIN = 8 * _SAMPLE  # fewer objects: the full compiled path (a radix cut) needs no threshold


def start(cand: Candidates, hull: greedy.Hull) -> np.ndarray:
    """(n,) hull increments taken at the start: the hull points costing no more than the previous option.

    A previous option off the hull (or over the budget) is clamped to the hull point
    below it; −1 or an invalid index starts the object undrawn.
    """
    k_ = kernels.compiled()
    if k_ is None:
        return start_numpy(cand, hull)
    return _start_compiled(k_, cand, hull)


def _start_compiled(k_, cand: Candidates, hull: greedy.Hull) -> np.ndarray:
    n = hull.shape[1]
    prev = np.asarray(cand.previous, np.int64)
    if prev.shape != (n,) or cand.k == 0:
        return np.zeros(n, np.int64)
    return k_.hull.start(greedy._c64(cand.cost), np.ascontiguousarray(cand.valid, bool), np.ascontiguousarray(prev),
                         np.ascontiguousarray(hull.d_cost), np.ascontiguousarray(hull.count, np.int64))


def start_numpy(cand: Candidates, hull: greedy.Hull) -> np.ndarray:
    """The vectorised reference of ``start``."""
    k, n = hull.shape
    prev = np.asarray(cand.previous, np.int64)
    if prev.shape != (n,) or cand.k == 0:
        return np.zeros(n, np.int64)
    p = np.clip(prev, 0, cand.k - 1)
    rows = np.arange(n)
    c_prev = cand.cost[rows, p]
    c_prev[(prev < 0) | (prev >= cand.k) | ~cand.valid[rows, p] | np.isnan(c_prev)] = -np.inf
    c_prev *= 1 + 1e-12
    steps = np.zeros(n, np.int64)
    point = np.zeros(n)
    for j in range(k):
        point += hull.d_cost[j]
        steps += (point <= c_prev) & (j < hull.count)
    return steps


def solve(
    cand: Candidates,
    budget: float,
    *,
    limit: TimeLimit = NO_LIMIT,
    state: dict | None = None,
    fill_rounds: int = 64,
) -> Result:
    """Choose at most one option per object within ``budget``, starting from ``cand.previous``.

    state : {"threshold": last frame's stats["threshold"]} (optional: estimated when missing)
    fill_rounds : bound on the fill rounds afterwards
    Without ``previous`` it is the greedy (stats["fallback"] = "no previous").
    """
    n, k = cand.n, cand.k
    if cand.previous is None or n == 0 or k == 0 or not budget > 0:
        r = greedy.solve(cand, budget, limit=limit, max_rounds=fill_rounds)
        r.stats["fallback"] = "no previous" if cand.previous is None else "empty"
        return r
    k_ = kernels.compiled()
    if k_ is None:
        return solve_numpy(cand, budget, limit=limit, state=state, fill_rounds=fill_rounds)
    prev = np.asarray(cand.previous, np.int64)
    prev = np.ascontiguousarray(prev) if prev.shape == (n,) else np.full(n, -1, np.int64)
    budget = float(budget)
    if limit.expired():
        return _solve_full(k_, cand, budget, prev, limit, fill_rounds, expired=True)
    theta = (state or {}).get("threshold")
    theta = float(theta) if isinstance(theta, (int, float)) and np.isfinite(theta) and theta > 0 else None
    b, c = greedy._c64(cand.benefit), greedy._c64(cand.cost)
    valid = np.ascontiguousarray(cand.valid, bool).view(np.uint8)
    width = _BAND / 2  # last frame's threshold: benefits change by a few % a frame
    if theta is None and n >= _ESTIMATE_MIN:
        width = _BAND
        theta = float(k_.coherent.estimate(b, c, valid, budget, budget, max(1, n // _SAMPLE)))
        theta = theta if np.isfinite(theta) and theta > 0 else None
    if theta is None:
        return _solve_full(k_, cand, budget, prev, limit, fill_rounds)
    sp = greedy._scratch(n, k, np.int16 if k < 2**15 else np.int64, k_.hull.RADIX_BINS)
    steps, nxt_v, nxt_c, band_obj = sp["steps"], sp["nxt_v"], sp["nxt_c"], sp["ready"]
    level = np.empty(n, np.int64)
    acc = np.zeros(5)
    settled, band, stop, best, spent = k_.coherent.coherent(b, c, valid, budget, prev, theta, width, budget, _KEEP,
                                                            level, steps, nxt_v, nxt_c, sp["band_f"], sp["band_i"],
                                                            acc)
    if not settled:
        r = _solve_full(k_, cand, budget, prev, limit, fill_rounds)
        r.stats.update(rounds=2, band=int(band), theta_missed=theta)
        return r
    remaining, rounds, stopped = budget - spent, 0, "done"
    idx = band_obj[: k_.coherent.coherent_ready(nxt_v, nxt_c, remaining, band_obj)]
    while idx.size and rounds < fill_rounds:
        if limit.expired():
            stopped = "limit"
            break
        idx, remaining, took = k_.coherent.coherent_fill_round(b, c, valid, budget, prev, steps, level, nxt_v,
                                                               nxt_c, idx, remaining, acc)
        if took == 0:
            break
        rounds += 1
    cost, benefit = float(acc[0]), float(acc[1])
    single = False
    if best >= 0 and float(cand.benefit.flat[best]) > benefit:
        level = np.full(n, -1, dtype=np.int64)
        level[best // k] = best % k
        cost, benefit, single = float(cand.cost.flat[best]), float(cand.benefit.flat[best]), True
    return Result(level, cost, benefit, {
        "stopped": stopped, "rounds": 1, "moves": int(acc[2]), "fill_rounds": rounds, "band": int(band),
        "increments": int(acc[3]), "candidates": int(acc[4]), "single": single,
        "threshold": float(stop) if np.isfinite(stop) and stop > 0 else None})


def _solve_full(k_, cand: Candidates, budget: float, prev: np.ndarray, limit: TimeLimit, fill_rounds: int,
                expired: bool = False) -> Result:
    """The compiled path over stored hulls: one radix cut of every increment (or, ``expired``, the start
    clamped to the budget)."""
    hull = greedy._hull_compiled(k_, cand, budget, scratch=True, previous=prev)
    begin = hull.begin
    if expired:
        # Anytime: no time for the cut. The start, if over the budget, loses its lowest-value increments.
        steps, _ = k_.cut.clamp(begin, hull.value, hull.d_cost, hull.count, budget)
        band, stop, rounds, filled, stopped = 0, -np.inf, 0, 0, "limit"
    else:
        steps = hull.steps
        spent, band, stop, nr = k_.cut.radix_cut(hull.value, hull.value.view(np.int64), hull.d_cost, hull.count,
                                                 begin, _KEEP, budget, hull.hist, hull.total, steps, hull.ready)
        rounds = 1
        filled, stopped = greedy._fill_compiled(k_, hull, steps, budget - spent, limit, fill_rounds, hull.ready[:nr])
    r = greedy._finish_compiled(k_, cand, budget, hull, steps, {
        "stopped": stopped, "rounds": rounds, "moves": int(k_.cut.moves(steps, begin)), "fill_rounds": filled,
        "band": int(band)})
    if np.isfinite(stop) and stop > 0:
        r.stats["threshold"] = float(stop)
    return r


def solve_numpy(
    cand: Candidates,
    budget: float,
    *,
    limit: TimeLimit = NO_LIMIT,
    state: dict | None = None,
    fill_rounds: int = 64,
) -> Result:
    """The vectorised reference of ``solve``: the band steps 1–3 of the module's text, in numpy."""
    n, k = cand.n, cand.k
    if cand.previous is None or n == 0 or k == 0 or not budget > 0:
        r = greedy.solve_numpy(cand, budget, limit=limit, max_rounds=fill_rounds)
        r.stats["fallback"] = "no previous" if cand.previous is None else "empty"
        return r
    hull = greedy.upper_hull_numpy(cand, budget)
    steps = start_numpy(cand, hull)

    vflat, cflat = hull.value.ravel(), hull.d_cost.ravel()
    counter = {"rounds": 0, "moves": 0, "stopped": "done"}

    def events(idx: np.ndarray):
        """The objects' next increment and last increment as (value, Δcost) events; −inf/0 where none."""
        m, st = idx.size, steps[idx]
        value, weight = np.empty(2 * m), np.empty(2 * m)
        at = np.minimum(st, k - 1) * n + idx
        np.take(vflat, at, out=value[:m])
        np.take(cflat, at, out=weight[:m])
        at = np.maximum(st - 1, 0) * n + idx
        np.take(vflat, at, out=value[m:])
        np.take(cflat, at, out=weight[m:])
        # Ties keep what is drawn: a swap must gain.
        dec = value[m:]
        np.maximum(dec * _KEEP, np.nextafter(dec, np.inf), out=dec)
        top, bottom = st >= hull.count[idx], st == 0
        value[:m][top], weight[:m][top] = -np.inf, 0.0
        dec[bottom], weight[m:][bottom] = -np.inf, 0.0
        return value, weight

    def resolve(idx: np.ndarray, capacity: float) -> float:
        """Re-cut every increment of the objects ``idx`` at once (the others fixed); returns the stop value."""
        value = hull.value[:, idx]
        taken = greedy.cut(value.ravel(), hull.d_cost[:, idx].ravel(), capacity)
        new = taken.reshape(value.shape).sum(axis=0)
        counter["moves"] += int(np.abs(new - steps[idx]).sum())
        counter["rounds"] += 1
        steps[idx] = new
        left = value.ravel()[~taken]
        return float(left.max()) if left.size else -np.inf

    everyone = np.arange(n)
    spent = _spent(hull, steps)
    value, weight = events(everyone)
    theta = (state or {}).get("threshold")
    theta = float(theta) if isinstance(theta, (int, float)) and np.isfinite(theta) and theta > 0 else None
    if theta is None:
        # No threshold from the last frame: where one batch round over everyone would stop.
        keep = greedy.cut(value, weight, budget - (spent - float(weight[n:].sum())))
        left = value[~keep]
        stop = float(left.max()) if left.size else -np.inf
        theta = stop if np.isfinite(stop) and stop > 0 else None
    settled, band, stop, width = False, 0, -np.inf, _BAND
    while not settled and theta is not None and width <= 4 * _BAND:
        if limit.expired():
            counter["stopped"] = "limit"
            break
        # Frame coherence: only objects with an increment or decrement near the threshold can move.
        lo, hi = theta * (1 - width), theta * (1 + width)
        act = np.flatnonzero((value[:n] > lo) | ((value[n:] < hi) & (steps > 0)))
        band = act.size
        fixed = spent - _spent(hull, steps, act)
        before = steps[act].copy()
        stop = resolve(act, budget - fixed)
        after = fixed + _spent(hull, steps, act)
        # The others stay right only if the cut stopped inside the band (their events lie outside it).
        settled = lo <= stop <= hi and after <= budget * (1 + 1e-12)
        if settled:
            spent = after
        else:
            steps[act] = before
            theta, width = (stop if np.isfinite(stop) and stop > 0 else theta), width * 2
    rounds, moves, stopped = counter["rounds"], counter["moves"], counter["stopped"]
    if not settled and stopped == "done":
        r = greedy.solve_numpy(cand, budget, limit=limit, max_rounds=fill_rounds)
        r.stats.update(fallback="unsettled", moves=moves, coherent_rounds=rounds, band=band)
        return r

    # Anytime: stopped before the band was settled, the start may be over the budget: drop the
    # lowest-value increments until it fits.
    while spent > budget * (1 + 1e-12):
        value, weight = events(everyone)
        keep = greedy.cut(value[n:], weight[n:], budget - (spent - float(weight[n:].sum())))
        steps -= ~keep & (steps > 0)
        spent = _spent(hull, steps)

    filled = 0
    if stopped == "done":
        filled, stopped = greedy.fill_numpy(hull, steps, budget - spent, limit, fill_rounds)
    level = hull.chosen(steps)
    cost, benefit = greedy.totals(cand, level)
    level, cost, benefit, single = greedy.best_single(cand, budget, level, cost, benefit, hull.ok)
    return Result(level, cost, benefit, {
        "stopped": stopped, "rounds": rounds, "moves": moves, "fill_rounds": filled, "band": band,
        "increments": int(steps.sum()), "single": single, "threshold": stop if np.isfinite(stop) else None,
    })


def _spent(hull: greedy.Hull, steps: np.ndarray, idx: np.ndarray | None = None) -> float:
    """Σ cost of the hull points reached after ``steps`` increments, over all objects or ``idx``."""
    total = 0.0
    st = steps if idx is None else steps[idx]
    for j in range(hull.shape[0]):
        row = hull.d_cost[j] if idx is None else hull.d_cost[j, idx]
        total += float((row * (st > j)).sum())
    return total
