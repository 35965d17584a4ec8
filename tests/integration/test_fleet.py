"""The fleet against a real ``walkstream serve``: kiosks' heartbeats over real websockets show in ``/fleet.json``,
``/fleet`` and ``/metrics``; a kiosk whose frames or heartbeats stop is marked stale; the admin token guards
the views; a replica of several workers shows every worker's kiosks. Waits poll the server with a deadline."""

from __future__ import annotations

import time

import httpx
import pytest
from prometheus_client.parser import text_string_to_metric_families

from bench.demo import ServerProcess
from proto.codec import encode

from .kiosk_stub import KioskStub


def fleet(srv, **params) -> dict:
    r = httpx.get(srv.http + "/fleet.json", headers=srv.admin_headers, params=params, timeout=10)
    r.raise_for_status()
    return r.json()


def kiosk_row(srv, kiosk: str) -> dict | None:
    return next((k for k in fleet(srv)["kiosks"] if k["kiosk"] == kiosk), None)


def wait_for(what: str, probe, timeout: float = 20.0):
    """``probe()`` polled until it returns something truthy, which is returned; fails after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while True:
        got = probe()
        if got:
            return got
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(0.1)  # between two polls of the server, not a synchronisation


def gauges(srv) -> dict[tuple[str, str | None], float]:
    text = httpx.get(srv.http + "/metrics", timeout=10).text
    return {(s.name, s.labels.get("kiosk")): s.value
            for family in text_string_to_metric_families(text) for s in family.samples}


@pytest.fixture(scope="module")
def server(demo_store):
    with ServerProcess([demo_store], replica="fleet-test") as srv:
        yield srv


def test_a_kiosks_heartbeats_show_in_the_json_and_the_metrics_and_stop_as_stale(server):
    with KioskStub(server.url, "lobby-1", interval=0.5, tour="harbour", stop=2) as kiosk:
        row = wait_for("three heartbeats of lobby-1",
                       lambda: (r := kiosk_row(server, "lobby-1")) and r["heartbeats"] >= 3 and r)
        assert row["session"] == kiosk.session and row["connected"] and not row["stale"] and not row["duplicate"]
        assert (row["tour"], row["stop"], row["state"], row["fps"], row["reconnects"]) == ("harbour", 2, "attract",
                                                                                           60.0, 1)
        assert row["rss"] >= 200 << 20 and row["cache_bytes"] >= 32 << 20 and row["gpu_memory"] is None
        assert len(row["frame_times"]) >= 36 and len(row["frame_p95_history"]) == row["heartbeats"]
        assert 0.018 <= row["frame_p95"] <= 0.022 and row["heard_s"] < 1.0
        listed = {s["session"]: s for s in fleet(server)["sessions"]}
        assert listed[kiosk.session]["kiosk"] == "lobby-1" and listed[kiosk.session]["scene"] == "demo"
        metrics = wait_for("the kiosk's gauges", lambda: (g := gauges(server)).get(
            ("walkstream_kiosk_fps", "lobby-1")) and g)
        assert metrics[("walkstream_kiosk_fps", "lobby-1")] == 60.0
        assert metrics[("walkstream_kiosk_stale", "lobby-1")] == 0
        assert metrics[("walkstream_kiosk_reconnects", "lobby-1")] == 1
        assert metrics[("walkstream_kiosk_connected", "lobby-1")] == 1
        assert metrics[("walkstream_heartbeats_total", None)] >= 3

        # The renderer hangs while the process goes on reporting: stale, though heard a moment ago.
        kiosk.drawing.clear()
        row = wait_for("lobby-1 stale with frames stopped", lambda: (r := kiosk_row(server, "lobby-1"))["stale"] and r)
        # Stale once its frames are over 2 intervals old; advanced_s, rounded to the millisecond, is then ≥ 1.0 s.
        assert row["heard_s"] < 1.0 and row["advanced_s"] >= 1.0 and row["connected"]
        assert gauges(server)[("walkstream_kiosk_stale", "lobby-1")] == 1
        kiosk.drawing.set()
        wait_for("lobby-1 drawing again", lambda: not kiosk_row(server, "lobby-1")["stale"])

        # The process stops (its socket still answers pings): no heartbeat, so no advance either.
        kiosk.beating.clear()
        row = wait_for("lobby-1 stale with heartbeats stopped",
                       lambda: (r := kiosk_row(server, "lobby-1"))["stale"] and r)
        # Stale once its last heartbeat (which advanced the frames) is over 2 intervals old: heard_s, rounded to
        # the millisecond, is then at least 1.0 s.
        assert row["heard_s"] >= 1.0 and row["connected"]
        assert kiosk.errors == []
    # Its session ended: still listed, disconnected, so a dead kiosk stays in sight.
    row = wait_for("lobby-1 disconnected", lambda: not (r := kiosk_row(server, "lobby-1"))["connected"] and r)
    assert row["stale"] and row["gone_s"] is not None and row["tour"] == "harbour"
    assert kiosk.session not in {s["session"] for s in fleet(server)["sessions"]}
    assert gauges(server)[("walkstream_kiosk_connected", "lobby-1")] == 0


def test_one_id_on_two_sessions_is_marked_duplicate_and_a_session_keeps_its_first_id(server):
    with KioskStub(server.url, "twin", interval=0.5) as a, KioskStub(server.url, "twin", interval=0.5) as b:
        row = wait_for("twin marked duplicate", lambda: (r := kiosk_row(server, "twin")) and r["duplicate"] and r)
        assert row["session"] in (a.session, b.session)
        a.ws.send(encode(a.heartbeat(kiosk="another")))
        refused = wait_for("the second id refused", lambda: a.errors)
        assert refused[0].code == "bad_state" and "another" in refused[0].message
        assert kiosk_row(server, "another") is None
        b.close()
        wait_for("twin no longer duplicate", lambda: not kiosk_row(server, "twin")["duplicate"])


def test_the_views_need_the_admin_token_and_a_browser_may_give_it_once(server):
    url = server.http
    assert httpx.get(url + "/fleet", timeout=10).status_code == 401
    assert httpx.get(url + "/fleet.json", timeout=10).status_code == 401
    wrong = "x" * len(server.admin_token)
    assert httpx.get(url + "/fleet", params={"token": wrong}, timeout=10).status_code == 401
    assert httpx.get(url + "/fleet.json", headers={"Authorization": f"Bearer {wrong}"}, timeout=10).status_code == 401
    assert httpx.get(url + "/fleet.json", params={"token": server.admin_token}, timeout=10).status_code == 200
    with httpx.Client(base_url=url, timeout=10) as browser:
        first = browser.get("/fleet", params={"token": server.admin_token})
        assert first.status_code == 303 and first.headers["location"] == "fleet"  # the token out of the URL
        cookie = first.headers["set-cookie"].lower()
        assert "httponly" in cookie and "samesite=strict" in cookie and server.admin_token.lower() not in cookie
        page = browser.get("/fleet")
        assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
        assert "Fleet of fleet-test" in page.text and 'http-equiv="refresh"' in page.text
        assert browser.get("/fleet.json").status_code == 200
        # The cookie opens the read-only views only.
        assert browser.get("/sessions").status_code == 401


@pytest.fixture()
def replica(demo_store):
    with ServerProcess([demo_store], workers=2) as srv:
        yield srv


def test_a_replica_of_two_workers_shows_every_workers_kiosks(replica):
    kiosks = [KioskStub(replica.url, f"k{i:02d}", interval=1.0) for i in range(12)]
    try:
        names = {k.kiosk for k in kiosks}
        rows = wait_for("every kiosk listed", lambda: (f := fleet(replica)) and
                        {r["kiosk"] for r in f["kiosks"]} == names and f["kiosks"])
        # The kernel spreads connections over both workers; whichever answers lists them all.
        assert len({r["worker"] for r in rows}) == 2
        sessions = fleet(replica)["sessions"]
        assert {s["kiosk"] for s in sessions} == names and len({s["worker"] for s in sessions}) == 2
        assert {r["kiosk"] for r in fleet(replica, local=1)["kiosks"]} < names  # one worker's share alone
        wait_for("every kiosk's gauges, whichever worker answers the scrape",
                 lambda: all({n for (m, n) in gauges(replica) if m == "walkstream_kiosk_frames"} == names
                             for _ in range(4)))
        kiosks.pop().close()
        wait_for("the closed kiosk disconnected in the replica's view", lambda: not next(
            r for r in fleet(replica)["kiosks"] if r["kiosk"] == "k11")["connected"])
    finally:
        for k in kiosks:
            k.close()
