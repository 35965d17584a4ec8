"""The scale-out topology of ``docker-compose.yml``, as native processes on loopback.

Redis for session state, N ``walkstream serve`` replicas sharing it, and nginx in
front (websocket upgrade, ``hash $arg_client consistent`` so a client stays on
one replica). CI has no Docker engine, so the fault tests and
benchmarks start the same parts from Debian's ``redis-server`` and ``nginx``,
with nginx running ``deploy/nginx.conf`` — the file compose mounts — rewritten
only where loopback differs from compose (addresses, ports, paths, user).

    with Cluster([store]) as cluster:
        run_client(cluster.url, "demo", ...)
        cluster.kill(cluster.which(session_id))
"""

from __future__ import annotations

import os
import re
import secrets
import shutil
import signal
import socket
import subprocess
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Sequence

import httpx

from .demo import ServerProcess

__all__ = ["Cluster", "ClusterError", "RedisProcess", "NGINX_TEMPLATE", "render_nginx_conf", "find_binary"]

#: The load balancer's configuration, shared with docker-compose.yml.
NGINX_TEMPLATE = Path(__file__).resolve().parents[1] / "deploy" / "nginx.conf"
_BOOTSTRAP_HINT = "run scripts/bootstrap.sh (it installs Debian's redis-server and nginx)"


class ClusterError(RuntimeError):
    """A part of the cluster is missing or did not start; the message says which and why."""


def find_binary(name: str) -> str:
    """Path of ``redis-server`` or ``nginx`` (also in the sbin folders, often off a user's PATH)."""
    path = shutil.which(name) or shutil.which(name, path="/usr/sbin:/usr/local/sbin:/sbin")
    if path is None:
        raise ClusterError(f"{name} is not installed: {_BOOTSTRAP_HINT}")
    return path


def _free_port() -> int:
    """A port nothing listens on right now (a child binds it next; a lost race shows up as a start failure)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _sub_once(pattern: str, repl: str, text: str) -> str:
    """Replace exactly one match, so a template edit that breaks the rewrite fails loudly, not silently."""
    out, n = re.subn(pattern, repl, text, flags=re.MULTILINE)
    if n != 1:
        raise ClusterError(f"{NGINX_TEMPLATE} no longer has exactly one match for {pattern!r} ({n}); update bench/cluster.py")
    return out


def render_nginx_conf(template: str, upstreams: Sequence[str], port: int, prefix: Path) -> str:
    """``deploy/nginx.conf`` for loopback: these replicas, this port, files under ``prefix``.

    Every other directive (hashing, upgrade, timeouts, failover) stays as compose runs it.
    """
    block = re.search(r"^([ \t]*)server[ \t]+\S+:\d+([ \t][^;]*)?;\n", template, flags=re.MULTILINE)
    if block is None:
        raise ClusterError(f"{NGINX_TEMPLATE} has no 'server host:port ...;' line in its upstream block")
    indent, params = block.group(1), block.group(2) or ""
    servers = "".join(f"{indent}server {addr}{params};\n" for addr in upstreams)
    text = re.sub(r"^[ \t]*server[ \t]+\S+:\d+([ \t][^;]*)?;\n", "", template, flags=re.MULTILINE)
    text = text[: block.start()] + servers + text[block.start():]
    # Only the master runs as root here; its workers must write the temp folders under prefix (mkdtemp: 0700).
    user = "user root;" if os.geteuid() == 0 else ""
    text = _sub_once(r"^user\s+[^;]*;", user, text)
    text = _sub_once(r"^worker_processes\s+[^;]*;", "worker_processes 1;", text)
    text = _sub_once(r"^pid\s+[^;]*;", f"pid {prefix}/nginx.pid;", text)
    text = _sub_once(r"^([ \t]*)listen\s+80;", rf"\g<1>listen 127.0.0.1:{port};", text)
    text = _sub_once(r"^([ \t]*)access_log\s+[^;]*;", rf"\g<1>access_log {prefix}/access.log;", text)
    for kind in ("client_body", "proxy", "fastcgi", "uwsgi", "scgi"):
        text = _sub_once(rf"^([ \t]*){kind}_temp_path\s+[^;]*;", rf"\g<1>{kind}_temp_path {prefix}/{kind}_temp;", text)
    return text


class _Child:
    """A child process whose output is drained into ``log`` (so it never blocks on a full pipe)."""

    def __init__(self, cmd: list[str], name: str, *, ready: str | None = None, timeout: float = 30.0):
        self.name = name
        self.log: list[str] = []
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self._ready = threading.Event()
        self._marker = ready
        self.ready_seen = False
        self._pump = threading.Thread(target=self._drain, daemon=True)
        self._pump.start()
        if ready is not None and not self._ready.wait(timeout):
            self.close()
            raise ClusterError(f"{name} did not say {ready!r} within {timeout:.0f} s: {self.tail()}")
        if ready is not None and not self.ready_seen:  # its output ended first: it exited
            self.close()
            raise ClusterError(f"{name} exited with {self.proc.returncode}: {self.tail()}")

    def _drain(self) -> None:
        for line in self.proc.stdout:
            self.log.append(line.rstrip())
            if self._marker is not None and self._marker in line:
                self.ready_seen = True
                self._ready.set()
        self._ready.set()  # end of output: wake a waiter so it sees the exit

    def tail(self, n: int = 20) -> str:
        return " | ".join(self.log[-n:])

    def close(self, sig: int = signal.SIGTERM) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._pump.join(5)


class RedisProcess:
    """A throw-away ``redis-server`` on a free loopback port: no persistence, gone on ``close()``.

    Ready when it has said so on its log and answered PING. ``url`` is ``redis://127.0.0.1:PORT/0``.
    """

    def __init__(self, workdir: Path | None = None, *, timeout: float = 30.0):
        binary = find_binary("redis-server")
        self._own_dir = workdir is None
        self.dir = Path(tempfile.mkdtemp(prefix="walkstream-redis-")) if workdir is None else Path(workdir)
        self._child = None
        last: Exception | None = None
        for _ in range(3):  # a port taken between choosing and binding: choose again
            port = _free_port()
            cmd = [binary, "--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
                   "--dir", str(self.dir), "--daemonize", "no", "--loglevel", "notice"]
            try:
                child = _Child(cmd, "redis-server", ready="Ready to accept connections", timeout=timeout)
                break
            except ClusterError as exc:
                last = exc
                if "in use" not in str(exc):
                    self.close()
                    raise
        else:
            self.close()
            raise ClusterError(f"redis-server found no free port: {last}")
        self._child = child
        self.port = port
        self.url = f"redis://127.0.0.1:{port}/0"
        import redis as redis_py

        with redis_py.Redis.from_url(self.url, socket_timeout=5) as client:
            if not client.ping():
                self.close()
                raise ClusterError(f"redis-server at {self.url} does not answer PING")

    def close(self) -> None:
        child = getattr(self, "_child", None)
        if child is not None:
            child.close(signal.SIGTERM)
            self._child = None
        if self._own_dir:
            shutil.rmtree(self.dir, ignore_errors=True)

    def __enter__(self) -> "RedisProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Cluster:
    """Redis, ``replicas`` × ``walkstream serve`` and nginx on loopback; a context manager.

    ``redis=False`` starts replicas that keep sessions in memory (no Redis) behind
    the same nginx: the sticky routing without resume on another replica.

    Attributes: ``url`` (ws:// through nginx), ``http`` (http:// through nginx),
    ``replicas`` (``bench.demo.ServerProcess``, index i is replica ``r{i}``),
    ``redis_url``, ``admin_token``, ``dir`` (nginx's prefix, logs).
    """

    def __init__(self, stores: Sequence[Path], replicas: int = 2, *, tau: float = 0.5, extra: Sequence[str] = (),
                 redis: bool = True, admin_token: str | None = None, timeout: float = 60.0):
        if replicas < 1:
            raise ValueError("a cluster needs at least one replica")
        if redis:
            find_binary("redis-server")
        nginx = find_binary("nginx")
        self.dir = Path(tempfile.mkdtemp(prefix="walkstream-cluster-"))
        self.admin_token = admin_token or secrets.token_urlsafe(24)
        self.redis_url: str | None = None
        self.replicas: list[ServerProcess] = []
        self._redis: RedisProcess | None = None
        self._nginx: _Child | None = None
        self._dead: set[int] = set()
        self._client = httpx.Client(timeout=10.0)  # one pool for the admin and routing look-ups
        try:
            if redis:
                self._start_redis(timeout)
            self._start_replicas(list(stores), replicas, tau, list(extra), timeout)
            self._start_nginx(nginx, timeout)
        except BaseException:
            self.close()
            raise

    # -- starting -------------------------------------------------------------------------------

    def _start_redis(self, timeout: float) -> None:
        self._redis = RedisProcess(self.dir, timeout=timeout)
        self.redis_url = self._redis.url

    def _start_replicas(self, stores: list[Path], n: int, tau: float, extra: list[str], timeout: float) -> None:
        def start(i: int) -> ServerProcess:
            # nginx (on loopback) names each client in X-Real-IP, and the replicas trust it; every simulated
            # client is on loopback too, so one address may hold as many connections as the cluster serves.
            return ServerProcess(stores, extra=["--tau", str(tau), "--trusted-proxy", "127.0.0.1",
                                                "--max-per-address", "100000", "--connect-rate", "1e6", *extra],
                                 admin_token=self.admin_token,
                                 redis=self.redis_url, replica=f"r{i}")

        with ThreadPoolExecutor(n) as pool:  # they import and open stores in parallel
            futures = [pool.submit(start, i) for i in range(n)]
            errors = []
            for f in futures:
                try:
                    self.replicas.append(f.result(timeout))
                except Exception as exc:  # noqa: BLE001 - gathered, the started ones are closed by close()
                    errors.append(exc)
        if errors:
            raise ClusterError(f"a replica did not start: {errors[0]}") from errors[0]

    def _start_nginx(self, binary: str, timeout: float) -> None:
        if not NGINX_TEMPLATE.exists():
            raise ClusterError(f"{NGINX_TEMPLATE} is missing: Cluster runs from a source checkout (pip install -e .)")
        template = NGINX_TEMPLATE.read_text()
        upstreams = [r.http.removeprefix("http://") for r in self.replicas]
        deadline = time.monotonic() + timeout
        for _ in range(3):
            self.port = _free_port()
            conf = self.dir / "nginx.conf"
            conf.write_text(render_nginx_conf(template, upstreams, self.port, self.dir))
            cmd = [binary, "-p", f"{self.dir}/", "-c", str(conf), "-e", "stderr", "-g", "daemon off; error_log stderr;"]
            child = _Child(cmd, "nginx")
            self._nginx = child
            self.http = f"http://127.0.0.1:{self.port}"
            self.url = f"ws://127.0.0.1:{self.port}/ws"
            if self._wait_ready(child, deadline):
                return
            if "Address already in use" not in child.tail():
                raise ClusterError(f"nginx did not start: {child.tail()}")
        raise ClusterError(f"nginx found no free port: {child.tail()}")

    def _wait_ready(self, child: _Child, deadline: float) -> bool:
        """Poll ``/health`` through nginx until it answers (True) or nginx exits (False); bounded by ``deadline``."""
        with httpx.Client(timeout=2.0) as client:
            while time.monotonic() < deadline:
                if child.proc.poll() is not None:
                    child._pump.join(5)
                    return False
                try:
                    if client.get(self.http + "/health").status_code == 200:
                        return True
                except httpx.TransportError:
                    pass
                child._ready.wait(0.02)  # output or exit wakes us; otherwise poll again
        raise ClusterError(f"nginx did not answer /health within the deadline: {child.tail()}")

    # -- looking and breaking -------------------------------------------------------------------

    def _admin(self, i: int) -> dict:
        return dict(self.replicas[i].admin_headers)

    def sessions(self) -> dict[int, list[dict]]:
        """Each live replica's ``/sessions`` (with the admin token)."""
        out = {}
        for i, rep in enumerate(self.replicas):
            if i in self._dead or rep.proc.poll() is not None:
                continue
            resp = self._client.get(rep.http + "/sessions", headers=self._admin(i))
            resp.raise_for_status()
            out[i] = resp.json()
        return out

    def which(self, session_id: str) -> int | None:
        """Index of the replica holding session ``session_id`` right now (None: no live replica does)."""
        for i, sessions in self.sessions().items():
            if any(s.get("session") == session_id for s in sessions):
                return i
        return None

    def route(self, client: str) -> int:
        """Index of the replica nginx sends ``?client=client`` to (from its ``X-Walkstream-Upstream`` header)."""
        resp = self._client.get(self.http + "/health", params={"client": client})
        resp.raise_for_status()
        # After a failover nginx lists every upstream it tried ("a:1, b:2"); the last one answered.
        addr = resp.headers["x-walkstream-upstream"].split(",")[-1].strip()
        for i, rep in enumerate(self.replicas):
            if rep.http.removeprefix("http://") == addr:
                return i
        raise ClusterError(f"nginx answered from {addr}, which is none of the replicas")

    def kill(self, i: int, timeout: float = 10.0) -> None:
        """SIGKILL replica ``i`` (no goodbye to its clients) and wait until it is gone."""
        proc = self.replicas[i].proc
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout)
        self._dead.add(i)

    @property
    def nginx_log(self) -> list[str]:
        return list(self._nginx.log) if self._nginx else []

    # -- lifetime -------------------------------------------------------------------------------

    def close(self) -> None:
        self._client.close()
        if self._nginx is not None:
            self._nginx.close(signal.SIGTERM)
            self._nginx = None
        for rep in self.replicas:
            rep.close()
        if self._redis is not None:
            self._redis.close()
            self._redis = None
        shutil.rmtree(self.dir, ignore_errors=True)

    def __enter__(self) -> "Cluster":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
