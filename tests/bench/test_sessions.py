"""``walkstream bench sessions``: the server's CPU by part, scripted sessions in one process."""

from __future__ import annotations

import json
import subprocess
import sys

from bench.sessions import PARTS, run


def test_every_part_is_measured_and_saves_keep_their_interval(denhaag_store):
    out = run(denhaag_store, clients=3, seconds=4.0, repeats=1, save_interval=1.0)
    (row,) = out["runs"]
    for name, _ in PARTS:
        assert out["parts"][name]["ms"] > 0, name
    assert out["parts"]["total"]["ms"] >= sum(out["parts"][name]["ms"] for name, _ in PARTS) * (1 - 1e-9)
    assert row["deltas"] >= 3 * 6  # a reset and then one every τ = 0.5 s, per session
    # At most one snapshot a second per session (4 s each, less the stagger), and one whenever it changed.
    assert 3 * 3 <= row["saves"] <= 3 * 5
    often = run(denhaag_store, clients=3, seconds=4.0, repeats=1, save_interval=0.25)
    assert often["runs"][0]["saves"] >= 3 * 12
    assert out["sessions_per_core"] > 0 and out["calibration_ms"] > 0


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "walkstream", "bench", "sessions", *args], capture_output=True,
                          text=True, timeout=300)


def test_the_command_prints_its_table_and_json(denhaag_store):
    out = _cli("--store", str(denhaag_store), "--clients", "2", "--seconds", "2", "--repeats", "1", "--json")
    assert out.returncode == 0, out.stderr[-2000:]
    figures = json.loads(out.stdout.strip().splitlines()[-1])
    assert figures["clients"] == 2 and figures["parts"]["selection and delta"]["ms"] > 0
    assert "sessions per core" in out.stderr


def test_a_missing_store_is_one_line_naming_it(tmp_path):
    out = _cli("--store", str(tmp_path / "nope.db"))
    assert out.returncode == 2
    assert "no such store" in out.stderr and "Traceback" not in out.stderr
