"""Prometheus metrics of one app (one replica): a registry of its own, so two apps in one process never mix.

A replica of several worker processes (``server.workers``) runs prometheus_client's multiprocess mode
(``PROMETHEUS_MULTIPROC_DIR``, set for the workers): every worker's counters and histograms live in files
of one folder and any worker's ``/metrics`` is their sum. There the per-process collector would show one
worker only, so ``walkstream_cpu_seconds`` carries the CPU time of all of them (those that ended included,
up to their last refresh), each worker refreshing its own every half second.

Per-kiosk gauges (``walkstream_kiosk_*``, labelled ``kiosk``) are read from the fleet (``server.fleet``)
at each scrape by a collector of their own, so a kiosk the fleet forgets leaves no series behind and the
label's values are bounded by the fleet's own bounds. prometheus_client's files cannot forget a label
set, so with several workers each one writes its fleet's rows to ``fleet-<pid>.json`` in the same folder
at every refresh, and any worker's ``/metrics`` merges those of the live workers (``server.fleet.merge``).

``walkstream_selection_seconds`` is the load test's "selection latency": the
wall time from when a selection was due (the deadline the session loop waited
for) until its delta was handed to the socket — queueing for a worker,
solving, encoding and the send together.
"""

from __future__ import annotations

import asyncio
import json
import os
import time
from pathlib import Path
from typing import Callable

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    ProcessCollector,
    generate_latest,
)
from prometheus_client.core import GaugeMetricFamily

from .fleet import merge

__all__ = ["Metrics", "FleetCollector", "LATENCY_BUCKETS", "CONTENT_TYPE_LATEST"]

#: 1 ms to 2 s, dense between 5 and 200 ms where the p99 goal (100 ms) lives.
LATENCY_BUCKETS = (
    0.001, 0.0025, 0.005, 0.0075, 0.01, 0.0125, 0.015, 0.02, 0.025, 0.03, 0.04, 0.05, 0.06, 0.075,
    0.1, 0.125, 0.15, 0.175, 0.2, 0.3, 0.5, 1.0, 2.0,
)


class Metrics:
    """The replica's counters; ``render()`` is the ``/metrics`` body."""

    def __init__(self, sessions: Callable[[], float]) -> None:
        self.registry = CollectorRegistry()
        self.folder = os.environ.get("PROMETHEUS_MULTIPROC_DIR")  # several workers: one sum of them all
        self._count = sessions
        r = self.registry
        if self.folder is None:
            ProcessCollector(registry=r)  # process_cpu_seconds_total, memory, fds
        self.sessions = Gauge("walkstream_sessions", "websocket sessions open on this replica", registry=r,
                              multiprocess_mode="livesum")
        self.cpu = Gauge("walkstream_cpu_seconds", "CPU seconds of the replica's server processes (all workers)",
                         registry=r, multiprocess_mode="sum")
        if self.folder is None:
            self.sessions.set_function(sessions)
            self.cpu.set_function(time.process_time)
        self.selection_seconds = Histogram(
            "walkstream_selection_seconds",
            "wall time from a selection's due time until its delta was handed to the socket",
            buckets=LATENCY_BUCKETS, registry=r,
        )
        self.selection_cpu_seconds = Histogram(
            "walkstream_selection_cpu_seconds", "worker thread CPU time of one poll that produced a delta",
            buckets=LATENCY_BUCKETS, registry=r,
        )
        self.ticks = Counter("walkstream_ticks", "batches of due polls run together (one shared culling pass each)",
                             registry=r)
        self.tick_polls = Counter("walkstream_tick_polls", "polls run in those batches", registry=r)
        self.bytes_out = Counter("walkstream_bytes_out", "websocket payload bytes sent to clients", registry=r)
        self.messages_in = Counter("walkstream_messages_in", "websocket frames received from clients", registry=r)
        self.errors = Counter("walkstream_errors", "error frames sent, by code", ["code"], registry=r)
        self.refused = Counter(
            "walkstream_refused",
            "refusals: busy (connection past max_sessions), rate (a dropped message), abuse (closed for "
            "flooding), idle (closed for silence)",
            ["reason"], registry=r,
        )
        self.resumes = Counter(
            "walkstream_resumes",
            "hellos by outcome: fresh (no resume asked), resumed, bad_token, not_found, corrupt",
            ["outcome"], registry=r,
        )
        self.state_failures = Counter(
            "walkstream_state_failures", "session-state saves or loads that failed", ["op"], registry=r,
        )
        self.heartbeats = Counter("walkstream_heartbeats", "kiosk heartbeats received", registry=r)
        self._fleet: Callable[[], list[dict]] = list

    def watch_fleet(self, rows: Callable[[], list[dict]]) -> None:
        """Serve per-kiosk gauges of ``rows()`` (``Fleet.rows`` at the scrape's time)."""
        self._fleet = rows
        if self.folder is None:
            self.registry.register(FleetCollector(rows))

    def _fleet_file(self, pid: int) -> Path:
        return Path(self.folder) / f"fleet-{pid}.json"

    def _write_fleet(self) -> None:
        """This worker's fleet rows where the other workers' ``render`` reads them (atomically)."""
        rows, path = self._fleet(), self._fleet_file(os.getpid())
        if not rows and not path.exists():
            return
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps({"kiosks": rows}))
        tmp.replace(path)

    def _replica_fleet(self) -> list[dict]:
        """The kiosks of every live worker: this one's now, the others' as of their last refresh."""
        parts = [{"kiosks": self._fleet()}]
        for path in Path(self.folder).glob("fleet-*.json"):
            try:
                pid = int(path.stem.split("-", 1)[1])
                if pid == os.getpid() or not _alive(pid):
                    continue
                parts.append(json.loads(path.read_text()))
            except (OSError, ValueError):
                continue  # a worker that ended meanwhile, or a name not ours
        return merge(parts)["kiosks"]

    def close(self) -> None:
        """This worker's fleet file removed: its kiosks are no longer this worker's to report."""
        if self.folder is not None:
            self._fleet_file(os.getpid()).unlink(missing_ok=True)

    def tick(self, polls: int) -> None:
        """A batch of ``polls`` ran (``server.ticker``)."""
        self.ticks.inc()
        self.tick_polls.inc(polls)

    def refresh(self) -> None:
        """Write this worker's own figures where the others' sum reads them (multiprocess mode only)."""
        if self.folder is not None:
            self.sessions.set(self._count())
            self.cpu.set(time.process_time())
            try:
                self._write_fleet()
            except OSError:
                pass  # the run folder is gone: the replica is stopping

    async def keep_fresh(self, every: float = 0.5) -> None:
        """``refresh`` every ``every`` seconds, for the scrapes other workers answer."""
        if self.folder is None:
            return
        while True:
            self.refresh()
            await asyncio.sleep(every)

    def render(self) -> bytes:
        if self.folder is None:
            return generate_latest(self.registry)
        from prometheus_client import multiprocess

        self.refresh()
        merged = CollectorRegistry()
        multiprocess.MultiProcessCollector(merged, path=self.folder)
        FleetCollector(self._replica_fleet, registry=merged)
        return generate_latest(merged)


class FleetCollector:
    """Per-kiosk gauges from ``rows()`` (``server.fleet`` rows) at each scrape; the series a row lacks end."""

    #: (row key, metric name, help); a row's None (GPU memory the driver does not tell) gives no sample.
    FIGURES = (
        ("fps", "walkstream_kiosk_fps", "frames per second the kiosk drew, at its last heartbeat"),
        ("frame_p95", "walkstream_kiosk_frame_p95_seconds", "95th percentile of the kiosk's recent frame times"),
        ("rss", "walkstream_kiosk_rss_bytes", "resident memory of the kiosk's process"),
        ("gpu_memory", "walkstream_kiosk_gpu_memory_bytes", "GPU memory the kiosk uses, where its driver tells"),
        ("cache_bytes", "walkstream_kiosk_cache_bytes", "bytes in the kiosk's representation cache"),
        ("reconnects", "walkstream_kiosk_reconnects", "times the kiosk dialled the server again since it started"),
        ("frames", "walkstream_kiosk_frames", "frames the kiosk drew since it started"),
        ("stale", "walkstream_kiosk_stale", "1 when the kiosk's frames have not advanced for 2 heartbeat intervals"),
        ("connected", "walkstream_kiosk_connected", "1 while a session of the kiosk is live"),
        ("heard_s", "walkstream_kiosk_heard_age_seconds", "seconds since the kiosk's last heartbeat"),
    )

    def __init__(self, rows: Callable[[], list[dict]], registry: CollectorRegistry | None = None) -> None:
        self.rows = rows
        if registry is not None:
            registry.register(self)

    def describe(self):
        return [GaugeMetricFamily(name, doc, labels=["kiosk"]) for _, name, doc in self.FIGURES]

    def collect(self):
        rows = self.rows()
        for key, name, doc in self.FIGURES:
            family = GaugeMetricFamily(name, doc, labels=["kiosk"])
            for row in rows:
                if row.get(key) is not None:
                    family.add_metric([row["kiosk"]], float(row[key]))
            yield family


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
