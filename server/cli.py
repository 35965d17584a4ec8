"""The server's commands: ``walkstream build``, ``inspect`` and ``serve``.

Defined here, beside what they run; the root ``walkstream`` app (``walkstream/cli.py``)
registers them. Each imports what it needs when it runs, so ``walkstream serve``
works on a machine without moderngl and ``--help`` is instant. The progress bar and
the solver check live here too: the benchmarks' and the client's commands share them.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

SOLVER_HELP = ("LOD selection solver the session asks for: none, static, feedback, greedy, optimization "
               "(alias incremental), hierarchical, mixed, exact")


def progress_bar(label: str, quiet: bool = False):
    """A rich progress bar on stderr whose ``tick(stage, done, total)`` follows a build's stages."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    bar = Progress(
        TextColumn(f"[bold]{label}[/bold] {{task.description:<12}}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        transient=False,
        disable=quiet,
        console=stderr_console(),
    )
    tasks: dict[str, int] = {}

    def tick(stage: str, done: int, total: int) -> None:
        if stage not in tasks:
            tasks[stage] = bar.add_task(stage, total=max(total, 1))
        bar.update(tasks[stage], completed=done, total=max(total, 1))

    return bar, tick


def stderr_console():
    from rich.console import Console

    return Console(stderr=True)


def fail(message: str) -> None:
    """End the command with one line on stderr and exit status 2 (a user's error: no traceback)."""
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(2)


def check_solver(name: str) -> None:
    """Refuse an unknown solver before connecting (the server would refuse it in its welcome)."""
    from server.select.solvers import SOLVERS

    if name not in SOLVERS:
        raise typer.BadParameter(f"unknown solver {name!r}; choose one of {', '.join(sorted(SOLVERS))}",
                                 param_hint="--solver")


def build(
    source: str = typer.Argument(..., help="a named scene (demo, auditorium, denhaag, sthelens, megacity) or a "
                                 "path to a CityJSON, glTF/GLB, OBJ, PLY, USGS DEM, .npz or CityGML file"),
    output: Optional[Path] = typer.Option(None, "-o", "--output",
                                          help="the scene store to write (default: SOURCE.db in the current folder)"),
    size: Optional[int] = typer.Option(None, help="scale of a named scene: objects (demo), buildings (megacity), "
                                       "trees (denhaag, sthelens)"),
    objects: Optional[int] = typer.Option(None, help="demo: number of objects (same as --size)"),
    grid: Optional[int] = typer.Option(None, help="sthelens: resample the DEM to GRID × GRID samples "
                                       "(ZMK 2002 use 2049; interpolated, not measured)"),
    seed: int = typer.Option(0, help="random seed of a named scene (same seed, same scene)"),
    workers: Optional[int] = typer.Option(None, help="worker processes (default: one per CPU)"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="no progress bar"),
    force: bool = typer.Option(False, "--force", help="replace an existing OUTPUT (atomically, once the build "
                               "completes)"),
    tree_model: list[Path] = typer.Option([], "--tree-model", help="a scanned tree (.xyz, .ply, .las, .laz point "
                                          "cloud) to draw the scene's trees with instead of their models; repeat "
                                          "for several, shared out by crown shape"),
) -> None:
    """Build a scene store. The store appears only when the build completes; an existing one is kept unless --force."""
    from server.scene.catalog import build_named, build_path, is_named
    from server.scene.source import SourceError
    from server.scene.store import StoreError

    size = size if size is not None else objects
    if size is not None and size < 1:
        raise typer.BadParameter("must be at least 1", param_hint="--size")
    if workers is not None and workers < 1:
        raise typer.BadParameter("must be at least 1", param_hint="--workers")
    named = is_named(source)
    if grid is not None and (source != "sthelens" or not 2 <= grid <= 8193):
        raise typer.BadParameter("resamples the sthelens DEM only, to 2..8193 samples a side", param_hint="--grid")
    if not named and not Path(source).exists():
        raise typer.BadParameter(
            f"{source!r} is neither a named scene (demo, auditorium, denhaag, sthelens, megacity) nor an existing file",
            param_hint="SOURCE")
    if not named and Path(source).is_dir():
        fail(f"{source!r} is a directory; give one scene file (CityJSON, glTF/GLB, OBJ, PLY, DEM, .npz, CityGML)")
    from server.scene.importers.pointcloud import POINT_CLOUD_SUFFIXES

    for f in tree_model:
        if not f.is_file():
            raise typer.BadParameter(f"{str(f)!r} is not a file", param_hint="--tree-model")
        if f.suffix.lower() not in POINT_CLOUD_SUFFIXES:
            raise typer.BadParameter(f"{str(f)!r} is not a point cloud ({', '.join(POINT_CLOUD_SUFFIXES)})",
                                     param_hint="--tree-model")
    if output is None:
        output = Path(f"{source if named else Path(source).name.split('.')[0]}.db")
    if not named and output.resolve() == Path(source).resolve():
        fail(f"output {str(output)!r} is the input: the build would overwrite it; choose another -o")
    if output.is_dir():
        fail(f"output {str(output)!r} is a directory; give the store's file name")
    if output.exists() and not force:
        fail(f"output {str(output)!r} exists; add --force to replace it")
    output.parent.mkdir(parents=True, exist_ok=True)
    bar, tick = progress_bar(f"building {source if named else Path(source).name}", quiet)
    try:
        with bar:
            if named:
                summary = build_named(source, output, seed=seed, size=size, grid=grid, workers=workers,
                                      progress=tick, tree_models=tree_model)
            else:
                summary = build_path(source, output, workers=workers, progress=tick, tree_models=tree_model)
    except (SourceError, StoreError, FileNotFoundError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    typer.echo(json.dumps({"store": str(output), **summary}, default=str))


def inspect(
    store: Path = typer.Argument(..., help="a scene store"),
    as_json: bool = typer.Option(False, "--json", help="print one JSON object instead of text"),
) -> None:
    """Print what a scene store holds: objects, representations and triangles per kind and level, bytes, depth."""
    from server.scene.inspect import format_report, inspect_store
    from server.scene.store import StoreError

    try:
        report = inspect_store(store)
    except StoreError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    if as_json:
        typer.echo(json.dumps(report))
    else:
        for line in format_report(report):
            typer.echo(line)



def serve(
    stores: list[Path] = typer.Argument(..., help="scene stores to serve, each under its recorded name"),
    host: str = typer.Option("127.0.0.1", help="address to listen on"),
    port: int = typer.Option(8765, help="port (0: any free port, printed once listening)"),
    tau: float = typer.Option(0.5, help="seconds between selections (τ)"),
    c_vertex: float = typer.Option(2.0e-7, help="first guess of the cost per vertex (s) before frames are measured"),
    log_level: str = typer.Option("warning", help="uvicorn log level"),
    redis: Optional[str] = typer.Option(None, "--redis", envvar="WALKSTREAM_REDIS",
                                        help="keep session state in this Redis (redis://host:port/0), shared by "
                                             "replicas so a client resumes on any; default: in memory"),
    admin_token: Optional[str] = typer.Option(None, "--admin-token", envvar="WALKSTREAM_ADMIN_TOKEN",
                                              help="bearer token for GET /sessions and DELETE /sessions/ID "
                                                   "(without one they answer 403)"),
    max_sessions: int = typer.Option(256, help="websocket sessions at once; past it new ones are refused (busy)"),
    rate: float = typer.Option(200.0, help="messages per second a session may send (token bucket rate)"),
    burst: float = typer.Option(400.0, help="messages a session may send at once (token bucket size)"),
    idle_timeout: float = typer.Option(60.0, help="seconds without a client message before the session is closed"),
    workers: Optional[int] = typer.Option(None, help="worker processes behind the one port (default: the number of "
                                          "CPUs); they share session state (--redis, or a file of their own)"),
    threads: Optional[int] = typer.Option(None, help="threads per worker process for hellos, restores and "
                                          "snapshots (default: the number of CPUs); selections run on the event loop"),
    state_ttl: float = typer.Option(300.0, help="seconds a disconnected session's state is kept for a resume"),
    replica: Optional[str] = typer.Option(None, help="this replica's name in /health (default: hostname:port)"),
    send_buffer: Optional[int] = typer.Option(None, help="kernel send buffer per connection in bytes (default: "
                                              "autotuned); smaller bounds what a slow client pins"),
    hello_timeout: float = typer.Option(5.0, help="seconds a new connection has to say its hello"),
    max_bad_frames: int = typer.Option(16, help="refused frames a connection may send before it is closed"),
    max_per_address: int = typer.Option(32, help="connections one remote address may hold open at once"),
    connect_rate: float = typer.Option(10.0, help="new connections per second one remote address may open "
                                       "(burst 40)"),
    byte_rate: float = typer.Option(256 * 1024, help="bytes per second a connection may send (token bucket)"),
    trusted_proxy: list[str] = typer.Option([], "--trusted-proxy", help="address of a reverse proxy whose "
                                            "X-Real-IP names the client (repeatable)"),
    allow_measurement_solvers: bool = typer.Option(False, "--allow-measurement-solvers",
                                                   help="let clients ask for the exact solver (for benchmarks; "
                                                        "one client can keep a CPU busy)"),
    docs: bool = typer.Option(False, "--docs", help="serve the interactive API docs at /docs (loads from a CDN)"),
) -> None:
    """Serve scene stores over websockets at /ws (plus /health, /scenes, /metrics; /sessions and /fleet for admins)."""
    import os

    from server.startup import ServeError
    from server.workers import serve as run_server
    from server.limits import ReplicaLimits
    from server.scene.store import StoreError
    from server.session import SessionConfig

    missing = [str(p) for p in stores if not p.exists()]
    if missing:
        raise typer.BadParameter(f"no such store: {', '.join(missing)}", param_hint="STORES")
    seen: set[Path] = set()
    for p in stores:
        if p.resolve() in seen:
            fail(f"store {str(p)!r} is given twice")
        seen.add(p.resolve())
    if not 0.05 <= tau <= 10:
        raise typer.BadParameter("τ must lie in [0.05, 10] seconds", param_hint="--tau")
    if not 1e-12 <= c_vertex <= 1e-3:
        raise typer.BadParameter("must lie in [1e-12, 1e-3] seconds", param_hint="--c-vertex")
    given = dict(max_sessions=max_sessions, rate=rate, burst=burst, idle_timeout=idle_timeout, state_ttl=state_ttl,
                 hello_timeout=hello_timeout, max_bad_frames=max_bad_frames, max_per_address=max_per_address,
                 byte_rate=byte_rate, connect_rate=connect_rate, trusted_proxies=tuple(trusted_proxy),
                 allow_measurement_solvers=allow_measurement_solvers, docs=docs)
    if threads is not None:
        given["threads"] = threads
    if workers is not None and workers < 1:
        raise typer.BadParameter("must be at least 1", param_hint="--workers")
    if send_buffer is not None:
        given["send_buffer"] = send_buffer
    try:
        limits = ReplicaLimits(**given)
    except ValueError as exc:
        name = str(exc).split()[0]
        raise typer.BadParameter(str(exc), param_hint="--" + name.replace("_", "-")) from None
    try:
        run_server(stores, host, port, SessionConfig(tau=tau, c_vertex=c_vertex), log_level,
                   announce=lambda s: print(s, flush=True), limits=limits, state_url=redis or None,
                   admin_token=admin_token or None, replica=replica, workers=workers or os.cpu_count() or 1)
    except (StoreError, ServeError) as exc:
        fail(str(exc))
