"""The server's side of the load test: its ``/metrics`` (Prometheus text) read into a ``Scrape``,
histogram quantiles over a window between two scrapes, and a process's CPU seconds from ``/proc``.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["Scrape", "parse_metrics", "merge", "histogram_quantile", "hist_delta", "quantiles_ms", "proc_cpu", "tree_cpu"]


# --------------------------------------------------------------------------- the server's /metrics


@dataclass
class Scrape:
    """One reading of ``/metrics`` at monotonic time ``at``.

    hist : histogram name → (le (b,) float64 with +inf last, cumulative counts (b,) float64), summed over labels
    values : sample name (counters with ``_total``) → value, summed over labels
    errors : ``walkstream_errors_total`` by ``code``
    """

    at: float
    hist: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    values: dict[str, float] = field(default_factory=dict)
    errors: dict[str, float] = field(default_factory=dict)


def parse_metrics(text: str, at: float = 0.0) -> Scrape:
    """Prometheus text → ``Scrape`` (prometheus_client's parser)."""
    from prometheus_client.parser import text_string_to_metric_families

    out = Scrape(at=at)
    buckets: dict[str, dict[float, float]] = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            if family.type == "histogram" and s.name.endswith("_bucket"):
                le = float(s.labels["le"])
                b = buckets.setdefault(s.name[: -len("_bucket")], {})
                b[le] = b.get(le, 0.0) + float(s.value)
                continue
            out.values[s.name] = out.values.get(s.name, 0.0) + float(s.value)
            if s.name == "walkstream_errors_total" and "code" in s.labels:
                out.errors[s.labels["code"]] = out.errors.get(s.labels["code"], 0.0) + float(s.value)
    for name, b in buckets.items():
        le = np.array(sorted(b), np.float64)
        out.hist[name] = (le, np.array([b[x] for x in le], np.float64))
    return out


def merge(scrapes: list[Scrape]) -> Scrape:
    """Several servers' scrapes as one (replicas behind a load balancer): samples and histograms summed."""
    out = Scrape(at=max(s.at for s in scrapes))
    for s in scrapes:
        for k, v in s.values.items():
            out.values[k] = out.values.get(k, 0.0) + v
        for k, v in s.errors.items():
            out.errors[k] = out.errors.get(k, 0.0) + v
        for name, (le, cum) in s.hist.items():
            held = out.hist.get(name)
            out.hist[name] = (le, cum.copy()) if held is None else (le, held[1] + cum)
    return out


def histogram_quantile(le: np.ndarray, cumulative: np.ndarray, q: float) -> float:
    """The q-quantile of a cumulative histogram by linear interpolation within its bucket (Prometheus' rule).

    Returns NaN for an empty histogram, and the largest finite bound when the
    quantile falls in the +Inf bucket.
    """
    le = np.asarray(le, np.float64)
    cum = np.asarray(cumulative, np.float64)
    if cum.size == 0 or cum[-1] <= 0:
        return math.nan
    rank = q * cum[-1]
    i = int(np.searchsorted(cum, rank, side="left"))
    i = min(i, cum.size - 1)
    if math.isinf(le[i]):
        finite = le[np.isfinite(le)]
        return float(finite[-1]) if finite.size else math.nan
    lo = le[i - 1] if i > 0 else 0.0
    c_lo = cum[i - 1] if i > 0 else 0.0
    if cum[i] <= c_lo:
        return float(le[i])
    return float(lo + (le[i] - lo) * (rank - c_lo) / (cum[i] - c_lo))


def hist_delta(a: Scrape | None, b: Scrape, name: str) -> tuple[np.ndarray, np.ndarray] | None:
    """The histogram's observations between two scrapes (b − a), or None when the server lacks it."""
    hb = b.hist.get(name)
    if hb is None:
        return None
    ha = a.hist.get(name) if a is not None else None
    if ha is None or ha[0].shape != hb[0].shape or not np.array_equal(ha[0], hb[0]):
        return hb
    return hb[0], np.maximum(hb[1] - ha[1], 0.0)


def quantiles_ms(a: Scrape | None, b: Scrape, name: str) -> tuple[float | None, float | None, int]:
    h = hist_delta(a, b, name)
    if h is None or h[1][-1] <= 0:
        return None, None, 0
    return (histogram_quantile(*h, 0.5) * 1e3, histogram_quantile(*h, 0.99) * 1e3, int(h[1][-1]))


def _stat(pid: int) -> list[str] | None:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None


def proc_cpu(pid: int) -> float | None:
    """utime + stime of a local process (s): the fallback when /metrics has no process collector."""
    fields = _stat(pid)
    try:
        return None if fields is None else (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (IndexError, ValueError):
        return None


def tree_cpu(pid: int) -> float | None:
    """CPU seconds of a local process and every process below it — a replica's supervisor and its workers —
    including the children it has reaped (a worker that was killed and replaced)."""
    parent: dict[int, int] = {}
    stats: dict[int, list[str]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit() and (fields := _stat(int(entry.name))) is not None:
            stats[int(entry.name)] = fields
            parent[int(entry.name)] = int(fields[1])
    if pid not in stats:
        return None
    tick = os.sysconf("SC_CLK_TCK")
    total, todo = 0.0, [pid]
    while todo:
        p = todo.pop()
        f = stats[p]
        own = (int(f[11]) + int(f[12])) / tick
        total += max(own, _runtime(p)) + (int(f[13]) + int(f[14])) / tick  # own, and the children it waited for
        todo += [c for c, up in parent.items() if up == p]
    return total


def _runtime(pid: int) -> float:
    """Seconds on a CPU of a process's live threads, from the scheduler's nanosecond clock (0 without it).

    /proc's utime and stime count whole clock ticks, coarser than what a lightly loaded server spends over a
    short window (a short reference read 0 from them). The ticks still bound it below, for threads that have
    exited."""
    total = 0
    try:
        for task in Path(f"/proc/{pid}/task").iterdir():
            try:
                total += int((task / "schedstat").read_text().split()[0])
            except (OSError, IndexError, ValueError):
                continue
    except OSError:
        return 0.0
    return total / 1e9
