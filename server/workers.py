"""``walkstream serve``: one process, or one process per core behind one port.

Python runs one thread of a process at a time, so a replica uses every core
only as several processes. With ``workers`` > 1 the command becomes a small
supervisor: it checks the port and the stores, holds the port, and starts the
workers, each a process of its own (spawned, so nothing of the supervisor's
state crosses over) that opens the scene stores read-only, listens on the
replica's port with SO_REUSEPORT — the kernel spreads new connections over
them — and serves. What a client's session needs on any worker lives in a
state store all of them share: Redis with ``--redis``, otherwise one SQLite
file in the replica's run folder (``server.state.SqliteStateStore``). A client
whose worker dies redials the same port, lands on a live worker and resumes
with nothing re-sent. The supervisor starts a new worker in its place.

The run folder also holds the workers' Prometheus files (one ``/metrics`` sums
them all) and their private loopback ports (``server.peers``: one ``/sessions``
lists them all). ``max_sessions``, the threads and the rate limits are per
worker.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import shutil
import signal
import socket
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from .limits import ReplicaLimits
from .session import SessionConfig
from .startup import ServeError, bind_listener, check_state_url, load_scenes, reserve_port
from .state import MemoryStateStore, RedisStateStore, SqliteStateStore, open_state_store

__all__ = ["serve", "WorkerSpec"]

log = logging.getLogger("walkstream.server")

#: Seconds a worker may take to load its stores and kernels before the replica gives up on starting.
START_TIMEOUT = 300.0
#: Least seconds between two starts of a worker in one slot (a worker that dies at once is not restarted hot).
RESPAWN_GAP = 1.0


@dataclass(frozen=True)
class WorkerSpec:
    """What a worker process is given (picklable: it crosses a spawn)."""

    paths: tuple[str, ...]
    host: str
    port: int
    config: SessionConfig
    limits: ReplicaLimits
    state_url: str | None
    admin_token: str | None
    replica: str
    log_level: str
    run_dir: str | None  # the replica's run folder (peers, metrics); None: a single process
    parent: int | None = None  # the supervisor's pid: a worker whose supervisor is gone ends


def serve(paths: list[Path], host: str = "127.0.0.1", port: int = 8765, config: SessionConfig | None = None,
          log_level: str = "warning", announce=print, *, limits: ReplicaLimits | None = None,
          state_url: str | None = None, admin_token: str | None = None, replica: str | None = None,
          workers: int = 1) -> None:
    """Serve ``paths`` on ``host:port`` (port 0: any free port, announced once listening) with ``workers``
    processes; returns when the server is stopped (SIGTERM, SIGINT)."""
    limits = limits or ReplicaLimits()
    config = config or SessionConfig()
    if workers < 1:
        raise ServeError(f"--workers must be at least 1, got {workers}")
    try:
        state = open_state_store(state_url)
    except Exception as exc:  # an unknown scheme, a malformed URL
        raise ServeError(str(exc)) from None
    if isinstance(state, RedisStateStore):
        check_state_url(state_url)
    if workers == 1:
        return _single(paths, host, port, config, log_level, announce, limits, state, admin_token, replica)
    if isinstance(state, MemoryStateStore) and state_url not in (None, "", "memory", "memory://"):
        raise ServeError("workers share their sessions' state: give --redis, or nothing for the shared file")
    # The port first: a port in use is the user's to fix, and they should not wait for the stores to learn it.
    held = reserve_port(host, port)
    bound = held.getsockname()[1]
    for store in _scenes(paths, held).values():  # each worker opens them again; a bad one is said once, here
        store.close()
    run_dir = tempfile.mkdtemp(prefix="walkstream-replica-")
    if state_url in (None, "", "memory", "memory://"):
        state_url = f"sqlite:///{run_dir}/state.db"
        SqliteStateStore.create(f"{run_dir}/state.db")  # made once here, not raced for by the workers
    os.makedirs(f"{run_dir}/metrics")
    spec = WorkerSpec(tuple(map(str, paths)), host, bound, config, limits, state_url, admin_token,
                      replica or f"{socket.gethostname()}:{bound}", log_level, run_dir, os.getpid())
    try:
        _supervise(spec, workers, announce)
    finally:
        held.close()
        shutil.rmtree(run_dir, ignore_errors=True)


def _single(paths, host, port, config, log_level, announce, limits, state, admin_token, replica) -> None:
    """One process: the listening socket, the stores and the kernels, then uvicorn."""
    sock = bind_listener(host, port, limits.send_buffer)
    bound = sock.getsockname()[1]
    scenes = _scenes(paths, sock)
    app = _app(scenes, config, state, limits, admin_token, replica or f"{socket.gethostname()}:{bound}", None)
    announce(f"walkstream: serving {', '.join(sorted(scenes))} on http://{host}:{bound} (websocket /ws)")
    _uvicorn(app, [sock], limits, log_level).run(sockets=[sock])


def _scenes(paths, sock: socket.socket) -> dict:
    """The scene stores opened; on failure ``sock`` closed and a ``ServeError`` for a store's own fault."""
    try:
        return load_scenes(paths)
    except ValueError as exc:
        sock.close()
        raise ServeError(str(exc)) from None
    except BaseException:
        sock.close()
        raise


def _app(scenes, config, state, limits, admin_token, replica, peers):
    # Selections switch from the numpy reference to the compiled kernels once those are ready; doing that
    # mid-session could flip a tie and morph an object for nothing, so sessions start only after it (the
    # bootstrap fills numba's cache, from which it is quick). WALKSTREAM_NUMBA=0 keeps the kernels off.
    from .app import create_app
    from .select import kernels

    began = time.perf_counter()
    compiled = kernels.warm_up(timeout=START_TIMEOUT, setting=os.environ.get("WALKSTREAM_NUMBA"))
    log.info("selection kernels: %s after %.1f s", "numba" if compiled else "numpy", time.perf_counter() - began)
    return create_app(scenes, config, state=state, limits=limits, admin_token=admin_token, replica=replica,
                      peers=peers)


def _uvicorn(app, sockets, limits: ReplicaLimits, log_level: str):
    import uvicorn

    return uvicorn.Server(uvicorn.Config(
        app, log_level=log_level, ws_max_size=limits.max_message, ws_ping_interval=limits.ping_interval,
        ws_ping_timeout=limits.ping_timeout,
        # Large frames are zstd'd by the codec already; deflate on top would only burn CPU on every small
        # frame of every session.
        ws_per_message_deflate=False))


# --------------------------------------------------------------------------- the supervisor


def _supervise(spec: WorkerSpec, n: int, announce) -> None:
    """Start ``n`` workers, say where they serve once all listen, restart any that dies, stop them on a signal."""
    from prometheus_client import multiprocess

    os.environ["PROMETHEUS_MULTIPROC_DIR"] = f"{spec.run_dir}/metrics"  # inherited by the spawned workers
    ctx = mp.get_context("spawn")
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    slots: list[tuple[mp.Process, float]] = []

    def start() -> tuple[mp.Process, float]:
        proc = ctx.Process(target=_worker, args=(spec,), name="walkstream-worker", daemon=False)
        proc.start()
        return proc, time.monotonic()

    try:
        slots = [start() for _ in range(n)]
        _wait_listening(spec, [p for p, _ in slots], stop)
        if stop.is_set():
            return
        names = ", ".join(sorted(_scene_names(spec.paths)))
        announce(f"walkstream: serving {names} on http://{spec.host}:{spec.port} (websocket /ws) "
                 f"with {n} worker processes")
        while not stop.wait(0.2):
            for i, (proc, began) in enumerate(slots):
                if proc.is_alive():
                    continue
                multiprocess.mark_process_dead(proc.pid, f"{spec.run_dir}/metrics")
                Path(f"{spec.run_dir}/peers/{proc.pid}").unlink(missing_ok=True)
                if time.monotonic() - began >= RESPAWN_GAP:
                    log.warning("worker %d ended (exit %s); starting another", proc.pid, proc.exitcode)
                    slots[i] = start()
    finally:
        for proc, _ in slots:
            if proc.is_alive():
                proc.terminate()  # uvicorn's graceful stop: clients are told to reconnect and resume
        deadline = time.monotonic() + 10.0
        for proc, _ in slots:
            proc.join(max(0.0, deadline - time.monotonic()))
            if proc.is_alive():
                proc.kill()
                proc.join()


def _wait_listening(spec: WorkerSpec, procs: list, stop: threading.Event) -> None:
    """Until every worker has registered its private port (it does once it serves), or one of them died."""
    folder = Path(f"{spec.run_dir}/peers")
    deadline = time.monotonic() + START_TIMEOUT
    while not stop.is_set():
        dead = [p for p in procs if not p.is_alive()]
        if dead:
            raise ServeError(f"a worker process ended while starting (exit {dead[0].exitcode}); see its error above")
        ready = {p.pid for p in procs if (folder / str(p.pid)).exists()}
        if len(ready) == len(procs):
            return
        if time.monotonic() > deadline:
            raise ServeError(f"the workers did not start within {START_TIMEOUT:g} s")
        time.sleep(0.05)


def _scene_names(paths) -> list[str]:
    scenes = load_scenes([Path(p) for p in paths])
    names = list(scenes)
    for store in scenes.values():
        store.close()
    return names


# --------------------------------------------------------------------------- one worker


def _worker(spec: WorkerSpec) -> None:
    """A worker process: its own socket on the replica's port, a private one for its peers, the stores, uvicorn."""
    from .peers import Peers

    logging.basicConfig(level=getattr(logging, spec.log_level.upper(), logging.WARNING))
    public = bind_listener(spec.host, spec.port, spec.limits.send_buffer, reuse_port=True)
    private = bind_listener("127.0.0.1", 0)
    scenes = load_scenes([Path(p) for p in spec.paths])
    peers = Peers(f"{spec.run_dir}/peers")
    app = _app(scenes, spec.config, open_state_store(spec.state_url), spec.limits, spec.admin_token, spec.replica,
               peers)
    server = _uvicorn(app, [public, private], spec.limits, spec.log_level)

    def watch() -> None:  # say where the peers find us once serving; end with the supervisor
        while not server.started and not server.should_exit:
            time.sleep(0.05)
        if server.started:
            peers.register(private.getsockname()[1])
        while not server.should_exit:
            if os.getppid() != spec.parent:
                server.should_exit = True
            time.sleep(0.5)

    threading.Thread(target=watch, name="walkstream-worker-watch", daemon=True).start()
    server.run(sockets=[public, private])
