"""The load commands: ``walkstream loadtest`` (clients over the network against a server) and ``walkstream bench
sessions`` (the server's sessions in one process, without a network). Each imports what it needs when it runs."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from server.cli import progress_bar, stderr_console

__all__ = ["loadtest", "bench_sessions"]


def loadtest(
    url: Optional[str] = typer.Option(None, help="a running server's websocket URL (ws://host:port/ws); "
                                      "default: start one on --store"),
    stores: Optional[list[Path]] = typer.Option(None, "--store", help="scene stores the started server serves "
                                                "(default: the Den Haag store, built if missing)"),
    scene: Optional[str] = typer.Option(None, help="scene to ask for (default: the server's first)"),
    clients: int = typer.Option(..., help="simulated clients (per worker process with --clients-per-worker)"),
    per_worker: bool = typer.Option(False, "--clients-per-worker", help="drive each worker process with --clients "
                                    "clients (a run of N workers: N × clients), so every run's processes carry the "
                                    "load one worker is measured at and the scaling ratio compares like with like"),
    duration: float = typer.Option(..., help="seconds to run, the ramp included"),
    tau: float = typer.Option(0.5, help="τ of the started server (seconds between selections)"),
    rate: float = typer.Option(10.0, help="camera poses and frame reports per second per client"),
    target_ms: float = typer.Option(50.0, help="target frame time each client asks for (ms)"),
    algorithms: str = typer.Option("flat", help="rendering algorithms the clients offer, comma-separated"),
    ramp: Optional[float] = typer.Option(None, help="seconds over which the clients connect "
                                         "(default: a quarter of the duration, at most 10)"),
    seed: int = typer.Option(0, help="random seed (viewports, tour phases, frame-time noise)"),
    reference: float = typer.Option(5.0, help="seconds of a one-client reference run first (0: skip)"),
    admin_token: Optional[str] = typer.Option(None, envvar="WALKSTREAM_ADMIN_TOKEN", show_envvar=True,
                                              help="the --url server's admin token, to read its client-cache "
                                              "mirror checks from /sessions"),
    workers: Optional[list[int]] = typer.Option(None, "--workers", help="worker processes of the started server; "
                                                "repeat (--workers 1 --workers 2) for a run of each and the "
                                                "scaling ratio (default: 1)"),
    repeats: int = typer.Option(1, min=1, help="rounds of the --workers runs, interleaved (1 2, 2 1, …); each "
                                "goal is judged on the median round and printed with the spread"),
    metrics: Optional[list[str]] = typer.Option(None, "--metrics", help="with --url: a server (http://host:port) "
                                                "whose /metrics and /sessions count, repeated for each replica "
                                                "behind the load balancer (default: the --url host)"),
    coherent: bool = typer.Option(True, "--coherent/--no-coherent", help="time the incremental solver's coherent "
                                  "step at 100k objects too (a goal of the same issue)"),
    separate: bool = typer.Option(False, "--separate-reports", help="send each frame's report in a message of its "
                                  "own, not with the next pose (twice the messages: what clients sent before)"),
    as_json: bool = typer.Option(False, "--json", help="end with one JSON object on stdout"),
) -> None:
    """Simulated clients (no GL) against a server: sessions, selections per second and the share of those due,
    p50/p99 selection latency, bytes per second, the server's CPU per session-second (all its processes) and
    sessions per core, the generator's own CPU, errors, and the goals; a live table on stderr."""
    from bench.loadtest.goals import format_goals, run_goals
    from bench.loadtest.run import LoadtestError

    algs = [a.strip() for a in algorithms.split(",") if a.strip()]
    if stores and url:
        raise typer.BadParameter("give either --url or --store", param_hint="--store")
    for path in stores or []:
        if not path.exists():
            raise typer.BadParameter(f"no such store: {path}", param_hint="--store")
    console = stderr_console()
    if url and workers:
        raise typer.BadParameter("--workers starts a server of that many processes; a --url server is as it is",
                                 param_hint="--workers")
    if metrics and not url:
        raise typer.BadParameter("--metrics names the servers behind a --url", param_hint="--metrics")
    try:
        result, runs = run_goals(
            workers or [1], repeats=repeats, coherent=coherent, per_worker=per_worker,
            url=url, stores=stores or None, scene=scene, clients=clients, duration=duration, tau=tau, rate=rate,
            target_ms=target_ms, algorithms=algs, ramp=ramp, seed=seed, reference=reference,
            admin_headers={"Authorization": f"Bearer {admin_token}"} if admin_token else None,
            live=True, log=lambda s: console.print(s, highlight=False), metrics=metrics, separate=separate,
        )
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from None
    except LoadtestError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    for line in format_goals(result, runs):
        typer.echo(line, err=as_json)
    if as_json:
        print(json.dumps(result))


def bench_sessions(
    store: Optional[Path] = typer.Option(None, help="the scene store (default: the Den Haag store, built if missing)"),
    clients: int = typer.Option(40, help="scripted sessions"),
    seconds: float = typer.Option(20.0, help="virtual seconds each run lasts"),
    repeats: int = typer.Option(3, help="runs (the median and the spread are reported)"),
    save_interval: float = typer.Option(1.0, help="the least seconds between two snapshots of a session, as "
                                        "the server's save interval"),
    separate: bool = typer.Option(False, "--separate-reports", help="each frame's report in a message of its own"),
    as_json: bool = typer.Option(False, "--json", help="end with one JSON line of figures"),
) -> None:
    """The server's CPU per session-second by part (selections, poses and reports, acks, encoding, snapshots),
    its sessions driven in this process on a virtual clock by the load test's clients: no network, no sockets."""
    from bench.sessions import run
    from bench.stores import cached_denhaag

    if clients < 1 or repeats < 1:
        raise typer.BadParameter("must be at least 1", param_hint="--clients/--repeats")
    if not seconds > 0 or not save_interval > 0:
        raise typer.BadParameter("must be positive", param_hint="--seconds/--save-interval")
    if store is not None and not store.exists():
        raise typer.BadParameter(f"no such store: {store}", param_hint="--store")
    path = store if store is not None else cached_denhaag(quiet=as_json)
    bar, tick = progress_bar("bench sessions", quiet=as_json)
    with bar:
        result = run(path, clients=clients, seconds=seconds, repeats=repeats, save_interval=save_interval,
                     separate=separate, progress=tick)
    for line in result["lines"]:
        typer.echo(line, err=as_json)
    if as_json:
        print(json.dumps({k: v for k, v in result.items() if k != "lines"}))
