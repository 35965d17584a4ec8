"""A snapshot written by an earlier version of the session still restores and resumes with nothing re-sent.

``fixtures/session-snapshot-demo.msgpack`` holds ``Session.snapshot()`` of a
session driven for 3 s along the demo scene's tour (``build_demo(objects=24,
seed=3)``, the ``demo_store`` fixture), the ids the client held then and the
session's id, token and seq. It was written before the session was split into
parts, so it pins the snapshot's format: a part that renames a field must still
read it.
"""

from __future__ import annotations

from pathlib import Path

import msgpack
import numpy as np
import pytest

from proto import PROTOCOL_VERSION
from proto.codec import decode_server, encode
from proto.manifest import digest, pack_held
from proto.messages import Ack, Camera, Delta, Error, FrameReport, Hello, Ping, Pong, Resume, Welcome
from server.scene.store import SceneStore
from server.session import Session, SessionConfig

FIXTURE = Path(__file__).parent / "fixtures" / "session-snapshot-demo.msgpack"
STEP = 0.1


@pytest.fixture(scope="module")
def saved():
    return msgpack.unpackb(FIXTURE.read_bytes())


@pytest.fixture(scope="module")
def demo(demo_store):
    store = SceneStore.open(demo_store)
    yield {store.index.name: store}
    store.close()


class HeldClient:
    """A client without GL that holds representation ids only: its acks state exactly what it holds."""

    def __init__(self, index, held: np.ndarray, t: float) -> None:
        self.index = index
        self.rep_bytes = np.asarray(index.rep_bytes, np.int64)
        self.held = set(int(r) for r in held)
        self.t = t
        self.deltas: list[Delta] = []
        self.sent_again: list[int] = []

    def ack(self, delta: Delta) -> Ack:
        self.sent_again += [a.rep for a in delta.add if a.rep in self.held]
        self.held |= {a.rep for a in delta.add}
        self.held -= set(delta.drop)
        ids = np.asarray(sorted(self.held), np.int64)
        return Ack(seq=delta.seq, t=self.t, held=int(ids.size), held_bytes=int(self.rep_bytes[ids].sum()),
                   digest=digest(ids))

    def handle(self, session: Session, messages) -> list:
        others = []
        for m in map(decode_server, map(encode, messages)):
            if isinstance(m, Ping):
                session.receive(encode(Pong(id=m.id, sent=m.sent, t=self.t)), self.t)
            elif isinstance(m, Delta):
                self.deltas.append(m)
                assert session.receive(encode(self.ack(m)), self.t) == []
            elif isinstance(m, Error):
                raise AssertionError(f"error frame: {m}")
            else:
                others.append(m)
        return others

    def run(self, session: Session, seconds: float) -> None:
        from proto.tour import Tour

        tour = Tour(self.index.tour)
        end = self.t + seconds
        frame = 0
        while self.t < end - 1e-9:
            self.t = round(self.t + STEP, 6)
            eye, forward, up = tour.pose_at(self.t)
            session.receive(encode(Camera(t=self.t, eye=eye.tolist(), forward=forward.tolist(), up=up.tolist())),
                            self.t)
            while (deadline := session.next_deadline()) is not None and deadline <= self.t:
                self.handle(session, session.poll(self.t))
            if self.deltas:
                frame += 1
                session.receive(encode(FrameReport(frame=frame, t=self.t, time=0.01, triangles=10_000,
                                                   vertices=6_000, draws=8, selection=self.deltas[-1].seq,
                                                   pixels=50_000)), self.t)


def test_a_snapshot_from_before_the_move_resumes_with_nothing_resent(saved, demo):
    index = next(iter(demo.values())).index
    assert saved["scene"] == index.name
    held = np.asarray(saved["held"], np.int64)
    assert held.size > 0 and int(np.asarray(index.rep_bytes, np.int64)[held].sum()) == saved["held_bytes"]

    session = Session(demo, saved["session"], SessionConfig(), token=saved["token"])
    session.restore(saved["blob"])
    assert session.seq == saved["seq"]
    client = HeldClient(index, held, saved["t"])
    hello = Hello(protocol=PROTOCOL_VERSION, scene=index.name, viewport=[640, 360], target_frame_time=0.05,
                  solver="mixed", algorithms=["flat", "lit"],
                  resume=Resume(session=saved["session"], token=saved["token"]), held=pack_held(held))
    (welcome,) = client.handle(session, session.receive(encode(hello), client.t))
    assert isinstance(welcome, Welcome) and welcome.resumed and welcome.held == held.size

    client.run(session, 1.5)
    assert client.deltas, "the resumed session sent no delta"
    assert client.deltas[0].seq == saved["seq"] + 1 and client.deltas[0].reset
    assert client.sent_again == []  # nothing the client held is sent again
    assert session.mirror_mismatch == 0
