"""A camera that jumps on every message makes at most one reset selection per τ/2, each of the newest pose."""

from __future__ import annotations

from time import perf_counter

from proto import PROTOCOL_VERSION
from proto.codec import decode_server, encode
from proto.messages import Camera, Delta, Hello, Ping, Pong
from server.scene.store import SceneStore
from server.session import Session, SessionConfig


def test_teleports_on_every_message_select_at_most_twice_per_tau(demo_store):
    tau = 0.5
    with SceneStore.open(demo_store) as store:
        scenes = {store.index.name: store}
        start = dict(store.index.start)
        s = Session(scenes, "jumper", SessionConfig(tau=tau), stopwatch=perf_counter)
        hello = Hello(protocol=PROTOCOL_VERSION, scene=store.index.name, viewport=[320, 180])
        ping = [m for m in s.receive(encode(hello), 0.0) if isinstance(m, Ping)][0]
        s.receive(encode(Pong(id=ping.id, sent=ping.sent, t=0.0)), 0.0)
        resets, rate, seconds = 0, 150.0, 4.0
        for k in range(int(rate * seconds)):  # 150 jumps of a kilometre a second, each polled at once
            now = k / rate
            eye = list(start["eye"])
            eye[0] += 1000.0 * (k % 2)
            s.receive(encode(Camera(t=now, eye=eye, forward=start["forward"], up=start["up"])), now)
            for m in s.poll(now):
                m = decode_server(encode(m))
                if isinstance(m, Delta) and m.reset:
                    resets += 1
        assert s.teleports > 100  # the jumps were seen as teleports ...
        assert 2 <= resets <= seconds / (tau / 2) + 1  # ... and cost at most one reset selection per τ/2
