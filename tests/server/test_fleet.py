"""The fleet registry on an injected clock: staleness, disconnection, bounds, duplicates and the merge of workers;
the page it renders, and its per-kiosk Prometheus gauges."""

from __future__ import annotations

import re
from html.parser import HTMLParser

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.parser import text_string_to_metric_families

from proto.messages import Heartbeat
from server.fleet import STALE_INTERVALS, Fleet, merge
from server.fleet_page import render, sparkline
from server.metrics import FleetCollector


def beat(kiosk="hall-1", frames=0, interval=1.0, **kw) -> Heartbeat:
    return Heartbeat(kiosk=kiosk, t=0.0, frames=frames, interval=interval, **kw)


def row(fleet: Fleet, now: float, kiosk="hall-1") -> dict:
    (found,) = [r for r in fleet.rows(now) if r["kiosk"] == kiosk]
    return found


# ----------------------------------------------------------------------------- staleness


def test_a_kiosk_whose_frames_advance_is_never_stale():
    f = Fleet()
    for i in range(20):
        f.heard("s1", beat(frames=60 * i), now=float(i))
        assert not row(f, float(i) + 1.9)["stale"]


def test_frames_that_stop_advancing_make_the_kiosk_stale_after_two_intervals_though_it_still_reports():
    f = Fleet()
    f.heard("s1", beat(frames=100), now=0.0)
    f.heard("s1", beat(frames=160), now=1.0)
    for t in (2.0, 2.5, 3.0):  # the renderer stuck: heartbeats go on, frames do not
        f.heard("s1", beat(frames=160), now=t)
    assert not row(f, 3.0)["stale"]  # exactly 2 intervals since the advance: not yet
    r = row(f, 3.01)
    assert r["stale"] and r["connected"] and r["advanced_s"] == pytest.approx(2.01) and r["heard_s"] == 0.01
    f.heard("s1", beat(frames=161), now=3.5)  # drawing again
    assert not row(f, 3.5)["stale"]


def test_a_silent_kiosk_is_stale_after_two_of_its_own_intervals():
    f = Fleet()
    f.heard("s1", beat(frames=10, interval=5.0), now=0.0)
    assert not row(f, 10.0)["stale"]
    assert row(f, 10.001)["stale"]


def test_the_first_heartbeat_counts_as_an_advance():
    f = Fleet()
    f.heard("s1", beat(frames=0), now=50.0)
    assert not row(f, 51.0)["stale"] and row(f, 52.5)["stale"]


def test_frames_going_back_count_a_restart_and_an_advance():
    f = Fleet()
    f.heard("s1", beat(frames=900), now=0.0)
    f.heard("s1", beat(frames=900), now=1.5)
    f.heard("s2", beat(frames=3), now=1.9)
    r = row(f, 3.0)
    assert r["restarts"] == 1 and not r["stale"] and r["session"] == "s2"


# ----------------------------------------------------------------------------- disconnection and bounds


def test_a_closed_session_leaves_its_kiosk_listed_disconnected_then_forgotten():
    f = Fleet(forget_after=100.0)
    f.heard("s1", beat(tour="harbour", stop=2), now=0.0)
    f.closed("s1", now=1.0)
    r = row(f, 5.0)
    assert not r["connected"] and r["gone_s"] == 4.0 and r["stale"] and r["tour"] == "harbour"
    assert [r["kiosk"] for r in f.rows(100.0)] == ["hall-1"]
    assert f.rows(100.01) == []


def test_a_closed_session_that_was_not_the_kiosks_does_not_disconnect_it():
    f = Fleet()
    f.heard("s1", beat(), now=0.0)
    f.closed("other", now=0.5)
    assert row(f, 0.5)["connected"]


def test_disconnected_kiosks_beyond_keep_gone_are_forgotten_longest_silent_first():
    f = Fleet(keep_gone=2)
    for i in range(4):
        f.heard(f"s{i}", beat(kiosk=f"k{i}"), now=float(i))
    f.heard("live", beat(kiosk="live"), now=0.0)
    for i in range(4):
        f.closed(f"s{i}", now=10.0)
    assert [r["kiosk"] for r in f.rows(10.0)] == ["k2", "k3", "live"]


def test_history_and_frame_times_are_bounded():
    f = Fleet(history=5, recent=7)
    for i in range(20):
        f.heard("s1", beat(frames=i, frame_p95=i / 1000, recent=[i / 1000] * 3, rss=i), now=float(i))
    r = row(f, 20.0)
    assert r["frame_p95_history"] == [i / 1000 for i in range(15, 20)]
    assert r["rss_history"] == list(range(15, 20)) and len(r["frame_times"]) == 7
    assert r["frame_times"][-1] == 0.019 and r["heartbeats"] == 20


@pytest.mark.parametrize("bad", [dict(history=0), dict(recent=0), dict(keep_gone=-1), dict(forget_after=0.0)])
def test_bad_bounds_are_refused_naming_the_field(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        Fleet(**bad)


events = st.lists(st.tuples(st.sampled_from(["beat", "close"]), st.integers(0, 5), st.integers(0, 3),
                            st.floats(0.0, 50.0), st.integers(0, 3)), max_size=60)


@settings(max_examples=200, deadline=None)
@given(events, st.integers(0, 3))
def test_rows_never_outnumber_live_sessions_plus_keep_gone(script, keep_gone):
    """Whatever the order of heartbeats and closes, the fleet (and so the gauges' label values) stays bounded:
    a connected kiosk has a live session reporting it, and at most ``keep_gone`` others are kept."""
    f = Fleet(keep_gone=keep_gone, history=4, recent=4)
    live: dict[str, str] = {}  # session → its kiosk (one each: a session reports one id)
    now = 0.0
    for kind, s, k, dt, frames in script:
        now += dt
        sid = f"s{s}"
        if kind == "beat":
            kiosk = live.setdefault(sid, f"k{k}")
            f.heard(sid, beat(kiosk=kiosk, frames=frames, recent=[0.01] * 3), now)
        else:
            live.pop(sid, None)
            f.closed(sid, now)
        rows = f.rows(now)
        connected = [r for r in rows if r["connected"]]
        assert len(connected) <= len(set(live.values()))
        assert len(rows) - len(connected) <= keep_gone
        assert all(len(r["frame_times"]) <= 4 and len(r["rss_history"]) <= 4 for r in rows)
        for r in rows:  # stale is exactly "no advance within 2 × interval" (ages are rounded to the ms)
            margin = r["advanced_s"] - STALE_INTERVALS * r["interval"]
            assert abs(margin) < 1e-3 or r["stale"] == (margin > 0)


# ----------------------------------------------------------------------------- duplicates and workers


def test_two_live_sessions_reporting_one_id_mark_it_duplicate_until_one_ends():
    f = Fleet()
    f.heard("a", beat(frames=1), now=0.0)
    f.heard("b", beat(frames=500), now=0.5)
    r = row(f, 0.6)
    assert r["duplicate"] and r["session"] == "b"
    f.closed("b", now=0.7)
    f.heard("a", beat(frames=2), now=1.0)
    assert not row(f, 1.0)["duplicate"] and row(f, 1.0)["connected"]


def test_a_claim_that_fell_silent_is_not_a_duplicate():
    f = Fleet()
    f.heard("old", beat(frames=1), now=0.0)  # its connection half-open, not yet noticed dead
    f.heard("new", beat(frames=2), now=5.0)
    assert not row(f, 5.0)["duplicate"]


def test_merge_keeps_the_connected_row_heard_last_and_marks_one_live_on_two_workers():
    def part(worker, connected, heard):
        return {"kiosks": [{"kiosk": "k", "connected": connected, "heard_s": heard, "interval": 1.0,
                            "duplicate": False, "worker": worker}],
                "sessions": [{"session": f"s{worker}", "kiosk": "k"}]}

    moved = merge([part(1, False, 0.1), part(2, True, 0.5)])
    assert [k["worker"] for k in moved["kiosks"]] == [2] and not moved["kiosks"][0]["duplicate"]
    assert len(moved["sessions"]) == 2
    twice = merge([part(1, True, 0.4), part(2, True, 0.2)])
    assert twice["kiosks"][0]["worker"] == 2 and twice["kiosks"][0]["duplicate"]


# ----------------------------------------------------------------------------- the page


class _Page(HTMLParser):
    def __init__(self):
        super().__init__()
        self.tags, self.text = [], []

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))

    def handle_data(self, data):
        self.text.append(data)


def _parse(page: str) -> _Page:
    p = _Page()
    p.feed(page)
    return p


def test_the_page_escapes_what_clients_sent_and_marks_stale_kiosks():
    f = Fleet()
    f.heard("s1", beat(kiosk="lobby", tour="<script>alert(1)</script>", stop=3, frames=5,
                       recent=[0.01, 0.02, 0.015], rss=300 << 20), now=0.0)
    data = merge([{"kiosks": f.rows(10.0), "sessions": [{"session": "s1", "kiosk": "lobby", "scene": "<b>x"}]}])
    page = render(data, "replica & co")
    parsed = _parse(page)
    assert "<script>" not in page and "&lt;script&gt;alert(1)&lt;/script&gt; · stop 3" in page
    assert ("meta", {"http-equiv": "refresh", "content": "3"}) in parsed.tags
    frame_times = next(a for t, a in parsed.tags if t == "polyline")  # the first: the kiosk's frame times
    assert len(frame_times["points"].split()) == 3
    assert "STALE" in parsed.text and "replica &amp; co" in page and "&lt;b&gt;x" in page


def test_an_empty_fleet_says_so():
    page = render({"kiosks": [], "sessions": []}, "r")
    assert "no kiosk has reported yet" in page and "no live session" in page


def test_a_sparkline_spans_its_box_and_puts_the_largest_value_at_the_top():
    svg = sparkline([0.0, 0.5, 1.0, float("nan")], width=100, height=20)
    xy = [tuple(map(float, p.split(","))) for p in re.search(r'points="([^"]*)"', svg).group(1).split()]
    assert [x for x, _ in xy] == [1.0, 50.0, 99.0] and xy[0][1] == 19.0 and xy[2][1] == 1.0
    assert "polyline" not in sparkline([])


# ----------------------------------------------------------------------------- the gauges


def _scrape(registry) -> dict:
    out = {}
    for family in text_string_to_metric_families(generate_latest(registry).decode()):
        for s in family.samples:
            out[(s.name, s.labels.get("kiosk"))] = s.value
    return out


def test_per_kiosk_gauges_follow_the_fleet_and_end_with_a_forgotten_kiosk():
    f = Fleet(keep_gone=0)
    clock = {"now": 0.0}
    registry = CollectorRegistry()
    FleetCollector(lambda: f.rows(clock["now"]), registry=registry)
    f.heard("s1", beat(kiosk="a", frames=9, fps=58.5, frame_p95=0.021, rss=123, cache_bytes=456,
                       reconnects=2), now=0.0)
    f.heard("s2", beat(kiosk="b", frames=1, gpu_memory=789), now=0.0)
    clock["now"] = 1.0
    got = _scrape(registry)
    assert got[("walkstream_kiosk_fps", "a")] == 58.5 and got[("walkstream_kiosk_frame_p95_seconds", "a")] == 0.021
    assert got[("walkstream_kiosk_rss_bytes", "a")] == 123 and got[("walkstream_kiosk_cache_bytes", "a")] == 456
    assert got[("walkstream_kiosk_reconnects", "a")] == 2 and got[("walkstream_kiosk_stale", "a")] == 0
    assert ("walkstream_kiosk_gpu_memory_bytes", "a") not in got  # its driver does not tell
    assert got[("walkstream_kiosk_gpu_memory_bytes", "b")] == 789
    clock["now"] = 2.5
    assert _scrape(registry)[("walkstream_kiosk_stale", "a")] == 1
    f.closed("s1", now=3.0)  # keep_gone=0: forgotten at once
    got = _scrape(registry)
    assert not [key for key in got if key[1] == "a"] and got[("walkstream_kiosk_frames", "b")] == 1
