"""``walkstream demo``: the whole loop on loopback, measured.

Starts a real server (uvicorn, in its own process, as a user would run it),
drives the real headless client over the scene's tour at a target frame time,
and reports how well the frame time held: a line per second while it runs, a
summary after, and a chart of every frame's time against the target.
"""

from __future__ import annotations

import os
import secrets
import subprocess
import sys
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

__all__ = ["ServerProcess", "Summary", "summarize", "write_chart", "per_second", "run_demo"]

#: Frames in the first seconds are the loop converging; the summary starts after them.
WARMUP_S = 2.0


class ServerProcess:
    """``walkstream serve`` in a child process on a free loopback port; a context manager.

    ``admin_token``: "auto" (default) makes a random one, passed through WALKSTREAM_ADMIN_TOKEN
    (never on the command line, where ``ps`` shows it); None starts without admin endpoints.
    ``srv.admin_headers`` carries it for httpx. ``redis``, ``replica``, ``port`` and ``env`` are
    passed on; ``extra`` are further ``serve`` options.
    """

    def __init__(
        self,
        stores: list[Path],
        *,
        host: str = "127.0.0.1",
        extra: list[str] | None = None,
        admin_token: str | None = "auto",
        redis: str | None = None,
        replica: str | None = None,
        port: int = 0,
        env: dict | None = None,
        workers: int = 1,
    ):
        cmd = [sys.executable, "-m", "walkstream", "serve", *map(str, stores), "--host", host, "--port", str(port),
               "--workers", str(workers)]
        if redis:
            cmd += ["--redis", redis]
        if replica:
            cmd += ["--replica", replica]
        cmd += extra or []
        self.admin_token = secrets.token_urlsafe(24) if admin_token == "auto" else admin_token
        self.admin_headers = {"Authorization": f"Bearer {self.admin_token}"} if self.admin_token else {}
        env = dict(os.environ, PYTHONUNBUFFERED="1", **(env or {}))
        env.pop("WALKSTREAM_ADMIN_TOKEN", None)
        if self.admin_token:
            env["WALKSTREAM_ADMIN_TOKEN"] = self.admin_token
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
        line = self.proc.stdout.readline()  # blocks until the socket listens, or the child dies
        if "http://" not in line:
            self.proc.kill()
            self.proc.wait()
            err = self.proc.stderr.read()
            raise RuntimeError(f"the server did not start: {line.strip()} {err.strip()[-2000:]}")
        self.http = line.split("on ", 1)[1].split()[0]
        self.port = int(self.http.rsplit(":", 1)[1])
        self.url = self.http.replace("http://", "ws://") + "/ws"
        # Keep draining the pipes so the child never blocks on a full one.
        self._drain = [threading.Thread(target=self._pump, args=(s,), daemon=True) for s in (self.proc.stdout, self.proc.stderr)]
        self.log: list[str] = []
        for t in self._drain:
            t.start()

    def kill(self) -> None:
        """End the server at once (SIGKILL): no goodbye to its clients, as when a machine dies."""
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()

    def _pump(self, stream) -> None:
        for line in stream:
            self.log.append(line.rstrip())

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()

    def __enter__(self) -> "ServerProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass
class Summary:
    """frames counts the drawn frames after the warm-up, which the figures are over; drawn counts them all."""

    frames: int
    target_ms: float
    mean_ms: float
    p95_ms: float
    max_ms: float
    std_ms: float
    cost_coeff: float
    triangles_mean: float
    deltas: int
    bytes_received: int
    errors: int
    warmup_s: float
    mean_ok: bool
    p95_ok: bool
    drawn: int = 0

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def summarize(run, target: float, warmup: float = WARMUP_S) -> Summary:
    """Frame-time figures over the frames after ``warmup`` seconds (drawn frames only)."""
    frames = [f for f in run.frames if f.t >= warmup and f.seq >= 0]
    times = np.array([f.time for f in frames]) * 1e3 if frames else np.zeros(1)
    tris = np.array([f.triangles for f in frames]) if frames else np.zeros(1)
    mean, p95 = float(times.mean()), float(np.percentile(times, 95))
    last = run.frames[-1] if run.frames else None
    return Summary(
        frames=len(frames),
        target_ms=target * 1e3,
        mean_ms=round(mean, 2),
        p95_ms=round(p95, 2),
        max_ms=round(float(times.max()), 2),
        std_ms=round(float(times.std()), 2),
        cost_coeff=float(last.cost_coeff) if last else 0.0,
        triangles_mean=round(float(tris.mean()), 1),
        deltas=run.deltas_received,
        bytes_received=run.bytes_received,
        errors=len(run.errors),
        warmup_s=warmup,
        mean_ok=bool(frames) and abs(mean - target * 1e3) <= 0.15 * target * 1e3,
        p95_ok=bool(frames) and p95 <= 1.3 * target * 1e3,
        drawn=sum(1 for f in run.frames if f.seq >= 0),
    )


def write_chart(run, target: float, path: Path, title: str = "walkstream demo", warmup: float = WARMUP_S) -> Path:
    """Frame time of every frame against the target (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.array([f.t for f in run.frames])
    ms = np.array([f.time for f in run.frames]) * 1e3
    fig, ax = plt.subplots(figsize=(10, 4), dpi=110)
    ax.axvspan(0, warmup, color="0.92", label="warm-up")
    ax.plot(t, ms, lw=1.0, color="tab:blue", label="frame time (fenced)")
    ax.axhline(target * 1e3, color="tab:red", ls="--", lw=1.2, label=f"target {target * 1e3:.0f} ms")
    ax.axhline(1.3 * target * 1e3, color="tab:red", ls=":", lw=0.8, label="1.3 × target")
    ax.set_xlabel("client time (s)")
    ax.set_ylabel("frame time (ms)")
    ax.set_ylim(0, max(2.0 * target * 1e3, float(ms.max()) * 1.05 if ms.size else 1.0))
    ax.set_title(title)
    ax.legend(loc="upper right", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def per_second(say: Callable[[str], None], target_ms: float) -> Callable:
    """An ``on_frame`` that says a line each second: the drawn frames' count, mean and max time, triangles,
    and the cost model's c_vertex."""
    state = {"second": 0, "frames": []}

    def on_frame(rec) -> None:
        state["frames"].append(rec)
        if rec.t >= state["second"] + 1:
            fs = [f for f in state["frames"] if f.seq >= 0]
            if fs:
                ms = [f.time * 1e3 for f in fs]
                say(f"t={int(rec.t):3d}s  frames {len(fs):3d}  mean {sum(ms) / len(ms):6.1f} ms  "
                    f"max {max(ms):6.1f} ms  target {target_ms:.0f} ms  "
                    f"triangles {int(sum(f.triangles for f in fs) / len(fs)):8d}  "
                    f"c_vertex {fs[-1].cost_coeff * 1e9:7.1f} ns")
            state["second"] = int(rec.t)
            state["frames"] = []

    return on_frame


def run_demo(
    store: Path,
    *,
    scene: str,
    duration: float,
    target: float,
    viewport: tuple[int, int],
    out: Path,
    on_frame: Callable | None = None,
    solver: str = "greedy",
    governor: bool = True,
    hold=None,
):
    """Serve ``store``, run the client over the tour, return (run, summary, chart path); ``hold`` is the
    governor's line (``client.hold.Hold``; None: the client's default)."""
    from client.app import run_client
    from client.hold import STRICT

    with ServerProcess([store]) as server:
        run = run_client(
            server.url, scene, duration=duration, viewport=viewport, target_frame_time=target, on_frame=on_frame,
            solver=solver, governor=governor, hold=hold or STRICT,
        )
    summary = summarize(run, target)
    chart = write_chart(run, target, out / "demo-frames.png", title=f"walkstream demo — {scene}, {solver}, target {target * 1e3:.0f} ms")
    return run, summary, chart

