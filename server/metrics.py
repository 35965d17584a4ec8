"""Prometheus metrics of one app (one replica): a registry of its own, so two apps in one process never mix.

A replica of several worker processes (``server.workers``) runs prometheus_client's multiprocess mode
(``PROMETHEUS_MULTIPROC_DIR``, set for the workers): every worker's counters and histograms live in files
of one folder and any worker's ``/metrics`` is their sum. There the per-process collector would show one
worker only, so ``walkstream_cpu_seconds`` carries the CPU time of all of them (those that ended included,
up to their last refresh), each worker refreshing its own every half second.

``walkstream_selection_seconds`` is the load test's "selection latency": the
wall time from when a selection was due (the deadline the session loop waited
for) until its delta was handed to the socket — queueing for a worker,
solving, encoding and the send together.
"""

from __future__ import annotations

import asyncio
import os
import time
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

__all__ = ["Metrics", "LATENCY_BUCKETS", "CONTENT_TYPE_LATEST"]

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

    def tick(self, polls: int) -> None:
        """A batch of ``polls`` ran (``server.ticker``)."""
        self.ticks.inc()
        self.tick_polls.inc(polls)

    def refresh(self) -> None:
        """Write this worker's own figures where the others' sum reads them (multiprocess mode only)."""
        if self.folder is not None:
            self.sessions.set(self._count())
            self.cpu.set(time.process_time())

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
        return generate_latest(merged)
