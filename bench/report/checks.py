"""The done-when checks, each with the margin by which it passes or misses, and the points of the
quality chart with their Pareto front (image error against mean frame time, lower is better in both).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from bench.machine import frame_noise
from bench.report.governed import explain, mean_words, std_words
from bench.report.results import (budget_free, finite, label, method_order, nearly_equal, repeats_at, run_at,
                                  target_of)

__all__ = [
    "STD_RATIO_LIMIT", "MAX_RATIO_LIMIT", "GOVERNOR_MEAN_LIMIT", "GOVERNOR_P99_LIMIT", "GOVERNOR_OVER_LIMIT",
    "GOVERNOR_FLIP_LIMIT", "quality_points", "pareto", "pareto_miss", "point_label", "verdict_word",
    "bound_frames", "bound_mask", "checks",
]


#: The done-when limits: Optimization's std ≤ a third of Static's and Feedback's, max ≤ 1.10 × target.
STD_RATIO_LIMIT = 1.0 / 3.0
MAX_RATIO_LIMIT = 1.10
#: The governor's limits: mean frame ≥ 0.85 × target where full detail exceeds it, p99 ≤ 1.15 × target,
#: ≤ 1 % of frames over 1.1 × target, and FLIP ≤ 0.75 × Optimization's without the governor.
GOVERNOR_MEAN_LIMIT = 0.85
GOVERNOR_P99_LIMIT = 1.15
GOVERNOR_OVER_LIMIT = 0.01
GOVERNOR_FLIP_LIMIT = 0.75


#: Relative slack on the limits, so a figure exactly at a limit passes despite float rounding.
_REL_EPS = 1e-9


def quality_points(results: dict) -> list[dict]:
    """Every (method, budget) run as a point — the median of its repeats (``run_at``), with the governor as
    its own method (``label``) — method, budget_ms (None if budget-free), frame_mean_ms, flip_mean,
    psnr_mean, ssim_mean (None where not measured). A budget-free method gives one point."""
    points = []
    runs = results.get("runs") or []
    for method in method_order(results):
        for governor in (False, True):
            mine = [r for r in runs if r.get("method") == method and bool(r.get("governor", False)) == governor]
            budgets = list(dict.fromkeys(float(r["target_ms"]) for r in mine if finite(r.get("target_ms")) is not None))
            for budget in sorted(budgets)[:1] if mine and budget_free(mine[0]) else sorted(budgets):
                run = run_at(results, method, budget, governor)
                if run is None:
                    continue
                s = run.get("summary") or {}
                points.append({
                    "method": label(method, governor),
                    "budget_ms": None if budget_free(run) else finite(run.get("target_ms")),
                    "frame_mean_ms": finite(s.get("frame_mean_ms")),
                    "flip_mean": finite(s.get("flip_mean")),
                    "psnr_mean": s.get("psnr_mean"),
                    "ssim_mean": finite(s.get("ssim_mean")),
                })
    return points


def _xy(points) -> np.ndarray:
    xy = np.asarray(points, dtype=float).reshape(-1, 2) if len(points) else np.zeros((0, 2))
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise ValueError(f"points must be (n, 2) pairs (frame time, error), got shape {xy.shape}")
    return xy


def pareto(points) -> np.ndarray:
    """(n,) bool: the points no other point dominates, both axes lower-is-better.

    points : (n, 2) — (mean frame time, mean FLIP). q dominates p when q ≤ p on both axes and q < p on
    at least one; equal points do not dominate each other, so ties are all on the front. A point with a
    NaN coordinate is neither on the front nor dominates anything.
    """
    xy = _xy(points)
    ok = np.isfinite(xy).all(axis=1)
    le = (xy[:, None, :] <= xy[None, :, :]).all(axis=2)  # le[q, p]: q ≤ p on both axes
    lt = (xy[:, None, :] < xy[None, :, :]).any(axis=2)
    dominated = (le & lt & ok[:, None]).any(axis=0)
    return ok & ~dominated


def pareto_miss(points, i: int) -> tuple[float, int | None]:
    """How far point ``i`` is from the front: (relative improvement, index of a point that dominates it).

    The improvement is the smallest relative decrease of either coordinate alone (frame time or error)
    that puts the point on the front: 0.0 when it already is, 1.0 when only a zero coordinate would do,
    NaN for a point with a NaN coordinate. The index names the dominating point nearest in that sense
    (None when on the front).
    """
    xy = _xy(points)
    p = xy[i]
    if not np.isfinite(p).all():
        return math.nan, None
    if pareto(xy)[i]:
        return 0.0, None
    others = np.isfinite(xy).all(axis=1)
    others[i] = False
    best, who = math.inf, None
    for axis in (0, 1):
        other = 1 - axis
        # to escape domination along ``axis``, p must beat every q at least as good on the other axis
        rivals = np.flatnonzero(others & (xy[:, other] <= p[other]))
        if rivals.size == 0 or p[axis] <= 0:
            continue
        j = int(rivals[np.argmin(xy[rivals, axis])])
        need = float(min(1.0, max(0.0, 1.0 - xy[j, axis] / p[axis])))
        if need < best:
            best, who = need, j
    return (best if math.isfinite(best) else 1.0), who


# ----------------------------------------------------------------------------- the done-when checks


def _check(name: str, passed: bool | None, value: float | None, limit: float | None, line: str, **extra) -> dict:
    return {"name": name, "passed": passed, "value": value, "limit": limit, "line": line, **extra}


def _skip(name: str, why: str) -> dict:
    return _check(name, None, None, None, f"SKIP {name}: {why}", skipped=why)


def verdict_word(passed: bool | None) -> str:
    return "SKIP" if passed is None else ("PASS" if passed else "FAIL")


def _std_check(name: str, opt: dict | None, ref: dict | None, ref_name: str, who: str = "optimization") -> dict:
    if opt is None or ref is None:
        return _skip(name, f"no {who if opt is None else ref_name} run at the target")
    o, r = finite(opt.get("frame_std_ms")), finite(ref.get("frame_std_ms"))
    if o is None or r is None:
        return _skip(name, "frame-time std not measured")
    ratio = o / r if r > 0 else (0.0 if o == 0 else math.inf)
    passed = o <= STD_RATIO_LIMIT * r * (1 + _REL_EPS) + 1e-12
    miss = "" if passed else f", misses by {ratio / STD_RATIO_LIMIT:.2f}× (needs std ≤ {STD_RATIO_LIMIT * r:.2f} ms)"
    line = (f"{verdict_word(passed)} {name}: {who} std {o:.2f} ms = {ratio:.3f} × {ref_name}'s {r:.2f} ms "
            f"(limit {STD_RATIO_LIMIT:.3f}){miss}")
    return _check(name, passed, ratio, STD_RATIO_LIMIT, line)


def point_label(point: dict) -> str:
    budget = point.get("budget_ms")
    return f"{point['method']}@{'any' if budget is None else f'{budget:g}'}"


def _pareto_check(name: str, method: str, points: list[dict], target: float) -> dict:
    usable = [p for p in points if p["frame_mean_ms"] is not None and p["flip_mean"] is not None]
    mine = [k for k, p in enumerate(usable) if p["method"] == method]
    if not mine:
        return _skip(name, f"no {method} run with image quality measured")
    at = [k for k in mine if usable[k]["budget_ms"] is None or nearly_equal(usable[k]["budget_ms"], target)]
    if not at:
        return _skip(name, f"no {method} run at the target {target:g} ms with image quality measured")
    xy = np.array([[p["frame_mean_ms"], p["flip_mean"]] for p in usable])
    front = pareto(xy)
    per_budget = {}
    for k in mine:
        miss, _ = pareto_miss(xy, k)
        per_budget[point_label(usable[k])] = miss
    i = at[0]
    miss, who = pareto_miss(xy, i)
    passed = bool(front[i])
    p = usable[i]
    line = (f"{verdict_word(passed)} {name}: {point_label(p)} (frame mean {p['frame_mean_ms']:.1f} ms, FLIP "
            f"{p['flip_mean']:.4f}) is {'on' if passed else 'off'} the Pareto front of {len(usable)} points")
    if not passed and who is not None:
        q = usable[who]
        line += (f"; dominated by {point_label(q)} ({q['frame_mean_ms']:.1f} ms, FLIP {q['flip_mean']:.4f}): "
                 f"needs {100 * miss:.1f} % lower frame time or FLIP")
    on = sum(1 for k in mine if front[k])
    line += f"; {on} of {len(mine)} {method} points on the front"
    return _check(name, passed, miss, 0.0, line, budgets=per_budget)


def _reference(results: dict, target: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Full detail's frame times at the target (the ``none`` run's frames that draw a selection), or None."""
    frames = (run_at(results, "none", target) or {}).get("frames") or {}
    if not frames.get("t"):
        return None
    rt = np.asarray(frames["t"], np.float64)
    rms = np.asarray(frames["time_ms"], np.float64)
    keep = np.asarray(frames.get("seq") or np.zeros(rt.size), np.int64) >= 0
    return (rt[keep], rms[keep]) if keep.sum() >= 2 else None


def _masks(frames: dict, reference: tuple[np.ndarray, np.ndarray], target: float,
           warmup: float) -> tuple[np.ndarray, np.ndarray]:
    """(used, bound) frames of a run: those after the warm-up that draw a selection within full detail's span,
    and of them those at which full detail takes longer than the target."""
    rt, rms = reference
    t = np.asarray(frames["t"], np.float64)
    seq = np.asarray(frames.get("seq") or np.zeros(t.size), np.int64)
    use = (t >= warmup) & (seq >= 0) & (t >= rt[0]) & (t <= rt[-1])
    return use, use & (np.interp(t, rt, rms) > target)


def bound_mask(results: dict, run: dict | None, target_ms: float | None = None) -> np.ndarray | None:
    """Which of ``run``'s frames are bound (``bound_frames``), or None without a ``none`` run or frames."""
    target = target_of(results, target_ms)
    reference = _reference(results, target)
    frames = (run or {}).get("frames") or {}
    if reference is None or not frames.get("t"):
        return None
    return _masks(frames, reference, target, float(results.get("warmup_s") or 0.0))[1]


def bound_frames(results: dict, target_ms: float | None = None) -> dict | None:
    """Where the budget binds: each method's frame figures over the frames at which full detail (the ``none``
    run, at the same tour time) takes longer than the target.

    F&S's Table 1 std is over the whole path, and on a path with a cheap stretch (the auditorium's viewpoint
    B, where full detail is well under the target) every method draws fast frames there — none has anything
    to spend the budget on — so the std measures the stretch as much as the method. Over the frames where
    full detail exceeds the target, a method that holds the budget shows a steady time. Frames are those after the
    warm-up that draw a selection; None's time at t is interpolated between its frames. Returns
    {"share": share of the optimization run's frames that are bound, "methods": {method (``label``: "+gov"
    with the governor): {frames, frame_mean_ms, frame_std_ms, frame_max_ms}}}, or None without a ``none`` run.
    """
    target = target_of(results, target_ms)
    reference = _reference(results, target)
    if reference is None:
        return None
    warmup = float(results.get("warmup_s") or 0.0)
    out: dict[str, Any] = {"methods": {}, "share": None}
    for method, governor in [(m, g) for m in method_order(results) for g in (False, True)]:
        run = run_at(results, method, target, governor)
        f = (run or {}).get("frames") or {}
        if not f.get("t"):
            continue
        use, bound = _masks(f, reference, target, warmup)
        v = np.asarray(f["time_ms"], np.float64)[bound]
        out["methods"][label(method, governor)] = {
            "frames": int(bound.sum()),
            "frame_mean_ms": float(v.mean()) if v.size else None,
            "frame_std_ms": float(v.std()) if v.size else None,
            "frame_max_ms": float(v.max()) if v.size else None,
        }
        if method == "optimization" and not governor and use.any():
            out["share"] = float(bound.sum() / use.sum())
    return out


def checks(results: dict) -> list[dict]:
    """The evaluation's done-when checks at the headline target, each {name, passed, value, limit, line}.

    - ``opt_std_vs_static`` / ``opt_std_vs_feedback``: value = Optimization's frame-time std ÷ the other's,
      limit 1/3 (at the limit passes);
    - ``opt_max``: value = Optimization's max frame time ÷ target, limit 1.10;
    - ``opt_std_bound_vs_static`` / ``opt_std_bound_vs_feedback``: the std checks over the frames where full
      detail exceeds the target (``bound_frames``; beyond the headline checks: where the budget binds), for
      Optimization with the client's frame governor (without it when the eval ran no governor);
    - ``governor_mean_bound``: Optimization with the governor, mean frame ÷ target over those frames, ≥ 0.85;
    - ``governor_p99``: its p99 ÷ target, ≤ 1.15; ``governor_over``: its share of frames over 1.1 × target,
      ≤ 0.01; ``governor_flip_ratio``: its mean FLIP ÷ Optimization's without the governor, ≤ 0.75 (skipped
      where full detail never exceeds the target: both then draw the whole scene);
    - ``opt_pareto`` / ``pred_pareto``: the method's point at the target against every (method, budget)
      point of the quality chart; value = the smallest relative improvement of frame time or FLIP that
      puts it on the front (0 on it), limit 0; ``budgets`` gives that figure for each of its budgets.

    A check whose methods or figures are absent has ``passed`` None and a ``skipped`` reason.
    """
    target = target_of(results, None)
    opt = run_at(results, "optimization", target)
    static = run_at(results, "static", target)
    feedback = run_at(results, "feedback", target)
    s = lambda run: None if run is None else (run.get("summary") or {})  # noqa: E731
    out = [
        _std_check("opt_std_vs_static", s(opt), s(static), "static"),
        _std_check("opt_std_vs_feedback", s(opt), s(feedback), "feedback"),
    ]
    mx = finite((s(opt) or {}).get("frame_max_ms"))
    if opt is None or mx is None:
        out.append(_skip("opt_max", "no optimization run at the target" if opt is None else "max not measured"))
    else:
        ratio = mx / target
        passed = mx <= MAX_RATIO_LIMIT * target * (1 + _REL_EPS)
        miss = "" if passed else f", misses by {mx - MAX_RATIO_LIMIT * target:.1f} ms"
        out.append(_check("opt_max", passed, ratio, MAX_RATIO_LIMIT,
                          f"{verdict_word(passed)} opt_max: optimization max {mx:.1f} ms = {ratio:.3f} × target "
                          f"{target:g} ms (limit {MAX_RATIO_LIMIT:.2f}){miss}"))
    bound = bound_frames(results, target)
    gov = run_at(results, "optimization", target, governor=True)
    who = "optimization+gov" if gov is not None else "optimization"
    warmup = float(results.get("warmup_s") or 0.0)
    mask = bound_mask(results, gov, target) if gov is not None else None
    why = None if mask is None else explain(gov.get("frames") or {}, mask, target, warmup)
    for ref_name in ("static", "feedback"):
        name = f"opt_std_bound_vs_{ref_name}"
        by = (bound or {}).get("methods", {})
        if bound is None:
            out.append(_skip(name, "no none run to tell where full detail exceeds the target"))
            continue
        c = _std_check(name, by.get(who), by.get(ref_name), ref_name, who)
        if c["passed"] is not None:
            share = bound["share"]
            c["line"] += (f" — over the frames where full detail exceeds the target"
                          + ("" if share is None else f" ({100 * share:.0f} % of optimization's)"))
            c["share"] = share
            if why is not None:
                c["why"] = why
                if not c["passed"]:
                    c["line"] += f"; {std_words(why)}"
        out.append(c)
    out += _governor_checks(gov, opt, (bound or {}).get("methods", {}).get("optimization+gov"), bound, target,
                            warmup)
    mean = next(c for c in out if c["name"] == "governor_mean_bound")
    if why is not None and mean["passed"] is not None:
        mean["why"] = why
        if not mean["passed"]:
            mean["line"] += f"; {mean_words(why, MAX_RATIO_LIMIT)}"
    flip = next(c for c in out if c["name"] == "governor_flip_ratio")
    if flip["passed"] is not None:
        _flip_samples(flip, repeats_at(results, "optimization", target, True),
                      repeats_at(results, "optimization", target, False))
    points = quality_points(results)
    out.append(_pareto_check("opt_pareto", "optimization", points, target))
    out.append(_pareto_check("pred_pareto", "predictive", points, target))
    return out


def _flip_samples(check: dict, governed: list[dict], plain: list[dict]) -> None:
    """Add to the FLIP check what its one pair of median repeats leaves out: the ratio over every repeat, and in
    how many of the image samples where Optimization without the governor errs the governed run errs less.
    Samples are paired by index: the same seed samples every run at the same tour times (``bench.quality``)."""
    def flips(runs: list[dict]) -> list[np.ndarray]:
        return [np.asarray((r.get("quality") or {}).get("flip") or [], np.float64) for r in runs]

    g, u = flips(governed), flips(plain)
    g_all, u_all = (np.concatenate(x) if x else np.zeros(0) for x in (g, u))
    if not g_all.size or not u_all.size or not u_all.mean() > 0:
        return
    lower = errs = 0
    for a, b in zip(g, u):
        n = min(a.size, b.size)
        err = b[:n] > 0
        errs += int(err.sum())
        lower += int((a[:n][err] < b[:n][err]).sum())
    check["all_repeats"] = float(g_all.mean() / u_all.mean())
    check["samples_lower"], check["samples_erring"] = lower, errs
    check["line"] += (f"; over every repeat {check['all_repeats']:.3f}, the governed error lower in {lower} of the "
                      f"{errs} samples where optimization's is not 0")


def _limit_check(name: str, value: float | None, limit: float, at_least: bool, what: str, why: str) -> dict:
    """A figure against a limit (``at_least``: value ≥ limit passes, else value ≤ limit), or a skip."""
    if value is None:
        return _skip(name, why)
    passed = value >= limit * (1 - _REL_EPS) if at_least else value <= limit * (1 + _REL_EPS)
    sign = "≥" if at_least else "≤"
    miss = "" if passed else f", misses by {abs(value - limit):.3f}"
    return _check(name, bool(passed), value, limit,
                  f"{verdict_word(passed)} {name}: {what} = {value:.3f} (limit {sign} {limit:g}){miss}")


def _governor_checks(gov: dict | None, opt: dict | None, gov_bound: dict | None, bound: dict | None,
                     target: float, warmup: float = 0.0) -> list[dict]:
    """The governor's checks: mean where full detail exceeds the target, p99, share over, FLIP against
    Optimization without the governor. The mean's line also says how far apart the run's consecutive frames of
    the same work, both at least half the target, fell (``bench.machine.frame_noise``, its ``identical_work``):
    a governor that predicts each frame from the one before and holds 99 % of frames within 1.1 × target is left a
    mean of at most about 1.1 ÷ that scatter's p99. Where the check misses, the line goes on with the governed
    run's own factors (``bench.report.governed``)."""
    names = ("governor_mean_bound", "governor_p99", "governor_over", "governor_flip_ratio")
    if gov is None:
        return [_skip(n, "no optimization run with the governor at the target") for n in names]
    s = gov.get("summary") or {}
    mean = finite((gov_bound or {}).get("frame_mean_ms"))
    p99, over = finite(s.get("frame_p99_ms")), finite(s.get("over_pct"))
    flip = finite(s.get("flip_mean"))
    base = finite(((opt or {}).get("summary") or {}).get("flip_mean"))
    flip_ratio = None if flip is None or base is None or base <= 0 else flip / base
    why_bound = ("no none run to tell where full detail exceeds the target" if bound is None
                 else "no frames where full detail exceeds the target")
    # Where the budget never binds, both runs draw (nearly) the whole scene: their FLIPs differ by sampling
    # noise, and their ratio says nothing of what the governor adds.
    unbound = bound is not None and not (gov_bound or {}).get("frames")
    why_flip = ("full detail never exceeds the target: with and without the governor the whole scene is drawn"
                if unbound else
                "optimization without the governor drew the full-detail picture (FLIP 0): no ratio"
                if base is not None and base <= 0 else
                "FLIP not measured for optimization with and without the governor")
    f = gov.get("frames") or {}
    noise = frame_noise(f.get("t") or [], np.asarray(f.get("time_ms") or [], np.float64) / 1e3,
                        f.get("triangles") or [], warmup, least=target / 2e3)
    mean_check = _limit_check(names[0], None if mean is None else mean / target, GOVERNOR_MEAN_LIMIT, True,
                              f"optimization+gov mean {mean or 0:.1f} ms ÷ target {target:g} ms where full detail "
                              f"exceeds it", why_bound)
    mean_check["identical_work"] = noise
    if mean_check["passed"] is not None and noise["p99"]:
        mean_check["line"] += (f"; consecutive frames of the same triangles (both ≥ ½ target) fell up to "
                               f"{noise['p99']:.3f} × apart (p99 of {noise['pairs']} pairs), so holding 99 % within "
                               f"{MAX_RATIO_LIMIT:.2f} × leaves a governor that predicts each frame from the one "
                               f"before a mean of at most about {MAX_RATIO_LIMIT / noise['p99']:.2f} × on this "
                               f"machine")
    return [
        mean_check,
        _limit_check(names[1], None if p99 is None else p99 / target, GOVERNOR_P99_LIMIT, False,
                     f"optimization+gov p99 {p99 or 0:.1f} ms ÷ target {target:g} ms", "p99 not measured"),
        _limit_check(names[2], None if over is None else over / 100.0, GOVERNOR_OVER_LIMIT, False,
                     f"optimization+gov share of frames over {MAX_RATIO_LIMIT:.2f} × target", "share not measured"),
        _limit_check(names[3], None if unbound else flip_ratio, GOVERNOR_FLIP_LIMIT, False,
                     f"optimization+gov FLIP {flip or 0:.4f} ÷ optimization's {base or 0:.4f}", why_flip),
    ]
