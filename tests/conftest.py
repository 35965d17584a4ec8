"""Shared fixtures: small real scene stores built once per test session."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import settings

# CI explores the same examples every run (a failure there reproduces); locally they vary.
settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session", autouse=True)
def _compiled_kernels_ready():
    """In-process sessions use the compiled selection kernels from their first selection, as a server does
    (``server.app.serve`` waits for them): a switch mid-session from the numpy path could flip a tie."""
    from server.select import kernels

    kernels.warm_up(timeout=600, setting=os.environ.get("WALKSTREAM_NUMBA"))


@pytest.fixture(scope="session")
def demo_store(tmp_path_factory) -> Path:
    """A small demo scene (same generator as ``walkstream build demo``), built once."""
    from server.scene.demo import build_demo

    path = tmp_path_factory.mktemp("scenes") / "demo-small.db"
    build_demo(path, objects=24, seed=3)
    return path


@pytest.fixture(scope="session")
def denhaag_store(tmp_path_factory) -> Path:
    """A small Den Haag: buildings under an HLOD tree, a TIN terrain and tree groups, built once."""
    from server.scene.catalog import build_named

    path = tmp_path_factory.mktemp("scenes") / "denhaag-small.db"
    build_named("denhaag", path, seed=0, size=400)
    return path


@pytest.fixture(scope="session")
def city_store(tmp_path_factory) -> Path:
    """A small synthetic city (``tests.city``) built as a user's file is: walk (its default), flyover, orbit."""
    from server.scene.builder import BuildOptions, build_store
    from tests.city import city_source

    source, _ = city_source()
    path = tmp_path_factory.mktemp("scenes") / "city.db"
    build_store(path, source, name="city", options=BuildOptions(workers=1, shape_guard=False), default_tour="walk")
    return path


@pytest.fixture(scope="session")
def auditorium_store(tmp_path_factory) -> Path:
    """The auditorium (``walkstream build auditorium``, seed 0): 440 chairs, 2.5 M triangles, built once (~12 s)."""
    from server.scene.catalog import build_named

    path = tmp_path_factory.mktemp("scenes") / "auditorium.db"
    build_named("auditorium", path, seed=0)
    return path


@pytest.fixture(scope="session")
def redis_url(tmp_path_factory):
    """A real redis-server on a free loopback port (no persistence), ready when yielded; stopped after."""
    import shutil
    import socket
    import subprocess
    import threading

    exe = shutil.which("redis-server") or "/usr/bin/redis-server"
    if not Path(exe).exists():
        pytest.skip("redis-server is not installed (apt-get install redis-server)")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen(
        [exe, "--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
         "--dir", str(tmp_path_factory.mktemp("redis"))],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    ready = threading.Event()
    log: list[str] = []

    def drain() -> None:  # read the log (so the pipe never fills) and signal readiness
        for line in proc.stdout:
            log.append(line)
            if "Ready to accept connections" in line:
                ready.set()
        ready.set()  # exited

    threading.Thread(target=drain, daemon=True).start()
    try:
        if not ready.wait(10.0) or proc.poll() is not None:
            raise RuntimeError(f"redis-server did not start on port {port}:\n{''.join(log)}")
        import redis

        client = redis.Redis(host="127.0.0.1", port=port, socket_connect_timeout=5)
        assert client.ping() is True
        client.close()
        yield f"redis://127.0.0.1:{port}/0"
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
