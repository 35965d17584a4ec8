"""The kiosk left alone, with real parts: ``walkstream kiosk`` as a process, a real server, the delaying proxy.

- the fleet page lists the kiosk, and marks it stale when its process is stopped (SIGSTOP) and live again
  when it continues (SIGCONT) — through ``/fleet.json`` and in Debian's chromium;
- a cut network never gives a black frame: every screenshot of the outage shows the scene;
- the two-minute soak holds every pass line (``walkstream bench soak``'s, run as in CI).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from bench.demo import ServerProcess
from bench.kiosk_config import soak_config
from bench.netem import DelayProxy
from bench.soak import SoakPlan, run

from .test_fleet_browser import browser  # noqa: F401 - the fleet page's chromium fixture
from .sky_pixels import scene_share

ROOT = Path(__file__).resolve().parents[2]
HEARTBEAT_S = 1.0


def _poll(predicate, timeout: float, what: str):
    """Poll ``predicate`` until it returns something truthy; fail naming ``what`` after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        got = predicate()
        if got:
            return got
        time.sleep(0.1)  # polling a server's JSON with a deadline
    pytest.fail(f"{what} did not happen within {timeout:.0f} s")


def _kiosk_row(server: ServerProcess, kiosk: str) -> dict | None:
    rows = httpx.get(f"{server.http}/fleet.json", headers=server.admin_headers, timeout=10).json()["kiosks"]
    return next((r for r in rows if r["kiosk"] == kiosk), None)


def _drawn(path: Path) -> float:
    """The share of a screenshot's pixels that show the scene (not the sky)."""
    from PIL import Image

    return scene_share(np.asarray(Image.open(path).convert("RGB")))


def _start_kiosk(config: Path, tmp_path: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "walkstream", "kiosk", str(config), "--headless",
                             "--duration", "600", *extra], cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=open(tmp_path / "kiosk.log", "w"))


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        os.kill(proc.pid, signal.SIGCONT)
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def test_the_fleet_page_shows_the_kiosk_and_marks_it_stale_while_its_process_is_stopped(demo_store, tmp_path,
                                                                                       browser):  # noqa: F811
    driver = browser
    with ServerProcess([demo_store]) as server:
        config = tmp_path / "kiosk.toml"
        config.write_text(soak_config(demo_store, server.url, kiosk_id="hall-7").replace(
            "heartbeat_s = 5.0", f"heartbeat_s = {HEARTBEAT_S}"))
        kiosk = _start_kiosk(config, tmp_path)
        try:
            row = _poll(lambda: (r := _kiosk_row(server, "hall-7")) and r["frames"] > 0 and not r["stale"] and r,
                        120, "the kiosk's first heartbeat")
            assert row["connected"] and row["tour"] == "soak" and row["interval"] == HEARTBEAT_S
            driver.get(f"{server.http}/fleet?token={server.admin_token}")
            _poll(lambda: "hall-7" in driver.page_source, 30, "the kiosk on the fleet page")
            assert "STALE" not in driver.page_source
            os.kill(kiosk.pid, signal.SIGSTOP)
            stopped = time.monotonic()
            _poll(lambda: (r := _kiosk_row(server, "hall-7")) and r["stale"] and r, 10 * HEARTBEAT_S + 10,
                  "the stale mark")
            # Stale within 2 × the heartbeat of the last advance (plus the poll and one heartbeat in flight).
            assert time.monotonic() - stopped <= 2 * HEARTBEAT_S + HEARTBEAT_S + 3.0
            _poll(lambda: "STALE" in driver.page_source, 30, "STALE on the page (its own reload)")
            os.kill(kiosk.pid, signal.SIGCONT)
            _poll(lambda: (r := _kiosk_row(server, "hall-7")) and not r["stale"] and r, 30,
                  "the kiosk live again after SIGCONT")
        finally:
            _stop(kiosk)


def test_a_cut_network_never_gives_a_black_frame_and_deltas_flow_again(demo_store, tmp_path):
    with ServerProcess([demo_store], admin_token=None) as server, \
            DelayProxy("127.0.0.1", server.port, latency=0.02) as proxy:
        config = tmp_path / "kiosk.toml"
        config.write_text(soak_config(demo_store, f"ws://127.0.0.1:{proxy.port}/ws"))
        status, shots = tmp_path / "status.json", tmp_path / "shots"
        kiosk = _start_kiosk(config, tmp_path, "--status-file", str(status), "--screenshot-every", "0.5",
                             "--screenshot-dir", str(shots))

        def state() -> dict:
            try:
                return json.loads(status.read_text())
            except (OSError, ValueError):
                return {}

        try:
            _poll(lambda: state().get("deltas", 0) > 2, 120, "the kiosk drawing its first deltas")
            before = {p.name for p in shots.glob("*.png")}
            proxy.cut()
            _poll(lambda: not state().get("connected", True), 30, "the kiosk noticing the cut")
            frames, cut = state()["frames"], {p.name for p in shots.glob("*.png")}

            def outage_shots() -> list[Path]:
                return sorted(p for p in shots.glob("*.png") if p.name not in cut)

            _poll(lambda: state().get("frames", 0) > frames + 20 and len(outage_shots()) >= 5, 60,
                  "frames and screenshots during the outage")
            during = outage_shots()[:-1]  # the newest may still be being written
            proxy.restore()
            back, deltas = time.monotonic(), state()["deltas"]
            _poll(lambda: state().get("deltas", 0) > deltas, 30, "deltas after the network's return")
            assert time.monotonic() - back < 10.0
        finally:
            _stop(kiosk)
    assert len(during) >= 4
    drawn = [_drawn(p) for p in during]
    assert min(drawn) > 0.3, drawn  # the held scene, never an empty or black screen


def test_the_two_minute_soak_holds_every_pass_line(demo_store, tmp_path):
    result = run(demo_store, SoakPlan.scaled(120.0), tmp_path / "soak")
    assert result["passed"], json.dumps(result["lines"], indent=1)
    assert len(result["recoveries"]) == 3  # two cuts and the restart, each followed by deltas
    assert Path(result["chart"]).stat().st_size > 10_000
