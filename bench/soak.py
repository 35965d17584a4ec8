"""``walkstream bench soak``: a kiosk left alone all day, compressed — does anything grow, stick or go dark?

A headless kiosk (``walkstream kiosk --headless`` in a child process) plays its
attract loop with synthetic visitors (random touches and walks) against a real
server through ``bench.netem.DelayProxy``. The network is cut every
``cut_every`` seconds for ``cut_for`` seconds and the server is killed and
started again once. Every ``sample_every`` seconds the soak samples the kiosk
process (RSS, threads, open sockets from ``/proc``) and the kiosk's status file
(frames, deltas, cache bytes, GPU memory, camera position), and after every
return of the network it watches, finely, for the first delta.

Pass lines (``judge``):

- RSS at the end ≤ 1.05 × RSS at minute 2 (runs shorter than 6 minutes take a third
  of the run instead of minute 2, so the reference is past the warm-up either way);
- sockets and threads back to their baseline (the last sample before the cut) by the
  last sample before the next event;
- frames advance in every sampling window;
- after every cut (and the restart), deltas flow again within 5 s of the network's return;
- the camera never leaves the kiosk's bounds.

The schedule and the judgement are pure (``SoakPlan``, ``judge``); ``run`` does the I/O.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

__all__ = ["SoakPlan", "Sample", "judge", "run", "RSS_GROWTH", "RECOVERY_S", "process_sample"]

#: RSS at the end may be at most this many times RSS at the reference sample.
RSS_GROWTH = 1.05
#: Deltas must flow again within this many seconds of the network's return.
RECOVERY_S = 5.0
#: The reference sample for RSS: minute 2, or a third of a shorter run.
RSS_REFERENCE_S = 120.0


@dataclass(frozen=True)
class SoakPlan:
    """When the network is cut and restored and when the server restarts, in seconds from the start.

    Cuts start at ``cut_every``, ``2·cut_every``, … while a cut still ends ``cut_for`` before the run
    does; the restart falls at ``restart_at`` (default: half-way between two cuts in the middle of the
    run), never inside a cut.
    """

    duration: float = 3600.0
    cut_every: float = 300.0
    cut_for: float = 60.0
    restart_at: float | None = None
    sample_every: float = 10.0

    def __post_init__(self) -> None:
        for name in ("duration", "cut_every", "cut_for", "sample_every"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number of seconds, got {v!r}")
        if self.cut_for >= self.cut_every:
            raise ValueError(f"cut_for ({self.cut_for} s) must be shorter than cut_every ({self.cut_every} s)")
        if self.duration < 2 * self.sample_every:
            raise ValueError(f"duration ({self.duration} s) must cover at least two samples of {self.sample_every} s")
        r = self.restart
        if r is not None and not 0 < r < self.duration:
            raise ValueError(f"restart_at must fall inside the run (0, {self.duration}), got {r}")
        if r is not None and any(a <= r < b + RECOVERY_S for a, b in self.cuts):
            raise ValueError(f"restart_at ({r} s) falls inside a network cut or its recovery")

    @classmethod
    def scaled(cls, duration: float, sample_every: float = 10.0) -> "SoakPlan":
        """The hour's schedule (cut every 5 min for 60 s) for long runs; a short run gets three cuts' worth."""
        if duration >= 900:
            return cls(duration=duration, sample_every=sample_every)
        every = duration / 3.0
        return cls(duration=duration, cut_every=every, cut_for=min(60.0, every / 4.0), sample_every=sample_every)

    @property
    def cuts(self) -> list[tuple[float, float]]:
        """(cut, restore) times."""
        out, k = [], 1
        while k * self.cut_every + self.cut_for <= self.duration - self.sample_every:
            out.append((k * self.cut_every, k * self.cut_every + self.cut_for))
            k += 1
        return out

    @property
    def restart(self) -> float | None:
        """When the server is restarted (None: the run is too short to fit one outside the cuts)."""
        if self.restart_at is not None:
            return self.restart_at
        cuts = self.cuts
        if len(cuts) >= 2:
            mid = len(cuts) // 2
            return (cuts[mid - 1][1] + cuts[mid][0]) / 2.0
        t = (cuts[0][1] + self.duration) / 2.0 if cuts else self.duration / 2.0
        return t if t < self.duration - self.sample_every else None

    def events(self) -> list[tuple[float, str]]:
        """(time, "cut" | "restore" | "restart"), in time order."""
        ev = [(a, "cut") for a, _ in self.cuts] + [(b, "restore") for _, b in self.cuts]
        if self.restart is not None:
            ev.append((self.restart, "restart"))
        return sorted(ev)


@dataclass
class Sample:
    """One sample of the kiosk: process figures from ``/proc`` and the kiosk's own status."""

    t: float
    rss: int
    threads: int
    sockets: int
    frames: int
    deltas: int
    cache_bytes: int
    gpu_memory: int | None
    state: str


def process_sample(pid: int) -> tuple[int, int, int]:
    """(RSS bytes, threads, open sockets) of a live process, from ``/proc``."""
    rss = threads = 0
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                rss = int(line.split()[1]) * 1024
            elif line.startswith("Threads:"):
                threads = int(line.split()[1])
    sockets = 0
    fd_dir = f"/proc/{pid}/fd"
    for name in os.listdir(fd_dir):
        try:
            sockets += os.readlink(f"{fd_dir}/{name}").startswith("socket:")
        except OSError:  # closed between listdir and readlink
            pass
    return rss, threads, sockets


def judge(plan: SoakPlan, samples: Sequence[Sample], recoveries: Sequence[tuple[float, float | None]],
          out_of_bounds: int) -> dict:
    """The pass lines over a run: each line's figure, its limit and whether it held, and ``passed``.

    recoveries : (time the network came back or the server restarted, seconds until the first delta after
        it, or None if none came)
    out_of_bounds : camera positions the kiosk reported outside its bounds
    """
    lines: dict[str, dict] = {}
    if len(samples) < 2:
        return {"passed": False, "lines": {"samples": {"figure": len(samples), "limit": 2, "ok": False}}}
    t = np.array([s.t for s in samples])
    ref_t = RSS_REFERENCE_S if plan.duration >= 3 * RSS_REFERENCE_S else plan.duration / 3.0
    ref = samples[int(np.argmin(np.abs(t - ref_t)))]
    growth = samples[-1].rss / max(ref.rss, 1)
    lines["rss_growth"] = {"figure": round(growth, 4), "limit": RSS_GROWTH, "ok": growth <= RSS_GROWTH,
                           "reference_s": round(ref.t, 1)}
    frames = np.array([s.frames for s in samples])
    stalled = int((np.diff(frames) <= 0).sum())
    lines["frames_advance"] = {"figure": stalled, "limit": 0, "ok": stalled == 0, "unit": "windows without frames"}
    leaks = []
    events = plan.events()
    for k, (at, kind) in enumerate(events):
        if kind not in ("cut", "restart"):
            continue
        before = [s for s in samples if s.t < at]
        nxt = next((e for e, kd in events[k + 1:] if kd in ("cut", "restart")), plan.duration + 1.0)
        after = [s for s in samples if s.t < nxt]
        if not before or not after or after[-1].t <= at:
            continue
        base, last = before[-1], after[-1]
        if last.threads > base.threads or last.sockets > base.sockets:
            leaks.append({"event": kind, "at": at, "threads": [base.threads, last.threads],
                          "sockets": [base.sockets, last.sockets]})
    lines["threads_sockets_baseline"] = {"figure": len(leaks), "limit": 0, "ok": not leaks, "leaks": leaks}
    waits = [w for _, w in recoveries]
    worst = max((w if w is not None else math.inf) for w in waits) if waits else 0.0
    lines["deltas_resume"] = {"figure": None if math.isinf(worst) else round(worst, 2), "limit": RECOVERY_S,
                              "ok": bool(waits) and worst <= RECOVERY_S, "after": [round(a, 1) for a, _ in recoveries]}
    lines["camera_in_bounds"] = {"figure": out_of_bounds, "limit": 0, "ok": out_of_bounds == 0}
    return {"passed": all(v["ok"] for v in lines.values()), "lines": lines}


@dataclass
class _Status:
    """The kiosk's status file, read tolerantly (it is replaced atomically, but may not exist yet)."""

    path: Path
    last: dict = field(default_factory=dict)

    def read(self) -> dict:
        try:
            self.last = json.loads(self.path.read_text())
        except (OSError, ValueError):
            pass
        return self.last


def chart(plan: SoakPlan, samples: Sequence[Sample], path: Path) -> Path:
    """RSS, threads and sockets, frames per second and cache bytes over the run, cuts shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.array([s.t for s in samples]) / 60.0
    fig, axes = plt.subplots(4, 1, figsize=(9, 9), sharex=True)
    axes[0].plot(t, [s.rss / 2**20 for s in samples], marker=".")
    axes[0].set_ylabel("RSS (MiB)")
    axes[1].plot(t, [s.threads for s in samples], marker=".", label="threads")
    axes[1].plot(t, [s.sockets for s in samples], marker=".", label="sockets")
    axes[1].legend(loc="upper left")
    frames = np.array([s.frames for s in samples], np.float64)
    dt = np.diff(np.array([s.t for s in samples]))
    axes[2].plot(t[1:], np.diff(frames) / np.maximum(dt, 1e-9), marker=".")
    axes[2].set_ylabel("frames / s")
    axes[3].plot(t, [s.cache_bytes / 2**20 for s in samples], marker=".")
    axes[3].set_ylabel("cache (MiB)")
    axes[3].set_xlabel("minutes")
    for ax in axes:
        for a, b in plan.cuts:
            ax.axvspan(a / 60.0, b / 60.0, color="tab:red", alpha=0.15, lw=0)
        if plan.restart is not None:
            ax.axvline(plan.restart / 60.0, color="tab:purple", ls="--", lw=1)
        ax.grid(alpha=0.3)
    axes[0].set_title("walkstream bench soak: network cuts shaded, server restart dashed")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def run(store: Path, plan: SoakPlan, workdir: Path, *, seed: int = 0, latency: float = 0.02,
        viewport: tuple[int, int] = (320, 180), progress: Callable[[str, int, int], None] | None = None,
        chart_path: Path | None = None) -> dict:
    """Run the soak and return ``judge``'s verdict with the samples, the recoveries and the chart's path."""
    from bench.demo import ServerProcess
    from bench.kiosk_config import soak_config
    from bench.netem import DelayProxy

    workdir.mkdir(parents=True, exist_ok=True)
    server = ServerProcess([store], admin_token=None)
    port = server.port
    proxy = DelayProxy("127.0.0.1", port, latency=latency, seed=seed)
    status = _Status(workdir / "kiosk-status.json")
    config = workdir / "kiosk.toml"
    config.write_text(soak_config(store, f"ws://127.0.0.1:{proxy.port}/ws", viewport=viewport))
    import subprocess

    log = open(workdir / "kiosk.log", "w")
    kiosk = subprocess.Popen(
        [sys.executable, "-m", "walkstream", "kiosk", str(config), "--headless", "--duration",
         str(plan.duration + 30.0), "--status-file", str(status.path), "--synthetic-visitors", str(seed)],
        stdout=log, stderr=subprocess.STDOUT)
    samples: list[Sample] = []
    recoveries: list[tuple[float, float | None]] = []
    events = plan.events()
    try:
        start = _wait_started(kiosk, status, 120.0)
        next_sample = 0.0
        while True:
            now = time.monotonic() - start
            if now >= plan.duration:
                break
            if kiosk.poll() is not None:
                raise RuntimeError(f"the kiosk exited with status {kiosk.returncode} at {now:.0f} s "
                                   f"(see {workdir / 'kiosk.log'})")
            if events and now >= events[0][0]:
                at, kind = events.pop(0)
                if kind == "cut":
                    proxy.cut()
                elif kind == "restore":
                    proxy.restore()
                    recoveries.append((at, _first_delta(status, start, at)))
                else:  # the server's own start-up is not the kiosk's to answer for: time from when it listens
                    server.kill()
                    server = ServerProcess([store], admin_token=None, port=port)
                    up = time.monotonic() - start
                    recoveries.append((up, _first_delta(status, start, up)))
                continue
            if now >= next_sample:
                samples.append(_sample(kiosk.pid, status.read(), now))
                next_sample += plan.sample_every
                if progress:
                    progress("soak", int(now), int(plan.duration))
                continue
            wake = min(next_sample, events[0][0] if events else plan.duration, plan.duration)
            time.sleep(max(0.0, min(0.5, wake - now)))  # pacing the sampler, not synchronising with the kiosk
        samples.append(_sample(kiosk.pid, status.read(), time.monotonic() - start))
    finally:
        kiosk.terminate()
        try:
            kiosk.wait(timeout=20)
        except subprocess.TimeoutExpired:
            kiosk.kill()
            kiosk.wait()
        log.close()
        proxy.close()
        server.close()
    verdict = judge(plan, samples, recoveries, int(status.last.get("out_of_bounds", 0)))
    path = chart(plan, samples, chart_path or workdir / "soak.png")
    return {**verdict, "chart": str(path), "plan": {**asdict(plan), "cuts": plan.cuts, "restart": plan.restart},
            "samples": [asdict(s) for s in samples], "recoveries": recoveries}


def _sample(pid: int, st: dict, now: float) -> Sample:
    rss, threads, sockets = process_sample(pid)
    return Sample(t=round(now, 2), rss=rss, threads=threads, sockets=sockets, frames=int(st.get("frames", 0)),
                  deltas=int(st.get("deltas", 0)), cache_bytes=int(st.get("cache_bytes", 0)),
                  gpu_memory=st.get("gpu_memory"), state=str(st.get("state", "")))


def _wait_started(kiosk, status: _Status, timeout: float) -> float:
    """Wait until the kiosk draws (its status shows frames and a delta); the soak's clock starts then."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if kiosk.poll() is not None:
            raise RuntimeError(f"the kiosk exited with status {kiosk.returncode} before drawing")
        st = status.read()
        if st.get("frames", 0) > 0 and st.get("deltas", 0) > 0:
            return time.monotonic()
        time.sleep(0.2)  # polling a file another process writes; the deadline bounds it
    raise RuntimeError(f"the kiosk drew nothing within {timeout:.0f} s")


def _first_delta(status: _Status, start: float, at: float, window: float = 4 * RECOVERY_S) -> float | None:
    """Seconds from ``at`` until the kiosk's delta count first grows (polled finely); None if not in ``window``."""
    base = int(status.read().get("deltas", 0))
    while time.monotonic() - start < at + window:
        if int(status.read().get("deltas", 0)) > base:
            return time.monotonic() - start - at
        time.sleep(0.05)
    return None
