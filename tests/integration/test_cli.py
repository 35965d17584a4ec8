"""The command line as a user runs it: real processes, real output."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from server.scene.store import SceneStore


def _walkstream(*args: str, cwd: Path | None = None, timeout: float = 240) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "walkstream", *args], capture_output=True, text=True, timeout=timeout,
                          cwd=cwd)


def test_build_demo_writes_a_store_and_reports_it(tmp_path):
    out = tmp_path / "tiny.db"
    done = _walkstream("build", "demo", "-o", str(out), "--objects", "6", "--seed", "1")
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    with SceneStore.open(out) as store:
        assert summary["representations"] == store.index.n_representations
        assert (store.index.rep_count >= 3).all()


def test_bad_arguments_fail_with_a_clear_message(tmp_path):
    done = _walkstream("build", "moon", "-o", str(tmp_path / "x.db"))
    said = " ".join(done.stderr.replace("│", " ").split())  # rich wraps the message in a box
    assert done.returncode == 2 and "'moon' is neither a named scene" in said and "auditorium" in said
    assert not (tmp_path / "x.db").exists()
    done = _walkstream("build", "megacity", "--grid", "2049", "-o", str(tmp_path / "x.db"))
    said = " ".join(done.stderr.replace("│", " ").split())
    assert done.returncode == 2 and "--grid" in said and "sthelens" in said and not (tmp_path / "x.db").exists()
    done = _walkstream("serve", str(tmp_path / "missing.db"))
    assert done.returncode == 2 and "no such store" in done.stderr
    for cmd in ("client", "demo"):
        done = _walkstream(cmd, "--hold", "p100:1.1")
        said = " ".join(done.stderr.replace("│", " ").split())
        assert done.returncode == 2 and "--hold" in said and "share in [0.5, 1)" in said, done.stderr
        done = _walkstream(cmd, "--hold", "99%")
        said = " ".join(done.stderr.replace("│", " ").split())
        assert done.returncode == 2 and "pNN:BOUND" in said and "'99%'" in said, done.stderr
    done = _walkstream("client", "--solver", "fastest")
    said = " ".join(done.stderr.replace("│", " ").split())
    assert done.returncode == 2 and "unknown solver 'fastest'" in said and "hierarchical" in said
    not_a_store = tmp_path / "text.db"
    not_a_store.write_text("hello")
    done = _walkstream("serve", str(not_a_store), "--port", "0")
    assert done.returncode == 2 and str(not_a_store) in done.stderr


def test_demo_json_reports_the_loop(demo_store, tmp_path):
    done = _walkstream("demo", "--store", str(demo_store), "--duration", "4", "--target-ms", "12",
                       "--width", "320", "--height", "180", "--json", "--out", str(tmp_path),
                       "--solver", "optimization")
    assert done.returncode == 0, done.stderr
    figures = json.loads(done.stdout.strip().splitlines()[-1])
    for key in ("frames", "target_ms", "mean_ms", "p95_ms", "max_ms", "cost_coeff", "chart"):
        assert key in figures
    assert figures["frames"] > 10 and figures["target_ms"] == 12.0 and figures["errors"] == 0
    assert figures["solver"] == "optimization" and figures["hold"] == "p95:1.3"  # the demo's own line
    assert Path(figures["chart"]).stat().st_size > 10_000  # a PNG with a plot in it
    assert "frames" in done.stderr and "c_vertex" in done.stderr  # the per-second lines


def test_bench_build_reports_figures_against_its_reference(tmp_path):
    done = _walkstream("bench", "build", "--scene", "auditorium", "--keep", str(tmp_path), "--json")
    assert done.returncode == 0, done.stderr
    figures = json.loads(done.stdout.strip().splitlines()[-1])
    (scene,) = figures["scenes"]
    assert scene["scene"] == "auditorium" and figures["reference_simplifier_tris_per_s"] > 0
    with SceneStore.open(tmp_path / "auditorium.db") as store:
        full = store.index.rep_first + store.index.rep_count - 1
        assert scene["triangles"] == int(store.index.rep_faces[full].sum())
    assert scene["store_bytes"] == (tmp_path / "auditorium.db").stat().st_size
    assert scene["triangles_per_s"] == pytest.approx(scene["triangles"] / scene["build_s"], rel=0.01)
    assert 0 < scene["index_load_s"] < 5 and scene["ratio_to_simplifier"] > 0


def _one_line_error(done: subprocess.CompletedProcess, *names: str) -> str:
    """The run failed as a user's error: status 2, one line on stderr naming each of ``names``, no traceback."""
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2, (done.returncode, done.stderr)
    assert len(lines) == 1 and lines[0].startswith("error: "), done.stderr
    assert "Traceback" not in done.stderr
    for name in names:
        assert name in lines[0], (name, lines[0])
    return lines[0]


def test_build_never_overwrites_its_input_nor_a_store_without_force(tmp_path, demo_store):
    city = tmp_path / "self.city.json"
    city.write_text('{"type": "CityJSON"}')
    _one_line_error(_walkstream("build", str(city), "-o", str(city)), str(city), "is the input")
    assert city.read_text() == '{"type": "CityJSON"}'
    _one_line_error(_walkstream("build", str(tmp_path)), str(tmp_path), "directory")
    existing = tmp_path / "kept.db"
    existing.write_bytes(b"mine")
    _one_line_error(_walkstream("build", "demo", "--objects", "4", "-o", str(existing)), str(existing), "--force")
    assert existing.read_bytes() == b"mine"
    done = _walkstream("build", "demo", "--objects", "4", "-q", "-o", str(existing), "--force")
    assert done.returncode == 0, done.stderr
    with SceneStore.open(existing) as store:
        assert store.index.n_objects >= 4


def test_serve_errors_are_one_line_and_the_port_is_checked_first(tmp_path, demo_store):
    import socket

    not_a_store = tmp_path / "text.db"
    not_a_store.write_text("hello")
    holder = socket.socket()
    holder.bind(("127.0.0.1", 0))
    holder.listen()
    port = holder.getsockname()[1]
    try:
        busy = _walkstream("serve", str(demo_store), "--port", str(port))
        # Checked before any store is opened: the broken store is never reached.
        busy_broken = _walkstream("serve", str(not_a_store), "--port", str(port))
    finally:
        holder.close()
    _one_line_error(busy, f"127.0.0.1:{port}", "in use")
    _one_line_error(busy_broken, f"127.0.0.1:{port}", "in use")
    _one_line_error(_walkstream("serve", str(demo_store), str(demo_store)), str(demo_store), "twice")
    other = tmp_path / "copy.db"
    other.write_bytes(demo_store.read_bytes())
    _one_line_error(_walkstream("serve", str(demo_store), str(other), "--port", "0"), "'demo'", str(other))


@pytest.mark.parametrize("url, names", [
    ("ws://127.0.0.1:99999/ws", ["ws://127.0.0.1:99999/ws", "Port out of range"]),
    ("ws://[::1", ["ws://[::1", "IPv6"]),
    ("ws://127.0.0.1:8765/", ["ws://127.0.0.1:8765/", "/ws", "try 'ws://127.0.0.1:8765/ws'"]),
    ("http://127.0.0.1:8765/ws", ["http://127.0.0.1:8765/ws", "ws://"]),
])
def test_client_refuses_a_bad_url_in_one_line(url, names):
    _one_line_error(_walkstream("client", url, "--duration", "1"), *names)


def test_an_unexpected_failure_is_one_line_and_debug_shows_its_traceback(demo_store, monkeypatch, capsys):
    """A failure no check foresaw (here a fault put into the store reader) is one line and exit status 2;
    ``--debug``, anywhere on the line, lets it through with its traceback."""
    import server.scene.inspect as inspect_module
    from walkstream.cli import main

    def broken(path):
        raise RuntimeError(f"the reader broke on {path}")

    monkeypatch.setattr(inspect_module, "inspect_store", broken)
    with pytest.raises(SystemExit) as ended:
        main(["inspect", str(demo_store)])
    err = capsys.readouterr().err
    assert ended.value.code == 2
    assert err.count("\n") == 1 and "Traceback" not in err
    assert "RuntimeError" in err and str(demo_store) in err and "--debug" in err
    with pytest.raises(RuntimeError, match="the reader broke"):
        main(["inspect", "--debug", str(demo_store)])
    with pytest.raises(RuntimeError, match="the reader broke"):
        main(["--debug", "inspect", str(demo_store)])
