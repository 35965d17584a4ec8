"""A session is a function of its input: the same script of messages, times and stopwatch readings gives
byte-identical deltas, run after run — whatever the machine's load (the selection sees no other clock)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from proto.tour import Tour
from proto import PROTOCOL_VERSION
from proto.codec import decode_server, encode
from proto.manifest import digest
from proto.messages import Ack, AlgorithmTerms, Camera, Delta, Error, FrameReport, Hello, Ping, Pong
from server.scene.store import SceneStore
from server.session import Session, SessionConfig

STEP = 0.05  # seconds between camera poses
SECONDS = 4.0


@pytest.fixture(scope="module")
def demo(demo_store):
    store = SceneStore.open(demo_store)
    yield {store.index.name: store}
    store.close()


def _step_stopwatch(step: float = 1e-3):
    """A stopwatch that advances ``step`` seconds at every reading."""
    ticks = itertools.count()
    return lambda: next(ticks) * step


def _run(scenes, solver: str) -> list[bytes]:
    """Drive one session along the scene's tour: poses, polls at deadlines, pongs, acks and frame reports
    computed from what it sent; returns every delta it sent, encoded."""
    index = next(iter(scenes.values())).index
    rep_bytes = np.asarray(index.rep_bytes, np.int64)
    session = Session(scenes, "replay", SessionConfig(), token="replay-token-0123456789",
                      stopwatch=_step_stopwatch())
    held: set[int] = set()
    deltas: list[bytes] = []
    t = 0.0

    def handle(messages) -> None:
        for m in map(decode_server, map(encode, messages)):
            if isinstance(m, Ping):
                session.receive(encode(Pong(id=m.id, sent=m.sent, t=t)), t)
            elif isinstance(m, Delta):
                deltas.append(encode(m))
                held.update(a.rep for a in m.add)
                held.difference_update(m.drop)
                ids = np.asarray(sorted(held), np.int64)
                ack = Ack(seq=m.seq, t=t, held=int(ids.size), held_bytes=int(rep_bytes[ids].sum()),
                          digest=digest(ids))
                assert session.receive(encode(ack), t) == []
            elif isinstance(m, Error):
                raise AssertionError(f"error frame: {m}")

    hello = Hello(protocol=PROTOCOL_VERSION, scene=index.name, viewport=[640, 360], target_frame_time=0.05,
                  solver=solver, algorithms=["flat", "lit"])
    handle(session.receive(encode(hello), t))
    tour = Tour(index.tour)
    frame = 0
    while t < SECONDS:
        t = round(t + STEP, 6)
        eye, forward, up = tour.pose_at(t)
        session.receive(encode(Camera(t=t, eye=eye.tolist(), forward=forward.tolist(), up=up.tolist())), t)
        while (deadline := session.next_deadline()) is not None and deadline <= t:
            handle(session.poll(t))
        if deltas:
            frame += 1
            load = 4_000 + 37 * (frame % 11)
            terms = AlgorithmTerms(triangles=[load, load // 2], vertices=[load, load // 3], pixels=[40_000, 9_000],
                                   draws=[6, 2])
            report = FrameReport(frame=frame, t=t, time=0.01 + 1e-6 * load, triangles=load + load // 2,
                                 vertices=load + load // 3, draws=8, selection=session.seq, pixels=49_000,
                                 terms=terms)
            session.receive(encode(report), t)
    return deltas


@pytest.mark.parametrize("solver", ["greedy", "mixed"])
def test_the_same_script_and_stopwatch_give_byte_identical_deltas(demo, solver):
    first, second = _run(demo, solver), _run(demo, solver)
    assert len(first) >= 5, len(first)
    assert first == second
