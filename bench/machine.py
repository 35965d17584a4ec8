"""Telling the method from the machine: cores apart for server and client, and a calibration workload.

On a shared machine the same work takes a different time from one second to the next. The evaluation
pins the server and the client to different cores (``split_cores``, when there are at least two), and
beside each run a ``Calibration`` thread times a small fixed workload once a second: a run whose
calibration is slow ran on a slow machine, whatever its method. The workload is numpy sorting (single
threaded, and it releases the GIL), so it does not hold up the client's frames. ``frame_noise`` measures the
machine from a run's own frames: how far apart consecutive frames of the same work fall.
"""

from __future__ import annotations

import os
import threading
import time

import numpy as np

__all__ = ["split_cores", "calibration_workload", "Calibration", "frame_noise"]

#: Values the workload sorts, and how many times.
_VALUES, _ROUNDS = 100_000, 4


def split_cores(server_pid: int) -> dict:
    """Pin ``server_pid`` (every thread of it) to the first core this process may use, and the calling thread
    (so the threads it starts later: the client's renderer) to the others.

    Returns {"server": [cores], "client": [cores]}, or {} when fewer than two cores are available or the
    platform has no ``sched_setaffinity`` (nothing is pinned then).
    """
    if not hasattr(os, "sched_setaffinity"):
        return {}
    cores = sorted(os.sched_getaffinity(0))
    if len(cores) < 2:
        return {}
    server, client = cores[:1], cores[1:]
    try:
        for tid in _threads(server_pid):  # a running server has threads already: each has its own mask
            os.sched_setaffinity(tid, server)
        os.sched_setaffinity(0, client)  # this thread; the client's renderer and its threads start after
    except OSError:
        return {}
    return {"server": server, "client": client}


def _threads(pid: int) -> list[int]:
    """The thread ids of process ``pid`` (Linux ``/proc``), or just ``pid`` where they cannot be listed."""
    try:
        return sorted(int(t) for t in os.listdir(f"/proc/{pid}/task"))
    except OSError:
        return [pid]


def calibration_workload(rng_seed: int = 0) -> float:
    """Seconds one fixed workload takes now (a few ms on an idle core)."""
    a = np.random.default_rng(rng_seed).standard_normal(_VALUES)
    t0 = time.perf_counter()
    for _ in range(_ROUNDS):
        b = np.sort(a)
    t1 = time.perf_counter()
    if not b[0] <= b[-1]:  # keeps the work from being optimised away, and says if it went wrong
        raise ArithmeticError("calibration workload did not sort")
    return t1 - t0


class Calibration:
    """A daemon thread timing ``calibration_workload`` every ``period`` s while a run lasts (a context manager),
    on ``cores`` when given (None: wherever the calling thread may run).

    ``samples()`` gives {"t": [s since start], "ms": [workload time]}.
    """

    def __init__(self, period: float = 1.0, cores: "list[int] | None" = None) -> None:
        if not period > 0:
            raise ValueError(f"period must be positive, got {period!r}")
        self.period = float(period)
        self.cores = None if not cores else [int(c) for c in cores]
        self._t: list[float] = []
        self._ms: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="calibration", daemon=True)

    def _loop(self) -> None:
        if self.cores is not None and hasattr(os, "sched_setaffinity"):
            # Beside the server, not the client: on the client's core the workload would take its frames'
            # time and measure their contention instead of the machine.
            try:
                os.sched_setaffinity(0, self.cores)
            except OSError:
                pass
        start = time.perf_counter()
        while True:
            at = time.perf_counter() - start
            self._ms.append(1e3 * calibration_workload())
            self._t.append(at)
            if self._stop.wait(self.period):
                return

    def __enter__(self) -> "Calibration":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()

    def samples(self) -> dict:
        n = min(len(self._t), len(self._ms))
        return {"t": [float(v) for v in self._t[:n]], "ms": [float(v) for v in self._ms[:n]]}


def frame_noise(t: np.ndarray, time_s: np.ndarray, work: np.ndarray, warmup: float = 2.0,
                within: float = 0.01, least: float = 0.0) -> dict:
    """The scatter of identical work: the time ratio of consecutive frames (after ``warmup`` s, both taking at
    least ``least`` s) whose work (vertices or triangles drawn) agrees within ``within``, as quantiles (None
    without such pairs). No cost model predicts it, so a governor holding a tail has to leave room for it. A
    frame of a few milliseconds scatters far more, relatively, than one near the target: ``least`` keeps the
    frames the budget is about. ``frame_sd``: one frame's relative scatter (the log ratios' std ÷ √2)."""
    t, y, v = (np.asarray(a, np.float64) for a in (t, time_s, work))
    pair = ((t[1:] >= warmup) & (v[:-1] > 0) & (y[:-1] > 0) & (np.minimum(y[1:], y[:-1]) >= least)
            & (np.abs(v[1:] / np.maximum(v[:-1], 1.0) - 1) <= within))
    r = y[1:][pair] / y[:-1][pair]
    q = (lambda k: round(float(np.percentile(r, k)), 3) if r.size else None)  # noqa: E731
    # Two frames of the same work differ by the scatter of both: one frame's is 1/√2 of their log ratio's.
    sd = float(np.std(np.log(r)) / np.sqrt(2.0)) if r.size >= 2 else None
    return {"pairs": int(r.size), "p50": q(50), "p95": q(95), "p99": q(99), "frame_sd": sd}
