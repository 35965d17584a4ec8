"""The evaluation's report folder, written from the results dict alone (``bench.evaluate.evaluate``).

What a reader needs to choose a method: Funkhouser & Séquin's Table 1 (their columns — compute mean and
max, frame mean, max and std — plus p95, image error and popping), their Figure 7 (frame time over the
tour, one panel per method on the same axes), the chart of image error against mean frame time for every
method at every budget with its Pareto front, false-colour level images at viewpoints A and C, and the
issue's done-when checks, each with the margin by which it passes or misses. ``index.html`` ties them
together with relative links, so the folder can be zipped, served or opened from disk.

Everything here reads only the results dict (the contract in the evaluation's schema: times in
milliseconds), never a store, a server or a GPU, so the report can be rebuilt from ``results.json``.
"""

from __future__ import annotations

import csv
import datetime as _dt
import html
import json
import math
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

__all__ = [
    "METHOD_ORDER",
    "COLUMNS",
    "table1",
    "write_table1",
    "quality_points",
    "pareto",
    "pareto_miss",
    "checks",
    "bound_frames",
    "write_traces",
    "write_quality",
    "write_checks",
    "write_index",
    "write_report",
    "summary_lines",
]

#: F&S Table 1's order, then the methods of Zach (2002) and Zach, Mantler & Karner (2002).
METHOD_ORDER = ("none", "static", "feedback", "optimization", "hierarchical", "predictive", "mixed")
#: Methods that ignore the budget: run once (at the headline target), their run counts for every budget.
BUDGET_FREE = frozenset({"none", "static"})

#: Table 1's columns: (key in the row and in a run's summary, markdown heading, decimals).
COLUMNS: tuple[tuple[str, str, int], ...] = (
    ("compute_mean_ms", "compute mean", 2),
    ("compute_max_ms", "compute max", 2),
    ("frame_mean_ms", "frame mean", 1),
    ("frame_max_ms", "frame max", 1),
    ("frame_std_ms", "frame std", 2),
    ("frame_p95_ms", "frame p95", 1),
    ("frame_p99_ms", "frame p99", 1),
    ("over_pct", "over 1.1 × target (%)", 2),
    ("flip_mean", "FLIP", 4),
    ("psnr_mean", "PSNR (dB)", 2),
    ("ssim_mean", "SSIM", 4),
    ("popping_mean", "popping", 3),
    ("triangles_mean", "triangles", 0),
    ("frames", "frames", 0),
)

#: The done-when limits (issue 8): Optimization's std ≤ a third of Static's and Feedback's, max ≤ 1.10 × target.
STD_RATIO_LIMIT = 1.0 / 3.0
MAX_RATIO_LIMIT = 1.10
#: PSNR at or above this (dB) means frames identical to full detail (bench.quality may cap ∞ here).
PSNR_CAP = 100.0
#: Relative slack on the limits, so a figure exactly at a limit passes despite float rounding.
_REL_EPS = 1e-9

_COLOURS = {
    "none": "tab:gray",
    "static": "tab:brown",
    "feedback": "tab:orange",
    "optimization": "tab:blue",
    "hierarchical": "tab:purple",
    "predictive": "tab:green",
    "mixed": "tab:red",
}
_MARKERS = {
    "none": "X",
    "static": "s",
    "feedback": "D",
    "optimization": "o",
    "hierarchical": "v",
    "predictive": "^",
    "mixed": "P",
}


# ----------------------------------------------------------------------------- reading the results


def _finite(x: Any) -> float | None:
    """``x`` as a float when it is a finite number, else None (missing, NaN, ±inf, not a number)."""
    if isinstance(x, bool) or x is None:
        return None
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _close(a: float, b: float) -> bool:
    return math.isclose(float(a), float(b), rel_tol=1e-6, abs_tol=1e-9)


def _method_order(results: dict) -> list[str]:
    """Methods in Table 1's order, then any others in the order the results name or run them."""
    seen = list(results.get("methods") or []) + [r.get("method") for r in results.get("runs") or []]
    names = [m for m in METHOD_ORDER if m in seen]
    names += [m for m in dict.fromkeys(seen) if m and m not in names]
    return names


def _target(results: dict, target_ms: float | None) -> float:
    target = results.get("target_ms") if target_ms is None else target_ms
    if _finite(target) is None or float(target) <= 0:
        raise ValueError(f"the report needs a positive target frame time in ms, got {target!r}")
    return float(target)


def _budget_free(run: dict) -> bool:
    flag = run.get("budget_dependent")
    return (not flag) if isinstance(flag, bool) else run.get("method") in BUDGET_FREE


def _run_at(results: dict, method: str, target_ms: float) -> dict | None:
    """The method's run at ``target_ms``; a budget-free method's only run counts for every budget."""
    runs = [r for r in results.get("runs") or [] if r.get("method") == method]
    for run in runs:
        if _finite(run.get("target_ms")) is not None and _close(run["target_ms"], target_ms):
            return run
    free = [r for r in runs if _budget_free(r)]
    return free[0] if free else None


# ----------------------------------------------------------------------------- Table 1


def table1(results: dict, target_ms: float | None = None) -> list[dict]:
    """One row per method at ``target_ms`` (default the headline target), in F&S Table 1's order.

    Each row: ``method`` plus every key of :data:`COLUMNS`, copied from the run's summary (times in
    ms); a figure the run did not measure (no image quality, say) is None. Methods without a run at
    the target are left out.
    """
    target = _target(results, target_ms)
    rows = []
    for method in _method_order(results):
        run = _run_at(results, method, target)
        if run is None:
            continue
        summary = run.get("summary") or {}
        if any(key not in summary for key, _, _ in COLUMNS) and (run.get("frames") or {}).get("t"):
            # Figures added to the summary since the run (p99, over 1.1 × target) come from its frames.
            from bench.evaluate import summarize_frames

            summary = {**summarize_frames(run["frames"], float(results.get("warmup_s") or 0.0),
                                          float(run.get("target_ms") or target)), **summary}
        row: dict[str, Any] = {"method": method}
        for key, _, _ in COLUMNS:
            value = summary.get(key)
            row[key] = value if key == "frames" or value is None else float(value)
        if row["frames"] is not None:
            row["frames"] = int(row["frames"])
        rows.append(row)
    return rows


def _fmt(value: Any, decimals: int) -> str:
    """A table cell: fixed decimals, "—" for missing, "∞" for infinite (PSNR of identical images)."""
    if value is None:
        return "—"
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        return str(int(value))
    v = float(value)
    if math.isnan(v):
        return "—"
    if math.isinf(v):
        return "∞" if v > 0 else "−∞"
    return f"{v:,.{decimals}f}" if decimals == 0 else f"{v:.{decimals}f}"


def _headings() -> list[str]:
    return ["method"] + [f"{label} (ms)" if key.endswith("_ms") else label for key, label, _ in COLUMNS]


def _cells(row: dict) -> list[str]:
    return [str(row["method"])] + [_fmt(row.get(key), dec) for key, _, dec in COLUMNS]


def write_table1(rows: Sequence[dict], out: Path, *, title: str | None = None) -> tuple[Path, Path]:
    """Write ``table1.csv`` (full-precision figures, empty for missing) and ``table1.md`` into folder ``out``.

    Times are milliseconds (F&S printed seconds; the headings say ms).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    keys = ["method"] + [key for key, _, _ in COLUMNS]
    csv_path, md_path = out / "table1.csv", out / "table1.md"
    with csv_path.open("w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, fieldnames=keys)
        writer.writeheader()
        for row in rows:
            writer.writerow({k: "" if row.get(k) is None else row.get(k) for k in keys})
    heads = _headings()
    lines = [f"# {title}", ""] if title else []
    lines += ["| " + " | ".join(heads) + " |", "|" + "|".join(["---"] + ["---:"] * (len(heads) - 1)) + "|"]
    lines += ["| " + " | ".join(_cells(row)) + " |" for row in rows]
    lines += ["", "Times in milliseconds; frame figures over the frames after the warm-up. FLIP: mean LDR-FLIP "
              "against the full-detail frame (lower is better); popping: excess frame-to-frame change over "
              "the full-detail sequence (lower is better)."]
    md_path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return csv_path, md_path


# ----------------------------------------------------------------------------- the quality chart's points and front


def quality_points(results: dict) -> list[dict]:
    """Every (method, budget) run as a point: method, budget_ms (None if budget-free), frame_mean_ms,
    flip_mean, psnr_mean, ssim_mean (None where not measured). A budget-free method gives one point."""
    points = []
    for method in _method_order(results):
        for run in results.get("runs") or []:
            if run.get("method") != method:
                continue
            s = run.get("summary") or {}
            points.append({
                "method": method,
                "budget_ms": None if _budget_free(run) else _finite(run.get("target_ms")),
                "frame_mean_ms": _finite(s.get("frame_mean_ms")),
                "flip_mean": _finite(s.get("flip_mean")),
                "psnr_mean": s.get("psnr_mean"),
                "ssim_mean": _finite(s.get("ssim_mean")),
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


def _word(passed: bool | None) -> str:
    return "SKIP" if passed is None else ("PASS" if passed else "FAIL")


def _std_check(name: str, opt: dict | None, ref: dict | None, ref_name: str) -> dict:
    if opt is None or ref is None:
        return _skip(name, f"no {'optimization' if opt is None else ref_name} run at the target")
    o, r = _finite(opt.get("frame_std_ms")), _finite(ref.get("frame_std_ms"))
    if o is None or r is None:
        return _skip(name, "frame-time std not measured")
    ratio = o / r if r > 0 else (0.0 if o == 0 else math.inf)
    passed = o <= STD_RATIO_LIMIT * r * (1 + _REL_EPS) + 1e-12
    miss = "" if passed else f", misses by {ratio / STD_RATIO_LIMIT:.2f}× (needs std ≤ {STD_RATIO_LIMIT * r:.2f} ms)"
    line = (f"{_word(passed)} {name}: optimization std {o:.2f} ms = {ratio:.3f} × {ref_name}'s {r:.2f} ms "
            f"(limit {STD_RATIO_LIMIT:.3f}){miss}")
    return _check(name, passed, ratio, STD_RATIO_LIMIT, line)


def _label(point: dict) -> str:
    budget = point.get("budget_ms")
    return f"{point['method']}@{'any' if budget is None else f'{budget:g}'}"


def _pareto_check(name: str, method: str, points: list[dict], target: float) -> dict:
    usable = [p for p in points if p["frame_mean_ms"] is not None and p["flip_mean"] is not None]
    mine = [k for k, p in enumerate(usable) if p["method"] == method]
    if not mine:
        return _skip(name, f"no {method} run with image quality measured")
    at = [k for k in mine if usable[k]["budget_ms"] is None or _close(usable[k]["budget_ms"], target)]
    if not at:
        return _skip(name, f"no {method} run at the target {target:g} ms with image quality measured")
    xy = np.array([[p["frame_mean_ms"], p["flip_mean"]] for p in usable])
    front = pareto(xy)
    per_budget = {}
    for k in mine:
        miss, _ = pareto_miss(xy, k)
        per_budget[_label(usable[k])] = miss
    i = at[0]
    miss, who = pareto_miss(xy, i)
    passed = bool(front[i])
    p = usable[i]
    line = (f"{_word(passed)} {name}: {_label(p)} (frame mean {p['frame_mean_ms']:.1f} ms, FLIP "
            f"{p['flip_mean']:.4f}) is {'on' if passed else 'off'} the Pareto front of {len(usable)} points")
    if not passed and who is not None:
        q = usable[who]
        line += (f"; dominated by {_label(q)} ({q['frame_mean_ms']:.1f} ms, FLIP {q['flip_mean']:.4f}): "
                 f"needs {100 * miss:.1f} % lower frame time or FLIP")
    on = sum(1 for k in mine if front[k])
    line += f"; {on} of {len(mine)} {method} points on the front"
    return _check(name, passed, miss, 0.0, line, budgets=per_budget)


def bound_frames(results: dict, target_ms: float | None = None) -> dict | None:
    """Where the budget binds: each method's frame figures over the frames at which full detail (the ``none``
    run, at the same tour time) takes longer than the target.

    F&S's Table 1 std is over the whole path, and on a path with a cheap stretch (the auditorium's viewpoint
    B: full detail 15 ms against 50) every method draws fast frames there — none has anything to spend the
    budget on — so the std measures the stretch as much as the method. Over the frames where full detail
    exceeds the target, a method that holds the budget shows a steady time. Frames are those after the
    warm-up that draw a selection; None's time at t is interpolated between its frames. Returns
    {"share": share of the optimization run's frames that are bound, "methods": {method: {frames,
    frame_mean_ms, frame_std_ms, frame_max_ms}}}, or None without a ``none`` run.
    """
    target = _target(results, target_ms)
    ref = _run_at(results, "none", target)
    frames = (ref or {}).get("frames") or {}
    if not frames.get("t"):
        return None
    warmup = float(results.get("warmup_s") or 0.0)
    rt = np.asarray(frames["t"], np.float64)
    rms = np.asarray(frames["time_ms"], np.float64)
    rseq = np.asarray(frames.get("seq") or np.zeros(rt.size), np.int64)
    keep = rseq >= 0
    if keep.sum() < 2:
        return None
    rt, rms = rt[keep], rms[keep]
    out: dict[str, Any] = {"methods": {}, "share": None}
    for method in _method_order(results):
        run = _run_at(results, method, target)
        f = (run or {}).get("frames") or {}
        if not f.get("t"):
            continue
        t = np.asarray(f["t"], np.float64)
        ms = np.asarray(f["time_ms"], np.float64)
        seq = np.asarray(f.get("seq") or np.zeros(t.size), np.int64)
        use = (t >= warmup) & (seq >= 0) & (t >= rt[0]) & (t <= rt[-1])
        bound = use & (np.interp(t, rt, rms) > target)
        v = ms[bound]
        out["methods"][method] = {
            "frames": int(bound.sum()),
            "frame_mean_ms": float(v.mean()) if v.size else None,
            "frame_std_ms": float(v.std()) if v.size else None,
            "frame_max_ms": float(v.max()) if v.size else None,
        }
        if method == "optimization" and use.any():
            out["share"] = float(bound.sum() / use.sum())
    return out


def checks(results: dict) -> list[dict]:
    """The issue's done-when checks at the headline target, each {name, passed, value, limit, line}.

    - ``opt_std_vs_static`` / ``opt_std_vs_feedback``: value = Optimization's frame-time std ÷ the other's,
      limit 1/3 (at the limit passes);
    - ``opt_max``: value = Optimization's max frame time ÷ target, limit 1.10;
    - ``opt_std_bound_vs_static`` / ``opt_std_bound_vs_feedback``: the std checks over the frames where full
      detail exceeds the target (``bound_frames``; beyond the issue's checks: where the budget binds);
    - ``opt_pareto`` / ``pred_pareto``: the method's point at the target against every (method, budget)
      point of the quality chart; value = the smallest relative improvement of frame time or FLIP that
      puts it on the front (0 on it), limit 0; ``budgets`` gives that figure for each of its budgets.

    A check whose methods or figures are absent has ``passed`` None and a ``skipped`` reason.
    """
    target = _target(results, None)
    opt = _run_at(results, "optimization", target)
    static = _run_at(results, "static", target)
    feedback = _run_at(results, "feedback", target)
    s = lambda run: None if run is None else (run.get("summary") or {})  # noqa: E731
    out = [
        _std_check("opt_std_vs_static", s(opt), s(static), "static"),
        _std_check("opt_std_vs_feedback", s(opt), s(feedback), "feedback"),
    ]
    mx = _finite((s(opt) or {}).get("frame_max_ms"))
    if opt is None or mx is None:
        out.append(_skip("opt_max", "no optimization run at the target" if opt is None else "max not measured"))
    else:
        ratio = mx / target
        passed = mx <= MAX_RATIO_LIMIT * target * (1 + _REL_EPS)
        miss = "" if passed else f", misses by {mx - MAX_RATIO_LIMIT * target:.1f} ms"
        out.append(_check("opt_max", passed, ratio, MAX_RATIO_LIMIT,
                          f"{_word(passed)} opt_max: optimization max {mx:.1f} ms = {ratio:.3f} × target "
                          f"{target:g} ms (limit {MAX_RATIO_LIMIT:.2f}){miss}"))
    bound = bound_frames(results, target)
    for ref_name in ("static", "feedback"):
        name = f"opt_std_bound_vs_{ref_name}"
        by = (bound or {}).get("methods", {})
        if bound is None:
            out.append(_skip(name, "no none run to tell where full detail exceeds the target"))
            continue
        c = _std_check(name, by.get("optimization"), by.get(ref_name), ref_name)
        if c["passed"] is not None:
            share = bound["share"]
            c["line"] += (f" — over the frames where full detail exceeds the target"
                          + ("" if share is None else f" ({100 * share:.0f} % of optimization's)"))
            c["share"] = share
        out.append(c)
    points = quality_points(results)
    out.append(_pareto_check("opt_pareto", "optimization", points, target))
    out.append(_pareto_check("pred_pareto", "predictive", points, target))
    return out


# ----------------------------------------------------------------------------- charts


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _colour(method: str, k: int) -> str:
    return _COLOURS.get(method, f"C{k % 10}")


def write_traces(results: dict, path: Path, target_ms: float | None = None) -> Path | None:
    """F&S Figure 7: frame time over client time, one panel per method at the target, shared axes.

    The target and 1.10 × target are horizontal lines, the warm-up is shaded, viewpoints A/B/C are
    vertical lines. The y axis stops at 4 × target so the budgeted methods stay readable; a panel whose
    frames go higher says so (its max after the warm-up is in its label). None when no run at the target
    has frames.
    """
    target = _target(results, target_ms)
    series = []
    for method in _method_order(results):
        run = _run_at(results, method, target)
        frames = (run or {}).get("frames") or {}
        t, ms = np.asarray(frames.get("t") or [], float), np.asarray(frames.get("time_ms") or [], float)
        if t.size and t.size == ms.size:
            series.append((method, t, ms, (run.get("summary") or {})))
    if not series:
        return None
    plt = _pyplot()
    peak = max(float(np.nanmax(ms)) for _, _, ms, _ in series)
    top = max(1.5 * target, min(1.05 * peak, 4.0 * target))
    fig, axes = plt.subplots(len(series), 1, sharex=True, sharey=True, figsize=(10, 1.25 + 1.45 * len(series)), dpi=110,
                             squeeze=False)
    warm = _finite(results.get("warmup_s")) or 0.0
    viewpoints = {k: v for k, v in (results.get("viewpoints") or {}).items() if _finite(v) is not None}
    for k, (ax, (method, t, ms, summary)) in enumerate(zip(axes[:, 0], series)):
        if warm > 0:
            ax.axvspan(0, warm, color="0.93", lw=0)
        for name, at in viewpoints.items():
            ax.axvline(float(at), color="0.35", lw=0.8, ls="-.")
            if k == 0:
                ax.text(float(at), 1.02, str(name), transform=ax.get_xaxis_transform(), ha="center", va="bottom",
                        fontsize=8)
        ax.plot(t, ms, lw=0.8, color=_colour(method, k))
        ax.axhline(target, color="tab:red", ls="--", lw=1.0)
        ax.axhline(MAX_RATIO_LIMIT * target, color="tab:red", ls=":", lw=0.8)
        stats = ", ".join(
            f"{label} {_fmt(summary.get(key), 1)}" for key, label in
            (("frame_mean_ms", "mean"), ("frame_std_ms", "std"), ("frame_max_ms", "max"))
        )
        clipped = f"; frames above {top:.0f} ms clipped" if float(np.nanmax(ms)) > top else ""
        ax.text(0.005, 0.95, f"{method} — {stats} ms{clipped}", transform=ax.transAxes, ha="left", va="top",
                fontsize=8, bbox=dict(boxstyle="round,pad=0.2", fc="white", ec="0.8", alpha=0.85))
        ax.grid(alpha=0.3)
        ax.set_ylabel("ms")
    axes[0, 0].set_ylim(0, top)
    axes[-1, 0].set_xlabel("client time (s)")
    fig.suptitle(f"Frame time per method at target {target:g} ms (dashed) and 1.10 × target (dotted) — "
                 f"{results.get('scene', '')}", fontsize=10)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def _scatter_by_method(ax, points: list[dict], key: str, *, annotate: bool = True) -> None:
    methods = list(dict.fromkeys(p["method"] for p in points))
    for k, method in enumerate(methods):
        mine = [p for p in points if p["method"] == method]
        xs = [p["frame_mean_ms"] for p in mine]
        ys = [p[key] for p in mine]
        ax.scatter(xs, ys, marker=_MARKERS.get(method, "o"), color=_colour(method, k), s=42, label=method, zorder=3)
        if len(mine) > 1:
            order = np.argsort(xs)
            ax.plot(np.asarray(xs)[order], np.asarray(ys)[order], color=_colour(method, k), lw=0.6, alpha=0.5)
        if annotate:
            for p, x, y in zip(mine, xs, ys):
                text = "any" if p["budget_ms"] is None else f"{p['budget_ms']:g}"
                ax.annotate(text, (x, y), xytext=(4, 3), textcoords="offset points", fontsize=7, color="0.25")


def _frame_axis(ax, xs) -> None:
    """Mean frame time on x: logarithmic when the points span more than 4× (budgets double), plain labels."""
    from matplotlib.ticker import ScalarFormatter

    xs = np.asarray(xs, float)
    xs = xs[np.isfinite(xs) & (xs > 0)]
    if xs.size and xs.max() > 4.0 * xs.min():
        ax.set_xscale("log")
        fmt = ScalarFormatter()
        fmt.set_scientific(False)
        ax.xaxis.set_major_formatter(fmt)
        ax.xaxis.set_minor_formatter(fmt)
        ax.set_xlabel("mean frame time (ms, log scale)")
    else:
        ax.set_xlabel("mean frame time (ms)")


def write_quality(results: dict, path: Path, psnr_path: Path | None = None) -> tuple[Path | None, Path | None]:
    """The chart of mean FLIP against mean frame time for every (method, budget), with the Pareto front
    as a step line and the target as a vertical line; optionally PSNR and SSIM against frame time too.

    Returns the paths written; None for a chart without data (no image quality was measured).
    """
    target = _target(results, None)
    points = [p for p in quality_points(results) if p["frame_mean_ms"] is not None]
    flip_pts = [p for p in points if p["flip_mean"] is not None]
    written: list[Path | None] = [None, None]
    plt = None
    if flip_pts:
        plt = _pyplot()
        fig, ax = plt.subplots(figsize=(8, 5.2), dpi=110)
        xy = np.array([[p["frame_mean_ms"], p["flip_mean"]] for p in flip_pts])
        front = xy[pareto(xy)]
        front = front[np.lexsort((front[:, 1], front[:, 0]))]
        ax.step(front[:, 0], front[:, 1], where="post", color="0.3", lw=1.0, ls="--", label="Pareto front", zorder=2)
        ax.axvline(target, color="tab:red", lw=1.0, ls=":", label=f"target {target:g} ms")
        _scatter_by_method(ax, flip_pts, "flip_mean")
        _frame_axis(ax, xy[:, 0])
        ax.set_ylabel("mean FLIP against full detail (lower is better)")
        ax.set_title(f"Image error against frame time — {results.get('scene', '')} (labels: budget, ms)", fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="best")
        fig.tight_layout()
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path)
        plt.close(fig)
        written[0] = path
    # PSNR of frames identical to full detail is infinite (or a cap as high as 100 dB): not drawn, named instead
    psnr = [(p, _finite(p["psnr_mean"])) for p in points if p["psnr_mean"] is not None]
    ps_pts = [p for p, v in psnr if v is not None and v < PSNR_CAP]
    exact = [_label(p) for p, v in psnr if (v is None and float(p["psnr_mean"]) > 0) or (v is not None and v >= PSNR_CAP)]
    ss_pts = [p for p in points if p["ssim_mean"] is not None]
    if psnr_path is not None and (ps_pts or ss_pts):
        plt = plt or _pyplot()
        fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.4), dpi=110)
        if exact:
            a1.text(0.01, 0.01, "not drawn, identical to full detail (PSNR ∞): " + ", ".join(exact),
                    transform=a1.transAxes, ha="left", va="bottom", fontsize=7, color="0.3")
        for ax, pts, key, label in ((a1, ps_pts, "psnr_mean", "mean PSNR (dB, higher is better)"),
                                    (a2, ss_pts, "ssim_mean", "mean SSIM (higher is better)")):
            if pts:
                _scatter_by_method(ax, pts, key)
            ax.axvline(target, color="tab:red", lw=1.0, ls=":")
            _frame_axis(ax, [p["frame_mean_ms"] for p in pts])
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
        a2.legend(fontsize=8, loc="best")
        fig.suptitle(f"PSNR and SSIM against frame time — {results.get('scene', '')}", fontsize=10)
        fig.tight_layout()
        psnr_path = Path(psnr_path)
        psnr_path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(psnr_path)
        plt.close(fig)
        written[1] = psnr_path
    return written[0], written[1]


# ----------------------------------------------------------------------------- text and HTML


def write_checks(results_checks: Sequence[dict], path: Path, *, title: str = "Done-when checks") -> Path:
    """The checks as a markdown list, one PASS / FAIL / SKIP line each."""
    lines = [f"# {title}", ""] + [f"- {c['line']}" for c in results_checks]
    path = Path(path)
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def _text_table(heads: list[str], rows: list[list[str]]) -> list[str]:
    widths = [max(len(h), *(len(r[k]) for r in rows)) if rows else len(h) for k, h in enumerate(heads)]
    fmt = lambda cells: "  ".join(c.ljust(w) if k == 0 else c.rjust(w) for k, (c, w) in enumerate(zip(cells, widths)))  # noqa: E731
    return [fmt(heads), fmt(["-" * w for w in widths])] + [fmt(r) for r in rows]


def summary_lines(results: dict) -> list[str]:
    """Table 1 as a plain-text table and the done-when checks: for the CLI and the README."""
    target = _target(results, None)
    rows = table1(results)
    lines = [f"Table 1 — {results.get('scene', '?')}, target {target:g} ms (times in ms)"]
    lines += _text_table(_headings(), [_cells(r) for r in rows]) if rows else ["(no runs at the target)"]
    lines += [""] + [c["line"] for c in checks(results)]
    return lines


def _jsonable(x: Any) -> Any:
    """Plain JSON: numpy scalars and arrays to Python, non-finite floats to null (strict JSON has no ∞)."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, Path):
        return str(x)
    return x


def _rel(src: str | Path, out: Path) -> str:
    """An image path as a link relative to the report folder (results give them relative already)."""
    p = Path(src)
    if p.is_absolute():
        try:
            p = p.resolve().relative_to(out.resolve())
        except ValueError:
            return p.as_uri()
    return p.as_posix()


def _exists(src: str | Path, out: Path) -> bool:
    p = Path(src)
    return (p if p.is_absolute() else out / p).is_file()


_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,sans-serif;margin:2em auto;max-width:1200px;padding:0 1em;color:#222}
table{border-collapse:collapse;margin:.5em 0 1.5em}th,td{border:1px solid #ccc;padding:.25em .6em}
td.num{text-align:right;font-variant-numeric:tabular-nums}th{background:#f3f3f3}
.pass{color:#17702a;font-weight:600}.fail{color:#b3261e;font-weight:600}.skip{color:#777;font-weight:600}
img.chart{max-width:100%;border:1px solid #ddd}
.grid{display:grid;grid-template-columns:repeat(auto-fill,minmax(260px,1fr));gap:.6em;margin-bottom:1.5em}
figure{margin:0}figure img{width:100%;border:1px solid #ddd}figcaption{font-size:.9em;text-align:center}
code{background:#f5f5f5;padding:0 .2em}
"""


def _status(passed: bool | None) -> str:
    word = _word(passed)
    return f'<span class="{word.lower()}">{word}</span>'


def write_index(results: dict, out: Path, *, rows: Sequence[dict], results_checks: Sequence[dict],
                charts: dict[str, Path | None], date: str | None = None) -> Path:
    """``index.html``: self-contained (inline CSS), relative links; every text goes through ``html.escape``."""
    out = Path(out)
    e = html.escape
    target = _target(results, None)
    scene = str(results.get("scene", ""))
    date = date or str(results.get("date") or _dt.datetime.now().isoformat(timespec="seconds"))
    title = f"walkstream evaluation — {scene}, target {target:g} ms, {date}"
    parts = [
        "<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{e(title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{e(title)}</h1>",
        '<p>Files: <a href="results.json">results.json</a> · <a href="table1.csv">table1.csv</a> · '
        '<a href="table1.md">table1.md</a> · <a href="checks.md">checks.md</a></p>',
        f"<h2>Table 1 at {target:g} ms</h2>",
        "<p>After Funkhouser &amp; Séquin (1993), Table 1: times in milliseconds over the frames after the warm-up; "
        "FLIP, PSNR and SSIM against the full-detail frame at the same camera; popping is the excess frame-to-frame "
        "change over the full-detail sequence.</p>",
    ]
    if rows:
        parts.append("<table><thead><tr>" + "".join(f"<th>{e(h)}</th>" for h in _headings()) + "</tr></thead><tbody>")
        for row in rows:
            cells = _cells(row)
            parts.append("<tr><td>" + e(cells[0]) + "</td>" + "".join(f'<td class="num">{e(c)}</td>' for c in cells[1:])
                         + "</tr>")
        parts.append("</tbody></table>")
    else:
        parts.append("<p>No runs at the target.</p>")

    parts.append("<h2>Done-when checks</h2><table><thead><tr><th>check</th><th>result</th><th>value</th>"
                 "<th>limit</th><th>figures</th></tr></thead><tbody>")
    for c in results_checks:
        parts.append(f"<tr><td><code>{e(str(c['name']))}</code></td><td>{_status(c['passed'])}</td>"
                     f'<td class="num">{e(_fmt(c.get("value"), 3))}</td><td class="num">{e(_fmt(c.get("limit"), 3))}</td>'
                     f"<td>{e(str(c['line']))}</td></tr>")
    parts.append("</tbody></table>")

    captions = {
        "traces": "Frame time per method at the target (F&amp;S Figure 7): shared axes; dashed = target, "
                  "dotted = 1.10 × target, dash-dot = viewpoints; the warm-up is shaded.",
        "quality": "Mean FLIP against mean frame time for every method and budget (labels: budget in ms; "
                   "“any” = budget-free); dashed step line = Pareto front; dotted = target.",
        "quality_psnr": "Mean PSNR and SSIM against mean frame time (higher is better).",
    }
    parts.append("<h2>Charts</h2>")
    for key, caption in captions.items():
        chart = charts.get(key)
        if chart is not None and Path(chart).is_file():
            src = e(_rel(chart, out), quote=True)
            parts.append(f'<figure><a href="{src}"><img class="chart" src="{src}" alt="{e(key)}"></a>'
                         f"<figcaption>{caption}</figcaption></figure><br>")
        elif key != "quality_psnr":
            parts.append(f"<p>No {e(key)} chart: nothing measured for it.</p>")

    images = results.get("images") or {}
    if images:
        parts.append("<h2>False-colour levels at the viewpoints</h2>"
                     "<p>Each object drawn in its level's colour; <em>full</em> is full detail.</p>")
        viewpoints = results.get("viewpoints") or {}
        for label, by_method in images.items():
            if not isinstance(by_method, dict):
                continue
            at = _finite(viewpoints.get(label))
            when = f" (t = {at:g} s)" if at is not None else ""
            parts.append(f"<h3>Viewpoint {e(str(label))}{e(when)}</h3><div class=\"grid\">")
            names = [m for m in ["full", *METHOD_ORDER] if m in by_method] + \
                    [m for m in by_method if m != "full" and m not in METHOD_ORDER]
            for method in names:
                src = by_method[method]
                if _exists(src, out):
                    link = e(_rel(src, out), quote=True)
                    parts.append(f'<figure><a href="{link}"><img src="{link}" alt="{e(str(label))} {e(method)}"></a>'
                                 f"<figcaption>{e(method)}</figcaption></figure>")
                else:
                    parts.append(f"<figure><p>missing: {e(str(src))}</p><figcaption>{e(method)}</figcaption></figure>")
            parts.append("</div>")

    scenarios = results.get("scenarios") or []
    if scenarios:
        parts.append("<h2>Scenarios where methods fail</h2><table><thead><tr><th>scenario</th><th>result</th>"
                     "<th>figures</th></tr></thead><tbody>")
        for sc in scenarios:
            name, title = str(sc.get("name", "")), str(sc.get("title") or "")
            parts.append(f"<tr><td><code>{e(name)}</code> {e(title)}</td><td>{_status(sc.get('passed'))}</td>"
                         f"<td>{e(str(sc.get('line', '')))}</td></tr>")
        parts.append("</tbody></table>")

    parts.append("<h2>Run settings</h2><table><tbody>")
    for key, value in _settings(results):
        parts.append(f"<tr><th>{e(key)}</th><td>{e(value)}</td></tr>")
    parts.append("</tbody></table></body></html>")
    path = out / "index.html"
    path.write_text("\n".join(parts) + "\n", encoding="utf-8")
    return path


_SETTINGS = ("scene", "store", "target_ms", "budgets_ms", "methods", "skipped", "viewport", "fov_y", "tau_s", "seed",
             "duration_s", "warmup_s", "viewpoints")


def _settings(results: dict) -> Iterable[tuple[str, str]]:
    """The run's settings, known keys first, then any other short top-level scalar the evaluation recorded."""
    shown = {"runs", "images", "scenarios", "date"}
    for key in _SETTINGS:
        if key in results:
            shown.add(key)
            value = results[key]
            yield key, value if isinstance(value, str) else json.dumps(_jsonable(value), ensure_ascii=False)
    for key, value in results.items():
        if key not in shown and (value is None or isinstance(value, (str, int, float, bool))) and len(str(value)) < 200:
            yield key, str(value)


def write_report(results: dict, out: Path, *, psnr_chart: bool = True, date: str | None = None) -> Path:
    """Write the report folder ``out`` from ``results`` and return the path of its ``index.html``.

    Files: ``results.json`` (strict JSON: non-finite figures as null), ``table1.csv``, ``table1.md``,
    ``traces.png``, ``quality.png`` (when image quality was measured), ``quality_psnr.png`` (optional),
    ``checks.md`` and ``index.html``. False-colour images are referenced from ``results["images"]``
    (paths relative to ``out``), not copied.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    target = _target(results, None)
    (out / "results.json").write_text(json.dumps(_jsonable(results), indent=1, allow_nan=False) + "\n",
                                      encoding="utf-8")
    rows = table1(results)
    write_table1(rows, out, title=f"Table 1 — {results.get('scene', '')}, target {target:g} ms (times in ms)")
    results_checks = checks(results)
    write_checks(results_checks, out / "checks.md",
                 title=f"Done-when checks — {results.get('scene', '')}, target {target:g} ms")
    traces = write_traces(results, out / "traces.png")
    quality, quality_psnr = write_quality(results, out / "quality.png", out / "quality_psnr.png" if psnr_chart else None)
    charts = {"traces": traces, "quality": quality, "quality_psnr": quality_psnr}
    return write_index(results, out, rows=rows, results_checks=results_checks, charts=charts, date=date)
