"""The report's charts (matplotlib, headless): Figure 7 (frame time over the tour, one panel per method
on the same axes) and image error against mean frame time with the Pareto front.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bench.report.checks import MAX_RATIO_LIMIT, pareto, point_label, quality_points
from bench.report.results import finite, label, method_order, run_at, target_of
from bench.report.table import fmt_cell

__all__ = ["PSNR_CAP", "write_traces", "write_quality"]


#: PSNR at or above this (dB) means frames identical to full detail (bench.quality may cap ∞ here).
PSNR_CAP = 100.0


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
    vertical lines; a governed panel also draws the governor's aim (the frame time it steered to). The y axis
    stops at 4 × target so the budgeted methods stay readable; a panel whose frames go higher says so (its max
    after the warm-up is in its label). None when no run at the target has frames.
    """
    target = target_of(results, target_ms)
    series = []
    calibration = []
    for method, governor in [(m, g) for m in method_order(results) for g in (False, True)]:
        run = run_at(results, method, target, governor)
        frames = (run or {}).get("frames") or {}
        t, ms = np.asarray(frames.get("t") or [], float), np.asarray(frames.get("time_ms") or [], float)
        if t.size and t.size == ms.size:
            aim = np.asarray(frames.get("governor_aim") or [], float) * target
            aim = aim if aim.size == t.size and (aim > 0).any() else None
            series.append((label(method, governor), t, ms, (run.get("summary") or {}), aim))
            c = run.get("calibration") or {}
            if c.get("t") and len(c["t"]) == len(c.get("ms") or []):
                calibration.append((label(method, governor), np.asarray(c["t"], float), np.asarray(c["ms"], float)))
    if not series:
        return None
    plt = _pyplot()
    peak = max(float(np.nanmax(ms)) for _, _, ms, _, _ in series)
    top = max(1.5 * target, min(1.05 * peak, 4.0 * target))
    panels = len(series) + (1 if calibration else 0)
    fig, axes = plt.subplots(panels, 1, sharex=True, figsize=(10, 1.25 + 1.45 * panels), dpi=110, squeeze=False)
    warm = finite(results.get("warmup_s")) or 0.0
    viewpoints = {k: v for k, v in (results.get("viewpoints") or {}).items() if finite(v) is not None}
    for k, (ax, (method, t, ms, summary, aim)) in enumerate(zip(axes[:, 0], series)):
        if warm > 0:
            ax.axvspan(0, warm, color="0.93", lw=0)
        for name, at in viewpoints.items():
            ax.axvline(float(at), color="0.35", lw=0.8, ls="-.")
            if k == 0:
                ax.text(float(at), 1.02, str(name), transform=ax.get_xaxis_transform(), ha="center", va="bottom",
                        fontsize=8)
        ax.plot(t, ms, lw=0.8, color=_colour(method, k))
        if aim is not None:  # what the governor steered to: where it sits below the target, the frames scattered
            ax.plot(t, np.where(aim > 0, aim, np.nan), lw=0.9, color="black", alpha=0.75, label="governor's aim")
            ax.legend(fontsize=6, loc="upper right")
        ax.axhline(target, color="tab:red", ls="--", lw=1.0)
        ax.axhline(MAX_RATIO_LIMIT * target, color="tab:red", ls=":", lw=0.8)
        stats = ", ".join(
            f"{label} {fmt_cell(summary.get(key), 1)}" for key, label in
            (("frame_mean_ms", "mean"), ("frame_std_ms", "std"), ("frame_max_ms", "max"))
        )
        clipped = f"; frames above {top:.0f} ms clipped" if float(np.nanmax(ms)) > top else ""
        ax.text(0.005, 0.95, f"{method} — {stats} ms{clipped}", transform=ax.transAxes, ha="left", va="top",
                fontsize=8, bbox=dict(boxstyle="round,pad=0.2", fc="white", ec="0.8", alpha=0.85))
        ax.grid(alpha=0.3)
        ax.set_ylabel("ms")
    for ax in axes[:len(series), 0]:
        ax.set_ylim(0, top)
    if calibration:
        ax = axes[-1, 0]
        for k, (name, t, ms) in enumerate(calibration):
            ax.plot(t, ms, lw=0.8, marker=".", ms=3, color=_colour(name.split("+")[0], k), label=name,
                    ls="--" if name.endswith("+gov") else "-")
        ax.set_yscale("log")
        ax.set_ylabel("calib. ms")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6, ncol=4, loc="upper right")
        ax.text(0.005, 0.95, "calibration workload beside each run (the machine's speed; lower is faster)",
                transform=ax.transAxes, ha="left", va="top", fontsize=8,
                bbox=dict(boxstyle="round,pad=0.2", fc="white", ec="0.8", alpha=0.85))
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
    target = target_of(results, None)
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
    psnr = [(p, finite(p["psnr_mean"])) for p in points if p["psnr_mean"] is not None]
    ps_pts = [p for p, v in psnr if v is not None and v < PSNR_CAP]
    exact = [point_label(p) for p, v in psnr if (v is None and float(p["psnr_mean"]) > 0) or (v is not None and v >= PSNR_CAP)]
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
