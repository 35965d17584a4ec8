"""``walkstream bench hostile``: one good client beside each attack on a real replica.

A real ``walkstream serve`` in its own process, one real headless client
(``client.app.run_client``) following the scene's tour, and in turn each
attack a hostile or careless client can mount: holding connections without a
hello, a camera teleporting on every message, asking for the exact solver, a
flood of oversized frames, a flood of invalid frames. Each attack runs for the
good client's whole run, and is compared with a run without attack measured
in the same process just before (the reference), so the figures are ratios
on whatever machine runs them.

Per attack: the good session's deltas against the reference, the share of
them on time, its frame p95, the server's CPU seconds and peak RSS against
its RSS before, whether a new client could say hello meanwhile, and how long
the server took to go idle after the attack stopped.
"""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import msgpack

from proto import PROTOCOL_VERSION
from proto.codec import MAX_CLIENT_FRAME, decode_server, encode
from proto.messages import Camera, Hello, Welcome

__all__ = ["ATTACKS", "run", "format_table"]

_TICKS = os.sysconf("SC_CLK_TCK")
_PAGE = os.sysconf("SC_PAGE_SIZE")

#: The pass lines (the issue's): deltas against the reference, deltas on time, RSS growth, idle after.
MIN_DELTA_SHARE, MIN_ON_TIME, MAX_RSS_GROWTH, MAX_IDLE_S = 0.95, 0.99, 50 * 2**20, 1.0


def _cpu_seconds(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / _TICKS


def _rss(pid: int) -> int:
    with open(f"/proc/{pid}/statm") as f:
        return int(f.read().split()[1]) * _PAGE


def _hello(**fields) -> bytes:
    return encode(Hello(**{"protocol": PROTOCOL_VERSION, "scene": "demo", "viewport": [64, 64], **fields}))


def _connect(url: str, **kw):
    from websockets.sync.client import connect

    return connect(url, open_timeout=5, close_timeout=0.5, max_size=None, compression=None, legacy=True, **kw)


def _loop(stop: threading.Event, body: Callable[[], None]) -> None:
    """Run ``body`` until ``stop``; a closed or refused connection is simply opened again (attackers persist)."""
    while not stop.is_set():
        try:
            body()
        except Exception:
            stop.wait(0.05)


# ----------------------------------------------------------------------------- the attacks


def slot_holding(url: str, scene: str, stop: threading.Event, n: int = 40) -> list[threading.Thread]:
    """``n`` connections that never say hello, each sending one invalid byte every half second."""
    def one() -> None:
        with _connect(url) as ws:
            while not stop.is_set():
                ws.send(b"\xc1")
                stop.wait(0.5)
                while True:  # read what came (refusals), without waiting
                    try:
                        ws.recv(timeout=0)
                    except TimeoutError:
                        break

    return [threading.Thread(target=_loop, args=(stop, one), daemon=True) for _ in range(n)]


def teleport_flood(url: str, scene: str, stop: threading.Event, n: int = 4, rate: float = 150.0,
                   start: dict | None = None) -> list[threading.Thread]:
    """``n`` sessions whose camera jumps a kilometre on every message, ``rate`` messages a second."""
    pose = dict(start or {"eye": [0.0, 0.0, 1.7], "forward": [0.0, 1.0, 0.0], "up": [0.0, 0.0, 1.0]})

    def one() -> None:
        with _connect(url) as ws:
            ws.send(_hello(scene=scene))
            if not isinstance(decode_server(ws.recv(timeout=10)), Welcome):
                return
            t0, k = time.monotonic(), 0
            while not stop.is_set():
                k += 1
                eye = list(pose["eye"])
                eye[0] += 1000.0 * (k % 2)
                ws.send(encode(Camera(t=time.monotonic() - t0, eye=eye, forward=pose["forward"], up=pose["up"])))
                while True:
                    try:
                        ws.recv(timeout=0)
                    except TimeoutError:
                        break
                stop.wait(max(0.0, t0 + k / rate - time.monotonic()))

    return [threading.Thread(target=_loop, args=(stop, one), daemon=True) for _ in range(n)]


def exact_flood(url: str, scene: str, stop: threading.Event, n: int = 12,
                start: dict | None = None) -> list[threading.Thread]:
    """``n`` sessions asking for the exact solver, each then teleporting as fast as the rate limit lets it."""
    pose = dict(start or {"eye": [0.0, 0.0, 1.7], "forward": [0.0, 1.0, 0.0], "up": [0.0, 0.0, 1.0]})

    def one() -> None:
        with _connect(url) as ws:
            ws.send(_hello(scene=scene, solver="exact"))
            reply = decode_server(ws.recv(timeout=10))
            if not isinstance(reply, Welcome):
                stop.wait(0.2)  # refused: ask again, as a careless client would
                return
            t0, k = time.monotonic(), 0
            while not stop.is_set():
                k += 1
                eye = list(pose["eye"])
                eye[0] += 1000.0 * (k % 2)
                ws.send(encode(Camera(t=time.monotonic() - t0, eye=eye, forward=pose["forward"], up=pose["up"])))
                stop.wait(1 / 150)

    return [threading.Thread(target=_loop, args=(stop, one), daemon=True) for _ in range(n)]


def oversized_flood(url: str, scene: str, stop: threading.Event, n: int = 5,
                    size: int = 1_000_000) -> list[threading.Thread]:
    """``n`` connections sending ``size``-byte frames back to back (each reconnecting when closed)."""
    frame = b"\x00" * size

    def one() -> None:
        with _connect(url) as ws:
            ws.send(_hello(scene=scene))
            ws.recv(timeout=10)
            while not stop.is_set():
                ws.send(frame)

    return [threading.Thread(target=_loop, args=(stop, one), daemon=True) for _ in range(n)]


def invalid_flood(url: str, scene: str, stop: threading.Event, n: int = 4) -> list[threading.Thread]:
    """``n`` sessions sending frames the server must refuse, as fast as they can."""
    bad = [b"\xc1\x00", msgpack.packb({"type": "explode"}), msgpack.packb({"type": "camera", "t": "x"}),
           b"\x91" * 50_000]

    def one() -> None:
        with _connect(url) as ws:
            ws.send(_hello(scene=scene))
            ws.recv(timeout=10)
            k = 0
            while not stop.is_set():
                ws.send(bad[k % len(bad)])
                k += 1
                if k % 64 == 0:
                    while True:
                        try:
                            ws.recv(timeout=0)
                        except TimeoutError:
                            break

    return [threading.Thread(target=_loop, args=(stop, one), daemon=True) for _ in range(n)]


ATTACKS = {
    "slot_holding": slot_holding,
    "teleport_flood": teleport_flood,
    "exact_flood": exact_flood,
    "oversized_flood": oversized_flood,
    "invalid_flood": invalid_flood,
}


# ----------------------------------------------------------------------------- one phase


@dataclass
class Phase:
    attack: str
    deltas: int = 0
    late: int = 0
    errors: int = 0
    p95_ms: float = 0.0
    cpu_s: float = 0.0
    rss_before: int = 0
    rss_peak: int = 0
    new_client: bool = False
    idle_after_s: float | None = None
    checks: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def _new_client_connects(url: str, scene: str, tries: int = 3) -> bool:
    """A fresh client says hello and is welcomed (retrying a busy answer a little, as the real client does)."""
    for _ in range(tries):
        try:
            with _connect(url) as ws:
                ws.send(_hello(scene=scene))
                if isinstance(decode_server(ws.recv(timeout=10)), Welcome):
                    return True
        except Exception:
            pass
        time.sleep(0.2)
    return False


def _idle_after(pid: int, window: float = 0.2, busy: float = 0.1, limit: float = 5.0) -> float | None:
    """Seconds until the server spends under ``busy`` of a core over a ``window`` (None: not within ``limit``)."""
    began = time.monotonic()
    while time.monotonic() - began < limit:
        c0, t0 = _cpu_seconds(pid), time.monotonic()
        time.sleep(window)
        if (_cpu_seconds(pid) - c0) / (time.monotonic() - t0) < busy:
            return round(max(0.0, time.monotonic() - window - began), 3)
    return None


#: The attacking host, as the trusted proxy (loopback) names it: the good clients are 127.0.0.1.
ATTACKER = "203.0.113.66"


def _attack_main(attack: str, url: str, scene: str, start: dict, stop, ready) -> None:
    """In a child process (its own GIL: the good client's frames are not slowed by the attacker's Python)."""
    import logging

    import websockets.sync.client as wsc

    logging.getLogger("websockets").setLevel(logging.CRITICAL)  # a refused attacker's traces are expected

    plain = wsc.connect

    def from_attacker(*args, **kw):  # every attacking connection comes from one other host
        return plain(*args, additional_headers={"X-Real-IP": ATTACKER}, **kw)

    wsc.connect = from_attacker
    local = threading.Event()
    kw = {"start": start} if attack in ("teleport_flood", "exact_flood") else {}
    threads = ATTACKS[attack](url, scene, local, **kw)
    for t in threads:
        t.start()
    ready.set()
    stop.wait()
    local.set()
    for t in threads:
        t.join(timeout=5)


def _phase(server, scene: str, attack: str | None, seconds: float, target: float, start: dict) -> Phase:
    from bench.demo import summarize
    from client.app import run_client

    pid = server.proc.pid
    phase = Phase(attack or "none")
    phase.rss_before = _rss(pid)
    import multiprocessing

    ctx = multiprocessing.get_context("spawn")
    stop, ready = ctx.Event(), ctx.Event()
    threads = []
    if attack is not None:
        threads = [ctx.Process(target=_attack_main, args=(attack, server.url, scene, start, stop, ready),
                               daemon=True)]
    peak = [phase.rss_before]
    sampling = threading.Event()

    def sample() -> None:
        while not sampling.is_set():
            peak[0] = max(peak[0], _rss(pid))
            sampling.wait(0.05)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    c0 = _cpu_seconds(pid)
    for t in threads:
        t.start()
    if threads:
        ready.wait(30)
        time.sleep(0.5)  # the attack under way before the good client starts
    result: dict = {}

    def newcomer() -> None:
        time.sleep(min(1.0, seconds / 2))
        result["new"] = _new_client_connects(server.url, scene)

    probe = threading.Thread(target=newcomer, daemon=True)
    probe.start()
    try:
        run = run_client(server.url, scene, duration=seconds, viewport=(320, 180), target_frame_time=target,
                         reconnect_timeout=5.0)
    finally:
        probe.join(timeout=30)
        stop.set()
        for t in threads:
            t.join(timeout=10)
            if t.is_alive():
                t.kill()
                t.join()
    phase.cpu_s = round(_cpu_seconds(pid) - c0, 3)
    phase.idle_after_s = _idle_after(pid)
    sampling.set()
    sampler.join(timeout=5)
    phase.rss_peak = peak[0]
    phase.new_client = bool(result.get("new"))
    summary = summarize(run, target, warmup=min(1.0, seconds / 4))
    phase.deltas, phase.late, phase.errors = run.deltas_received, run.late, len(run.errors)
    phase.p95_ms = summary.p95_ms
    return phase


def run(store: Path, *, seconds: float = 16.0, attacks: list[str] | None = None, target_ms: float = 20.0,
        say: Callable[[str], None] = lambda s: None) -> dict:
    """Each attack in turn beside one good client, after a reference run without attack; figures + verdicts."""
    from bench.demo import ServerProcess
    from server.scene.store import SceneStore

    with SceneStore.open(store) as s:
        scene, start = s.index.name, dict(s.index.start)
    chosen = list(attacks or ATTACKS)
    unknown = [a for a in chosen if a not in ATTACKS]
    if unknown:
        raise ValueError(f"unknown attack {unknown[0]!r}; choose from {', '.join(ATTACKS)}")
    target = target_ms / 1e3
    phases: list[Phase] = []
    # Loopback is the trusted proxy: the attackers name their own host in X-Real-IP, as behind nginx.
    with ServerProcess([store], admin_token=None, extra=["--trusted-proxy", "127.0.0.1"]) as server:
        say("reference: the good client alone")
        reference = _phase(server, scene, None, seconds, target, start)
        phases.append(reference)
        for attack in chosen:
            say(f"attack: {attack}")
            phases.append(_phase(server, scene, attack, seconds, target, start))
    base = max(1, reference.deltas)
    for p in phases:
        on_time = 1.0 - p.late / max(1, p.deltas)
        p.checks = {
            "delta_share": round(p.deltas / base, 3),
            "on_time": round(on_time, 4),
            "rss_growth_mb": round((p.rss_peak - p.rss_before) / 2**20, 1),
            "pass_deltas": p.deltas / base >= MIN_DELTA_SHARE,
            "pass_on_time": on_time >= MIN_ON_TIME,
            "pass_new_client": p.new_client,
            "pass_rss": p.rss_peak - p.rss_before <= MAX_RSS_GROWTH,
            "pass_idle": p.idle_after_s is not None and p.idle_after_s <= MAX_IDLE_S,
        }
    rows = [p.as_dict() for p in phases]
    return {"seconds": seconds, "target_ms": target_ms, "reference_deltas": reference.deltas, "phases": rows,
            "passed": all(all(v for k, v in r["checks"].items() if k.startswith("pass_")) for r in rows[1:])}


def format_table(result: dict) -> list[str]:
    """The README's table: one line per attack."""
    lines = ["| attack | deltas vs none | on time | frame p95 (ms) | server CPU (s) | RSS growth (MB) "
             "| new client | idle after (s) | pass |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in result["phases"]:
        c = r["checks"]
        ok = all(v for k, v in c.items() if k.startswith("pass_"))
        lines.append(f"| {r['attack']} | {c['delta_share']:.0%} | {c['on_time']:.1%} | {r['p95_ms']:.1f} "
                     f"| {r['cpu_s']:.1f} | {c['rss_growth_mb']:+.1f} | {'yes' if r['new_client'] else 'NO'} "
                     f"| {r['idle_after_s'] if r['idle_after_s'] is not None else '> 5'} | {'yes' if ok else 'NO'} |")
    return lines
