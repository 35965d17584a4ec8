"""The report folder: the checks as text, the summary lines, and ``index.html`` tying Table 1, the
charts, the false-colour images and the checks together with relative links; ``write_report`` writes it all.
"""

from __future__ import annotations

import datetime as _dt
import html
import json
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from bench.jsonable import jsonable
from bench.report.checks import checks, verdict_word
from bench.report.figures import write_quality, write_traces
from bench.report.results import METHOD_ORDER, finite, target_of
from bench.report.table import fmt_cell, row_cells, table1, table_headings, write_table1

__all__ = ["write_checks", "summary_lines", "write_index", "write_report"]


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
    target = target_of(results, None)
    rows = table1(results)
    lines = [f"Table 1 — {results.get('scene', '?')}, target {target:g} ms (times in ms)"]
    lines += _text_table(table_headings(), [row_cells(r) for r in rows]) if rows else ["(no runs at the target)"]
    lines += _setup_lines(results)
    lines += [""] + [c["line"] for c in checks(results)]
    return lines


def _setup_lines(results: dict) -> list[str]:
    """How the runs were made: the one rendering algorithm, the repeats, the cores, the calibration."""
    out = []
    if results.get("algorithms"):
        out.append(f"every method draws with the same rendering algorithm: {', '.join(results['algorithms'])}")
    if results.get("repeats"):
        out.append(f"{results['repeats']} repeat(s) of every run, interleaved; each row is the median repeat")
    cores = results.get("cores") or {}
    if cores:
        out.append(f"server on core(s) {cores.get('server')}, client on core(s) {cores.get('client')}")
    elif "cores" in results:
        out.append("server and client share the cores (fewer than 2, or pinning off)")
    calib = [c for r in results.get("runs") or [] for c in (r.get("calibration") or {}).get("ms") or []]
    if calib:
        q = np.percentile(calib, [5, 50, 95])
        out.append(f"calibration workload beside the runs: median {q[1]:.2f} ms, 5–95 % {q[0]:.2f}–{q[2]:.2f} ms "
                   f"({q[2] / q[1]:.2f} × the median at the 95th percentile)")
    return out


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
    word = verdict_word(passed)
    return f'<span class="{word.lower()}">{word}</span>'


def write_index(results: dict, out: Path, *, rows: Sequence[dict], results_checks: Sequence[dict],
                charts: dict[str, Path | None], date: str | None = None) -> Path:
    """``index.html``: self-contained (inline CSS), relative links; every text goes through ``html.escape``."""
    out = Path(out)
    e = html.escape
    target = target_of(results, None)
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
        heads = "".join(f"<th>{e(h)}</th>" for h in table_headings())
        parts.append("<table><thead><tr>" + heads + "</tr></thead><tbody>")
        for row in rows:
            cells = row_cells(row)
            parts.append("<tr><td>" + e(cells[0]) + "</td>" + "".join(f'<td class="num">{e(c)}</td>' for c in cells[1:])
                         + "</tr>")
        parts.append("</tbody></table>")
    else:
        parts.append("<p>No runs at the target.</p>")

    parts.append("<h2>Done-when checks</h2><table><thead><tr><th>check</th><th>result</th><th>value</th>"
                 "<th>limit</th><th>figures</th></tr></thead><tbody>")
    for c in results_checks:
        parts.append(f"<tr><td><code>{e(str(c['name']))}</code></td><td>{_status(c['passed'])}</td>"
                     f'<td class="num">{e(fmt_cell(c.get("value"), 3))}</td><td class="num">{e(fmt_cell(c.get("limit"), 3))}</td>'
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
            at = finite(viewpoints.get(label))
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
             "duration_s", "warmup_s", "viewpoints", "repeats", "governor", "algorithms", "cores")


def _settings(results: dict) -> Iterable[tuple[str, str]]:
    """The run's settings, known keys first, then any other short top-level scalar the evaluation recorded."""
    shown = {"runs", "images", "scenarios", "date"}
    for key in _SETTINGS:
        if key in results:
            shown.add(key)
            value = results[key]
            yield key, value if isinstance(value, str) else json.dumps(jsonable(value), ensure_ascii=False)
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
    target = target_of(results, None)
    (out / "results.json").write_text(json.dumps(jsonable(results), indent=1, allow_nan=False) + "\n",
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
