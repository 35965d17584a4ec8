"""Sessions driven in one process on a virtual clock: the load test's clients without sockets.

Each scripted client is a ``SimulatedClient`` (the load generator's, so the same
poses, frame reports, pongs and acks) whose messages go straight into a sans-I/O
``Session`` at their virtual time, and whose replies to what the session sends
arrive a fixed ``latency`` later. Time advances in ticks; in each tick every
client's messages due by then are received, then every session whose
selection or ping is due is polled — one at a time, or all together through the
server's ``Ticker`` — with the tick's time as ``now``, and then the sessions whose
state changed are snapshotted as the app saves them (``save_interval``). Nothing reads a clock, so a
session's messages depend only on its own script: the same scripted session
gives the same deltas alone and among fifty others (``tests/server/session/
test_batch.py``), and the CPU each part of the server spends per session-second
is measured without a network, a load generator or the machine's other work in
the figure (``walkstream bench sessions``).
"""

from __future__ import annotations

import heapq
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Callable, Mapping

import msgpack
import numpy as np

from bench.loadtest.client import ClientConfig, RendererModel, SimulatedClient, unframe
from proto.codec import encode
from proto.messages import Delta, Ping
from server.session.payloads import packed

__all__ = ["ScriptedRun", "run_scripted"]


@dataclass
class ScriptedRun:
    """What a scripted run sent and what it cost.

    frames : per client, every frame the server sent it after the welcome (encoded bytes, in order)
    cpu : thread CPU seconds by part (``receive:<type>``, ``poll``, ``encode``)
    session_seconds : the sum over sessions of the virtual seconds each was open
    """

    frames: list[list[bytes]]
    cpu: Counter = field(default_factory=Counter)
    session_seconds: float = 0.0
    deltas: int = 0
    polls: int = 0
    snapshots: int = 0

    def per_session_second(self) -> dict[str, float]:
        """CPU seconds per session-second, by part and in total."""
        s = max(self.session_seconds, 1e-9)
        out = {k: v / s for k, v in sorted(self.cpu.items())}
        out["total"] = sum(self.cpu.values()) / s
        return out


def run_scripted(
    scenes: Mapping,
    n: int,
    seconds: float,
    *,
    scene: str | None = None,
    make_session: Callable[[int], object],
    poll: Callable[[list, float], list[list]] | None = None,
    rate: float = 10.0,
    tick: float = 0.01,
    latency: float = 0.02,
    stagger: float = 0.5,
    seed: int = 0,
    algorithms: tuple[str, ...] = ("flat",),
    target: float = 0.05,
    only: int | None = None,
    separate: bool = False,
    save_interval: float | None = None,
) -> ScriptedRun:
    """Run ``n`` scripted clients for ``seconds`` of virtual time; client i starts at i·stagger/n.

    make_session(i) : a fresh ``Session`` for client i
    poll(sessions, now) : polls the due sessions together, returning each one's messages (default: one at a time)
    only : keep the frames of this client alone (the others' are dropped as they go)
    separate : each frame's report in a message of its own (default: with the frame's pose, as clients send it)
    save_interval : snapshot each session whose state changed, at most this often (``cpu["snapshot"]``), as the
        app saves them (None: no snapshots)
    """
    name = scene or next(iter(scenes))
    cfg = ClientConfig(url="", http="", scene=name, rate=rate, target=target, algorithms=tuple(algorithms),
                       model=RendererModel(), seed=seed)
    clients = [SimulatedClient(i, max(n, 1), cfg) for i in range(n)]
    sessions = [make_session(i) for i in range(n)]
    origin = [i * stagger / max(n, 1) for i in range(n)]
    run = ScriptedRun(frames=[[] for _ in range(n)])
    cpu = run.cpu
    # (arrival time, order, client, raw frame) — the order keeps same-time frames in the order sent.
    inbox: list[tuple[float, int, int, bytes]] = []
    order = 0
    steps = [0] * n  # frames each client has sent
    opened = [False] * n
    saved = [-np.inf] * n  # when each session's state was last saved (``save_interval``)
    chunks: list[dict] = [{} for _ in range(n)]
    period = 1.0 / rate
    packb = msgpack.packb

    def client_t(i: int, now: float) -> float:
        return now - origin[i]

    def post(at: float, i: int, data: bytes) -> None:
        nonlocal order
        order += 1
        heapq.heappush(inbox, (at, order, i, data))

    def deliver(i: int, out: list, now: float) -> None:
        """The session's messages reach client i ``latency`` / 2 later; its answers the session ``latency`` later."""
        for m in out:
            began = time.thread_time()
            data = encode(m, packed=packed)
            cpu["encode"] += time.thread_time() - began
            if only is None or only == i:
                run.frames[i].append(data)
            if isinstance(m, Ping):
                post(now + latency, i, packb({"type": "pong", "id": m.id, "sent": m.sent,
                                              "t": client_t(i, now + latency / 2)}))
            elif isinstance(m, Delta):
                run.deltas += 1
                ack = clients[i].apply_delta(unframe(data), client_t(i, now + latency / 2))
                post(now + latency, i, packb(ack))

    def say_hello(i: int, now: float) -> None:
        c = clients[i]
        out = sessions[i].receive(c.hello(), now)
        welcome = out[0]
        c.opened, c.session, c.tau = True, welcome.session, float(welcome.tau)
        from proto.tour import Tour

        c.tour = Tour([k.model_dump() for k in welcome.tour])
        c.phase = c.tour.t[0] + c.tour.duration * ((c.index / c.n) % 1.0)
        opened[i] = True
        deliver(i, out[1:], now)

    def client_frames(i: int, now: float) -> None:
        """Camera and frame report of every frame of client i due by ``now`` (``SimulatedClient._send``'s)."""
        c = clients[i]
        while origin[i] + steps[i] * period <= now + 1e-9:
            k = steps[i]
            chunk = chunks[i]
            if k not in chunk:
                ts = c.phase + (k + np.arange(64)) * period
                e, f, u = c.tour.pose_at(ts)
                noise = c.rng.lognormal(0.0, c.cfg.model.sigma, 64)
                chunk.clear()
                chunk.update({k + j: (e[j].tolist(), f[j].tolist(), u[j].tolist(), float(noise[j])) for j in range(64)})
            eye, fwd, up, noise = chunk[k]
            t = k * period
            at = origin[i] + t
            camera = {"type": "camera", "t": t, "eye": eye, "forward": fwd, "up": up}
            report, _ = c.frame_report(c.frames, t, noise)
            c.frames += 1
            if separate:
                post(at, i, packb(camera))
                post(at, i, packb(report))
            else:
                camera["report"] = report
                post(at, i, packb(camera))
            steps[i] += 1

    now = 0.0
    end = float(seconds)
    while now <= end + 1e-9:
        for i in range(n):
            if not opened[i] and origin[i] <= now + 1e-9:
                say_hello(i, now)
            if opened[i]:
                client_frames(i, now)
        while inbox and inbox[0][0] <= now + 1e-9:
            _, _, i, data = heapq.heappop(inbox)
            kind = msgpack.unpackb(data)["type"]
            began = time.thread_time()
            out = sessions[i].receive(data, now)
            cpu[f"receive:{kind}"] += time.thread_time() - began
            deliver(i, out, now)
        due = [i for i in range(n) if opened[i] and (d := sessions[i].next_deadline()) is not None and d <= now + 1e-9]
        if due:
            run.polls += len(due)
            began = time.thread_time()
            if poll is None:
                outs = [sessions[i].poll(now) for i in due]
            else:
                outs = poll([sessions[i] for i in due], now)
            cpu["poll"] += time.thread_time() - began
            for i, out in zip(due, outs):
                deliver(i, out, now)
        if save_interval is not None:
            for i in range(n):
                if opened[i] and now >= saved[i] + save_interval - 1e-9 and sessions[i].dirty:
                    began = time.thread_time()
                    sessions[i].snapshot()
                    cpu["snapshot"] += time.thread_time() - began
                    saved[i] = now
                    run.snapshots += 1
        now = round(now + tick, 9)
    run.session_seconds = sum(max(0.0, end - o) for o in origin)
    return run
