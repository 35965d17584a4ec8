"""Funkhouser & Séquin's Table 1 from the results: one row per method at the target, written as CSV
(full precision) and markdown (the columns' decimals).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from bench.report.results import finite, label, method_order, repeats_at, run_at, target_of

__all__ = ["COLUMNS", "table1", "fmt_cell", "table_headings", "row_cells", "write_table1"]


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
    ("frame_mean_spread_ms", "spread of mean (repeats)", 1),
    ("repeats", "repeats", 0),
    ("calibration_median_ms", "calibration", 2),
)


def table1(results: dict, target_ms: float | None = None) -> list[dict]:
    """One row per method at ``target_ms`` (default the headline target), in F&S Table 1's order, a
    budget-dependent method's run with the client's frame governor after it (``method+gov``).

    Each row: ``method`` plus every key of :data:`COLUMNS`, copied from the median repeat's summary
    (``results.run_at``; times in ms), with the spread (max − min) of the repeats' mean frame times and
    their count; a figure the run did not measure (no image quality, say) is None. Methods without a run
    at the target are left out.
    """
    target = target_of(results, target_ms)
    rows = []
    for method, governor in [(m, g) for m in method_order(results) for g in (False, True)]:
        run = run_at(results, method, target, governor)
        if run is None:
            continue
        means = [finite((r.get("summary") or {}).get("frame_mean_ms"))
                 for r in repeats_at(results, method, target, governor)]
        means = [v for v in means if v is not None]
        summary = run.get("summary") or {}
        if any(key not in summary for key, _, _ in COLUMNS) and (run.get("frames") or {}).get("t"):
            # Figures added to the summary since the run (p99, over 1.1 × target) come from its frames.
            from bench.evaluate import summarize_frames

            summary = {**summarize_frames(run["frames"], float(results.get("warmup_s") or 0.0),
                                          float(run.get("target_ms") or target)), **summary}
        summary = {**summary, "repeats": len(means),
                   "frame_mean_spread_ms": (max(means) - min(means)) if means else None}
        row: dict[str, Any] = {"method": label(method, governor)}
        for key, _, _ in COLUMNS:
            value = summary.get(key)
            row[key] = value if key in ("frames", "repeats") or value is None else float(value)
        for key in ("frames", "repeats"):
            if row[key] is not None:
                row[key] = int(row[key])
        rows.append(row)
    return rows


def fmt_cell(value: Any, decimals: int) -> str:
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


def table_headings() -> list[str]:
    return ["method"] + [f"{label} (ms)" if key.endswith("_ms") else label for key, label, _ in COLUMNS]


def row_cells(row: dict) -> list[str]:
    return [str(row["method"])] + [fmt_cell(row.get(key), dec) for key, _, dec in COLUMNS]


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
    heads = table_headings()
    lines = [f"# {title}", ""] if title else []
    lines += ["| " + " | ".join(heads) + " |", "|" + "|".join(["---"] + ["---:"] * (len(heads) - 1)) + "|"]
    lines += ["| " + " | ".join(row_cells(row)) + " |" for row in rows]
    lines += ["", "Times in milliseconds; frame figures over the frames after the warm-up. FLIP: mean LDR-FLIP "
              "against the full-detail frame (lower is better); popping: excess frame-to-frame change over "
              "the full-detail sequence (lower is better). Each row is the median of its repeats by mean frame time; "
              "spread: max − min of the repeats' means; calibration: the median time of the fixed workload timed "
              "every second beside the run; +gov: with the client's frame governor."]
    md_path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return csv_path, md_path
