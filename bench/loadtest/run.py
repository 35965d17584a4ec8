"""The load test's run: a one-client reference phase, then N clients ramped in over one asyncio
loop, the server's ``/metrics`` scraped every second into a live table, and the window's figures.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections import Counter
from dataclasses import asdict
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from bench.loadtest.client import ClientConfig, RendererModel, SimulatedClient
from bench.loadtest.metrics import Scrape, hist_delta, merge, parse_metrics, quantiles_ms, tree_cpu
from bench.loadtest.summary import GOAL_SESSIONS_PER_CORE, SKIPPED_LIMIT, LoadSummary, PhaseResult, at_the_lines, fmt
from proto.messages import ALGORITHMS

__all__ = ["LoadtestError", "run_loadtest"]


#: The key a scrape carries the server's CPU seconds under (all its processes).
SERVER_CPU = "server_cpu_seconds"


class LoadtestError(RuntimeError):
    """The load test cannot run (no server, no /metrics, an unknown scene)."""


# --------------------------------------------------------------------------- a phase: N clients for S seconds


class _Totals:
    """What the clients of a phase did so far, summed (for the live table and the window's start and end)."""

    def __init__(self, clients: list[SimulatedClient]) -> None:
        self.clients = clients
        self.notes: list[str] = []

    def note(self, text: str) -> None:
        if len(self.notes) < 20:
            self.notes.append(text)

    def snapshot(self) -> dict:
        errors: Counter[str] = Counter()
        for c in self.clients:
            errors.update(c.errors)
        return {
            "connected": sum(c.connected for c in self.clients),
            "opened": sum(c.opened for c in self.clients),
            "deltas": sum(c.deltas for c in self.clients),
            "bytes": sum(c.bytes for c in self.clients),
            "errors": errors,
            "cpu": time.process_time(),  # this process: the load generator's own cost
        }


class _Monitor:
    """Scrapes /metrics every second and keeps the live table's figures; the window's ends are scrapes too.

    bases : the servers whose /metrics are summed (one replica, or each replica behind a load balancer)
    pid : a server this process started: its CPU (and its workers') is read from /proc, to the tick
    """

    def __init__(self, http, bases: list[str], pid: int | None, headers: dict | None) -> None:
        self.http, self.bases, self.pid, self.headers = http, bases, pid, headers
        self.first: Scrape | None = None
        self.last: Scrape | None = None

    async def _one(self, base: str, at: float) -> Scrape:
        import httpx

        try:
            r = await self.http.get(f"{base}/metrics")
        except httpx.HTTPError as exc:
            raise LoadtestError(f"lost the server's /metrics ({base}/metrics): {type(exc).__name__}: {exc}") from None
        if r.status_code == 404:
            raise LoadtestError(f"the server has no /metrics ({base}/metrics: 404)")
        if r.status_code != 200:
            raise LoadtestError(f"the server's /metrics answered {r.status_code}")
        return parse_metrics(r.text, at)

    async def scrape(self) -> Scrape:
        at = asyncio.get_running_loop().time()
        s = merge(list(await asyncio.gather(*(self._one(b, at) for b in self.bases))))
        # The server's CPU, all its processes: from /proc for a server we started; else what its workers
        # report (walkstream_cpu_seconds sums them), else its one process's collector.
        cpu = tree_cpu(self.pid) if self.pid is not None else None
        if cpu is None:
            cpu = s.values.get("walkstream_cpu_seconds", s.values.get("process_cpu_seconds_total"))
        if cpu is not None:
            s.values[SERVER_CPU] = cpu
        if self.first is None:
            self.first = s
        self.last = s
        return s

    async def sessions(self, ids: set[str]) -> dict | None:
        """Mirror checks of our sessions from each server's ``/sessions`` (None when one refuses or lacks them)."""
        rows: dict[str, dict] = {}
        for base in self.bases:
            try:
                r = await self.http.get(f"{base}/sessions", headers=self.headers or {})
            except Exception:
                return None
            if r.status_code != 200:
                return None
            body = r.json()
            for row in body.get("sessions", []) if isinstance(body, dict) else body:
                if isinstance(row, dict) and row.get("session") in ids:
                    rows[row["session"]] = row
        ours = list(rows.values())
        if not ours or any("mirror_mismatch" not in s for s in ours):
            return None
        return {k: int(sum(int(s.get(k, 0)) for s in ours)) for k in ("mirror_checks", "mirror_mismatch", "resyncs")}


class _Display:
    """The live table (rich.live on stderr), refreshed twice a second."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self.live = None
        self.rows: dict[str, str] = {}

    def __enter__(self) -> "_Display":
        if self.enabled:
            from rich.console import Console
            from rich.live import Live

            self.live = Live(self._table(), console=Console(stderr=True), auto_refresh=False, transient=False)
            self.live.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        if self.live is not None:
            self.live.update(self._table(), refresh=True)
            self.live.__exit__(*exc)

    def _table(self):
        from rich.table import Table

        table = Table(title="walkstream loadtest", show_header=False, min_width=48)
        for k, v in self.rows.items():
            table.add_row(k, v)
        return table

    def update(self, rows: dict[str, str]) -> None:
        self.rows = rows
        if self.live is not None:
            self.live.update(self._table(), refresh=True)


async def _phase(cfg: ClientConfig, name: str, n: int, duration: float, ramp: float, *, monitor_args, display: _Display,
                 ) -> PhaseResult:
    import httpx

    loop = asyncio.get_running_loop()
    clients = [SimulatedClient(i, n, cfg) for i in range(n)]
    totals = _Totals(clients)
    stop = asyncio.Event()
    settle = min(2.0, 0.4 * (duration - ramp))  # past the last clients' first, largest deltas
    async with httpx.AsyncClient(timeout=10.0) as http:
        monitor = _Monitor(http, *monitor_args)
        first = await monitor.scrape()
        t0 = loop.time()
        w0, w1 = t0 + ramp + settle, t0 + duration
        tasks = [asyncio.create_task(c.run(t0 + ramp * i / n, stop, totals)) for i, c in enumerate(clients)]
        window_start: tuple[Scrape, dict] | None = None
        prev = (t0, totals.snapshot())
        ticks = 0
        try:
            while (now := loop.time()) < w1:
                if window_start is None and now >= w0:
                    window_start = (await monitor.scrape(), totals.snapshot())
                elif ticks % 2 == 0:  # the table twice a second, the scrape once
                    await monitor.scrape()
                ticks += 1
                snap = totals.snapshot()
                dt = max(now - prev[0], 1e-3)
                p50, p99, _ = quantiles_ms(first, monitor.last, "walkstream_selection_seconds")
                display.update({
                    "phase": f"{name}: {now - t0:5.1f} / {duration:g} s" + ("  (ramp)" if now < t0 + ramp else ""),
                    "clients connected": f"{snap['connected']} / {n}",
                    "deltas/s": f"{(snap['deltas'] - prev[1]['deltas']) / dt:.1f}",
                    "selection latency p50 / p99 (server)": f"{fmt(p50)} / {fmt(p99)} ms",
                    "MB/s received": f"{(snap['bytes'] - prev[1]['bytes']) / dt / 1e6:.2f}",
                    "errors": ", ".join(f"{k} {v}" for k, v in sorted(snap["errors"].items())) or "0",
                })
                prev = (now, snap)
                wake = min(now + 0.5, w1, w0 if window_start is None and w0 > now else math.inf)
                await asyncio.sleep(max(0.0, wake - loop.time()))
            end = await monitor.scrape()
            end_totals = totals.snapshot()
            mirror = await monitor.sessions({c.session for c in clients if c.connected})
        finally:
            stop.set()
            await asyncio.gather(*tasks, return_exceptions=True)
    if window_start is None:  # a window too short to reach: measure from the start
        window_start = (first, {"deltas": 0, "bytes": 0, "cpu": end_totals["cpu"]})
    return _result(cfg, clients, totals, first, window_start, end, end_totals, mirror, w0, w1)


def _result(cfg: ClientConfig, clients: list[SimulatedClient], totals: _Totals, first: Scrape, window_start,
            end: Scrape, end_totals: dict, mirror: dict | None, w0: float, w1: float) -> PhaseResult:
    a, a_totals = window_start
    wall = max(end.at - a.at, 1e-6)
    n = len(clients)
    p50, p99, measured = quantiles_ms(a, end, "walkstream_selection_seconds")
    h = hist_delta(a, end, "walkstream_selection_seconds")
    if h is not None and h[1].size > 1 and h[1][-1] - h[1][-2] > 0.01 * h[1][-1]:
        totals.note(f"over 1 % of the selections took longer than the histogram's largest bucket "
                    f"({h[0][-2]:g} s): the p99 shown is a lower bound")
    cpu50, cpu99, _ = quantiles_ms(a, end, "walkstream_selection_cpu_seconds")
    def within(at: list[float], values: np.ndarray) -> np.ndarray:
        at_ = np.asarray(at, np.float64)
        return values[(at_ >= w0) & (at_ <= w1)]

    gaps = [np.diff(within(c.arrivals, np.asarray(c.arrivals, np.float64))) for c in clients]
    gaps_all = np.concatenate(gaps) if gaps else np.zeros(0)
    frames = np.concatenate([within(c.frame_at, np.asarray(c.frame_time, np.float64)) for c in clients])
    cpu = None
    if SERVER_CPU in end.values and SERVER_CPU in a.values:
        cpu = end.values[SERVER_CPU] - a.values[SERVER_CPU]
    sessions = end_totals["connected"]
    tau = next((c.tau for c in clients if c.tau), None)
    deltas = end_totals["deltas"] - a_totals["deltas"]
    # Selections the sessions were owed (one per τ each): a server that falls behind delivers fewer, and its CPU
    # per session then understates what the load would cost it.
    share = deltas / (sessions * wall / tau) if tau and sessions else None
    if share is not None and share < 0.9:
        totals.note(f"the server delivered {share:.0%} of the selections due (one per τ = {tau:g} s per session): "
                    "it is saturated or starved by other processes, so sessions per core overstates its capacity")
    cpu_self = (end_totals["cpu"] - a_totals["cpu"]) / wall
    skipped = sum(c.skipped for c in clients)
    fell_behind = skipped > SKIPPED_LIMIT * max(1, sum(c.frames for c in clients))
    if fell_behind:
        totals.note(f"the load generator skipped {skipped} frames for falling behind while using {cpu_self:.0%} of "
                    "a core: " + ("it is the bottleneck" if cpu_self > 0.7 else "the machine is overloaded"))
    bout = None
    if "walkstream_bytes_out_total" in end.values:
        bout = (end.values["walkstream_bytes_out_total"] - a.values.get("walkstream_bytes_out_total", 0.0)) / wall
    ticks = end.values.get("walkstream_ticks_total", 0.0) - a.values.get("walkstream_ticks_total", 0.0)
    tick_polls = end.values.get("walkstream_tick_polls_total", 0.0) - a.values.get("walkstream_tick_polls_total", 0.0)
    server_errors = {k: int(v - first.errors.get(k, 0.0)) for k, v in end.errors.items()
                     if v - first.errors.get(k, 0.0) > 0}
    target_ms = cfg.target * 1e3
    frame_p95 = float(np.percentile(frames, 95)) * 1e3 if frames.size else None
    per_client = [c.deltas for c in clients]
    return PhaseResult(
        clients=n,
        sessions_opened=end_totals["opened"],
        connected_at_end=sessions,
        window_s=round(wall, 3),
        deltas=deltas,
        selections_per_s=deltas / wall,
        selections_due_share=share,
        selection_p50_ms=p50,
        selection_p99_ms=p99,
        selections_measured=measured,
        selection_cpu_p50_ms=cpu50,
        selection_cpu_p99_ms=cpu99,
        delta_interarrival_p99_ms=float(np.percentile(gaps_all, 99)) * 1e3 if gaps_all.size else None,
        bytes_per_s=(end_totals["bytes"] - a_totals["bytes"]) / wall,
        server_bytes_out_per_s=bout,
        server_cpu_s=cpu,
        server_cpu_per_session_s=cpu / (sessions * wall) if cpu is not None and sessions else None,
        sessions_per_core=sessions / (cpu / wall) if cpu and sessions else None,
        errors=dict(sorted(end_totals["errors"].items())),
        server_errors=server_errors,
        frame_p95_ms=frame_p95,
        frame_target_ms=target_ms,
        frame_p95_over_target=frame_p95 / target_ms if frame_p95 is not None else None,
        clients_with_deltas=sum(d > 0 for d in per_client),
        min_deltas_per_client=min(per_client) if per_client else 0,
        acks=sum(c.acks for c in clients),
        pongs=sum(c.pongs for c in clients),
        frames_skipped=skipped,
        generator_fell_behind=fell_behind,
        generator_cpu_per_session_s=(end_totals["cpu"] - a_totals["cpu"]) / (sessions * wall) if sessions else None,
        generator_cores=cpu_self,
        polls_per_tick=tick_polls / ticks if ticks > 0 else None,
        server_cores=cpu / wall if cpu is not None else None,
        mirror_checks=None if mirror is None else mirror["mirror_checks"],
        mirror_mismatch=None if mirror is None else mirror["mirror_mismatch"],
        resyncs=None if mirror is None else mirror["resyncs"],
        notes=list(totals.notes),
    )


# --------------------------------------------------------------------------- the whole test


def _http_base(url: str) -> str:
    if url.startswith("ws://"):
        base = "http://" + url[len("ws://"):]
    elif url.startswith("wss://"):
        base = "https://" + url[len("wss://"):]
    else:
        raise LoadtestError(f"expected a ws:// or wss:// URL, got {url!r}")
    base = base.split("?", 1)[0]
    if base.endswith("/ws"):
        base = base[: -len("/ws")]
    return base.rstrip("/")


def _preflight(base: str, scene: str | None, headers: dict | None) -> str:
    """Check /metrics is there and pick the scene; returns the scene's name."""
    import httpx

    try:
        r = httpx.get(f"{base}/metrics", timeout=10.0)
    except httpx.HTTPError as exc:
        raise LoadtestError(f"cannot reach the server at {base}: {exc}") from None
    if r.status_code == 404:
        raise LoadtestError(f"the server has no /metrics ({base}/metrics: 404); walkstream loadtest reads the "
                            "selection latency and the server's CPU time from it")
    if r.status_code != 200:
        raise LoadtestError(f"the server's /metrics answered {r.status_code}")
    try:
        names = [s["name"] for s in httpx.get(f"{base}/scenes", timeout=10.0, headers=headers or {}).json()]
    except Exception as exc:
        raise LoadtestError(f"cannot list the server's scenes ({base}/scenes): {exc}") from None
    if scene is None:
        if not names:
            raise LoadtestError("the server serves no scene")
        return names[0]
    if scene not in names:
        raise LoadtestError(f"the server does not serve scene {scene!r}; it serves {', '.join(names) or 'none'}")
    return scene


def _ratio(a: float | None, b: float | None) -> float | None:
    return a / b if a is not None and b else None


def run_loadtest(
    *,
    clients: int,
    duration: float,
    url: str | None = None,
    stores: Sequence[Path] | None = None,
    scene: str | None = None,
    tau: float = 0.5,
    rate: float = 10.0,
    target_ms: float = 50.0,
    algorithms: Sequence[str] = ("flat",),
    ramp: float | None = None,
    seed: int = 0,
    reference: float = 5.0,
    model: RendererModel | None = None,
    admin_headers: dict | None = None,
    live: bool = False,
    log: Callable[[str], None] | None = None,
    workers: int = 1,
    metrics: Sequence[str] | None = None,
    separate: bool = False,
) -> LoadSummary:
    """Run ``clients`` simulated sessions for ``duration`` seconds (the ramp included) and measure the server.

    Without ``url`` a server (``bench.demo.ServerProcess``) is started on
    ``stores`` (default: the Den Haag store) with ``--tau``; with it, that
    server is used (``tau`` is then whatever it runs with) and its ``/metrics``
    is read from the same host. ``ramp`` (default: a quarter of the duration,
    at most 10 s) spreads the connections; the figures are over the rest.
    ``reference`` seconds of one client are measured first (0: skip).
    ``workers``: processes of the started server. ``metrics``: the servers (http://host:port) whose /metrics
    and /sessions are summed — each replica of a deployment behind ``url``'s load balancer (default: ``url``'s).
    The server's CPU is its processes' own: from /proc for a started server (supervisor and workers), else its
    ``walkstream_cpu_seconds``. ``separate``: each frame's report in a message of its own (two messages a frame,
    as before ``Camera.report``), to measure what the messages cost.
    Raises ``LoadtestError`` when the server cannot be used.
    """
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    if clients < 1:
        raise ValueError(f"clients must be at least 1, got {clients}")
    if not 0 < rate <= 120:
        raise ValueError(f"rate must lie in (0, 120] Hz, got {rate}")
    if not 1 <= target_ms <= 2000:
        raise ValueError(f"target_ms must lie in [1, 2000], got {target_ms}")
    bad = [a for a in algorithms if a not in ALGORITHMS]
    if bad or not algorithms or len(set(algorithms)) != len(algorithms):
        raise ValueError(f"algorithms must be distinct names among {', '.join(ALGORITHMS)}, got {list(algorithms)}")
    ramp = min(10.0, 0.25 * duration) if ramp is None else float(ramp)
    if ramp < 0 or duration <= ramp:
        raise ValueError(f"duration ({duration} s) must exceed the ramp ({ramp} s)")
    if reference < 0:
        raise ValueError(f"reference must be non-negative, got {reference}")
    model = model or RendererModel()
    say = log or (lambda s: None)
    server = None
    try:
        pid = None
        if url is None:
            from bench.demo import ServerProcess

            if not stores:
                from bench.stores import cached_denhaag

                stores = [cached_denhaag(quiet=not live)]
            missing = [str(p) for p in stores if not Path(p).exists()]
            if missing:
                raise LoadtestError(f"no such store: {', '.join(missing)}")
            say(f"starting a server on {', '.join(map(str, stores))} (τ = {tau:g} s)")
            extra = ["--tau", str(tau)]
            if clients > 256:  # the server's default max_sessions: past it, it would refuse them (busy)
                extra += ["--max-sessions", str(clients)]
            # Every simulated client is on loopback: one address opens them all, at once.
            extra += ["--max-per-address", str(max(32, clients + 2)), "--connect-rate", "1e6"]
            server = ServerProcess(list(map(Path, stores)), extra=extra, workers=workers)
            url, pid = server.url, server.proc.pid
            admin_headers = admin_headers or getattr(server, "admin_headers", None)
        base = _http_base(url)
        scene = _preflight(base, scene, admin_headers)
        cfg = ClientConfig(url=url, http=base, scene=scene, rate=float(rate), target=target_ms / 1e3,
                      algorithms=tuple(algorithms), model=model, seed=int(seed), separate=bool(separate))
        bases = [_http_base(m.replace("http://", "ws://").replace("https://", "wss://")) for m in metrics or ()]
        monitor_args = (bases or [base], pid, admin_headers)

        async def main() -> tuple[PhaseResult | None, PhaseResult]:
            with _Display(live) as display:
                ref = None
                if reference > 0:
                    ref = await _phase(cfg, "reference, 1 client", 1, reference, 0.0, monitor_args=monitor_args,
                                       display=display)
                run = await _phase(cfg, f"{clients} clients", clients, duration, ramp, monitor_args=monitor_args,
                                   display=display)
            return ref, run

        say(f"scene {scene!r} at {url}: {clients} clients for {duration:g} s (ramp {ramp:g} s)"
            + (f" after a {reference:g} s one-client reference" if reference > 0 else ""))
        ref, run = asyncio.run(main())
        lines = at_the_lines(run)
        spc_ok = run.sessions_per_core is not None and run.sessions_per_core >= GOAL_SESSIONS_PER_CORE
        return LoadSummary(
            **asdict(run),
            scene=scene, url=url, tau=tau if server is not None else None, rate=float(rate),
            duration_s=float(duration), ramp_s=ramp, server_pid=pid, reference=ref,
            cpu_per_session_ratio=_ratio(run.server_cpu_per_session_s, ref and ref.server_cpu_per_session_s),
            p99_ratio=_ratio(run.selection_p99_ms, ref and ref.selection_p99_ms),
            workers=workers if server is not None else None, lines_met=lines,
            goal_met=bool(lines and spc_ok),
        )
    finally:
        if server is not None:
            server.close()
