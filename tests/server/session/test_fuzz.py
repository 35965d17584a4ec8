"""Hostile input: over 100k malformed or hostile frames into the decoder and live sessions.

A seeded mutation fuzzer derives frames from valid protocol-4 client messages
(byte flips, truncation, splicing, msgpack type confusion, boundary and
non-finite numbers, deep nesting, oversized lists, unknown keys, zlib bombs in
``held``, random bytes). The contract it checks is the h11 split of
``proto.errors``: a peer's frame is either a message or a ``ProtocolError``
with a known code, and a session answers anything with messages (an
``error`` frame at worst) — never an exception — while the sessions beside it
go on exactly as if nothing happened.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
import zlib
from collections import Counter
from dataclasses import dataclass, field

import httpx
import msgpack
import numpy as np
import pytest
from hypothesis import assume, HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import BaseModel

from proto import PROTOCOL_VERSION
from proto.codec import MAX_CLIENT_FRAME, decode_client, decode_server, encode
from proto.errors import ERROR_CODES, ProtocolError
from proto.manifest import digest, pack_held, unpack_held
from proto.messages import (
    CLIENT_TYPES,
    SERVER_TYPES,
    Ack,
    AlgorithmTerms,
    Camera,
    Delta,
    Error,
    FrameReport,
    Heartbeat,
    Hello,
    Navigation,
    Ping,
    Pong,
    Resume,
    TourKey,
    TourPlan,
    Welcome,
)
from server.scene.store import SceneStore
from server.session import Session, SessionConfig, SessionState

#: Frames the in-process campaign feeds (the issue asks for at least 100k); raise it locally to fuzz longer.
FRAMES = int(os.environ.get("WALKSTREAM_FUZZ_FRAMES", "100000"))
SEED = int(os.environ.get("WALKSTREAM_FUZZ_SEED", "7"))

NAN, INF = float("nan"), float("inf")
#: Numbers at and just past every limit of the protocol, and the ones msgpack and floats make special.
INTS = [0, 1, -1, 2, 3, 4, 15, 16, 17, 127, 128, 255, 256, 16383, 16384, 16385, 65535, 65536,
        (1 << 16) - 1, 1 << 16, (1 << 20), (1 << 20) + 1, (1 << 31) - 1, 1 << 31, -(1 << 31), (1 << 32) - 1,
        1 << 32, (1 << 32) + 1, (1 << 40), (1 << 40) + 1, 1 << 42, (1 << 42) + 1, (1 << 63) - 1, -(1 << 63),
        (1 << 64) - 1, 10**9, 10**9 + 1, -(10**9), -(10**9) - 1, 10**7, 10**7 + 1]
FLOATS = [NAN, INF, -INF, 0.0, -0.0, 5e-324, -5e-324, 2.2250738585072014e-308, 1e308, -1e308, 1.7976931348623157e308,
          1e9, 1e9 + 1e-6, 1e9 - 0.01, -1e9, -1e9 - 1.0, 1e7, -1e7, 1e7 + 1.0, 1e6, 1e6 + 1.0, 60.0, 60.000001,
          2.0, 2.0000001, 0.001, 0.00099, 5.0, 5.000001, 170.0, 169.9999, 1e-9, 1e-10, 1e4, 1e4 + 1, 3600.0,
          3600.1, 255.0, 256.0, 0.5, 1e-300, float(1 << 53) + 1, 123456.789]
#: Byte strings that mean something to a msgpack parser: reserved, huge length headers, ext, deep openers.
MAGIC = [b"\xc1", b"\xdc\xff\xff", b"\xdd\xff\xff\xff\xff", b"\xde\xff\xff", b"\xdf\xff\xff\xff\xff",
         b"\xc6\xff\xff\xff\xff", b"\xdb\xff\xff\xff\xff", b"\xc9\x00\x00\x00\x01\x05", b"\xd4\xff\x00",
         b"\xd7\xff" + b"\x00" * 8, b"\xcb\x7f\xf8\x00\x00\x00\x00\x00\x00", b"\xcb\x7f\xf0" + b"\x00" * 6,
         b"\xcf\xff\xff\xff\xff\xff\xff\xff\xff", b"\xd3\x80" + b"\x00" * 7, b"\x91" * 64, b"\x81\xa1k" * 32,
         b"\xa4type", b"\xa6camera", b"\xa5hello", b"\xc0", b"\xc2", b"\xc3", b"\xff", b"\xe0", b"\x00"]
TYPES = list(CLIENT_TYPES) + ["welcome", "delta", "error", "ping", "", "HELLO", "camera\x00", "x" * 300]
TEXT = ["", "a", "demo", "greedy", "hello", "camera", "\x00", "ü", "😀", "a" * 129, "../etc", "flat",
        "textured", "x" * 2000, "A" * 16, "deadbeef" * 4, "\ud7ff", "-", "."]
SERVER_CLASSES = tuple(SERVER_TYPES.values())
CLIENT_CLASSES = tuple(CLIENT_TYPES.values())


# --------------------------------------------------------------------------- valid seeds


def seed_messages(index) -> list[dict]:
    """Valid protocol-4 client messages for the scene ``index``: every type, every optional field used."""
    start = index.start
    n = int(index.n_representations)
    some = np.arange(0, n, 7)
    pose = {k: list(map(float, start[k])) for k in ("eye", "forward", "up")}
    hellos = [
        Hello(protocol=PROTOCOL_VERSION, scene=index.name, viewport=[640, 360]),
        Hello(protocol=PROTOCOL_VERSION, scene=index.name, viewport=[1280, 720], fov_y=70.0, target_frame_time=0.02,
              solver="greedy", client="fuzz", predict=False, morph=False, max_speed=5.0, max_turn=90.0,
              cache_bytes=1 << 20, algorithms=["flat", "lit", "textured"]),
        Hello(protocol=PROTOCOL_VERSION, scene=index.name, viewport=[640, 360],
              resume=Resume(session="0123456789abcdef", token="A" * 32), held=pack_held(some)),
        Hello(protocol=PROTOCOL_VERSION, scene=index.name, viewport=[320, 200], held=pack_held(np.arange(n))),
        Hello(protocol=PROTOCOL_VERSION, scene=index.name, viewport=[320, 200], held=pack_held(np.zeros(0))),
    ]
    terms = AlgorithmTerms(triangles=[1000, 200, 30], vertices=[600, 100, 20], pixels=[50_000, 9_000, 100],
                           draws=[10, 2, 1])
    others = [
        Camera(t=0.0, **pose),
        Camera(t=0.5, eye=[pose["eye"][0] + 1.0, *pose["eye"][1:]], forward=pose["forward"], up=pose["up"]),
        FrameReport(frame=1, t=0.1, time=0.02, triangles=20_000, vertices=10_000, draws=12, selection=1,
                    pixels=100_000, splats=10, gpu_time=0.01, cpu_time=0.002, terms=terms),
        FrameReport(frame=2, t=0.2, time=0.05, triangles=1, vertices=1, draws=1),
        Pong(id=1, sent=0.0, t=0.0),
        Pong(id=2, sent=1.0, t=1.01),
        Ack(seq=1, t=0.3, rejected=[1, 2, 3], held=12, digest=digest(np.arange(12)), held_bytes=4096),
        Ack(seq=2, t=0.6),
        Heartbeat(kiosk="hall-1.west", t=0.7, interval=5.0, state="visitor", frames=420, fps=59.9, frame_p95=0.021,
                  recent=[0.016, 0.017, 0.03], rss=300 << 20, gpu_memory=64 << 20, cache_bytes=1 << 20, reconnects=2,
                  tour="harbour", stop=3),
        Heartbeat(kiosk="k", t=0.8, frames=0),
        TourPlan(t=0.9, keys=[TourKey(t=1.0, **pose), TourKey(t=3.0, **pose)], tour="harbour"),
        TourPlan(t=0.2, keys=[TourKey(t=0.2, **pose), TourKey(t=5.0, **pose)], tour="fuzz"),
        TourPlan(t=0.4, keys=[]),
        Heartbeat(kiosk="k1", t=1.0, frames=60, fps=60.0, frame_p95=0.02, recent=[0.016, 0.017]),
    ]
    hellos.append(Hello(protocol=PROTOCOL_VERSION, scene=index.name, viewport=[320, 200], walkable=True,
                        navigation=Navigation(mode="walk", bounds=[[-50.0, -50.0, -5.0], [50.0, 50.0, 20.0]]),
                        plan=TourPlan(t=0.0, keys=[TourKey(t=0.0, **pose), TourKey(t=9.0, **pose)])))
    return [m.model_dump(mode="python") for m in hellos + others]


# --------------------------------------------------------------------------- the mutation fuzzer


class Fuzzer:
    """Frames derived from ``seeds`` by a seeded numpy generator; ``frame()`` gives the next (bytes or, rarely, str)."""

    def __init__(self, seeds: list[dict], seed: int) -> None:
        self.rng = np.random.default_rng(seed)
        self._u: list = []  # uniforms drawn from ``rng`` in blocks: one numpy call per 64k decisions
        self._k = 0
        self.seeds = seeds
        self.packed = [msgpack.packb(s, use_bin_type=True) for s in seeds]
        self.ops = Counter()
        held = pack_held(np.arange(0, 4000, 3))
        # zlib bombs and near misses for ``held``: far more bits than a scene has, or a broken stream.
        self.blobs = [held, held[:-1], held[:5], held + b"\x00", zlib.compress(b"\xff" * 2_000_000, 9),
                      zlib.compress(b"\x00" * 5_000_000, 9), b"", b"\x78\x9c", b"not zlib at all",
                      zlib.compress(b"\x80" * 600, 9), zlib.compress(b"\x01"), zlib.compressobj(9, zlib.DEFLATED, -15).compress(b"\xff" * 10)]

    # -- values

    def u(self) -> float:
        """The next uniform in [0, 1)."""
        if self._k >= len(self._u):
            self._u, self._k = self.rng.random(1 << 16).tolist(), 0
        self._k += 1
        return self._u[self._k - 1]

    def ri(self, lo: int, hi: int | None = None) -> int:
        """A uniform integer in [lo, hi) (or [0, lo))."""
        if hi is None:
            lo, hi = 0, lo
        return lo + int(self.u() * (hi - lo))

    def choice(self, seq):
        return seq[self.ri(len(seq))]

    def text(self) -> str:
        r = self.u()
        if r < 0.6:
            return self.choice(TEXT)
        return "".join([chr(self.ri(32, 0x2FF)) for _ in range(self.ri(0, 24))])

    def value(self, depth: int = 0):
        """A random msgpack value of a random kind (the type-confusion pool)."""
        kind = self.ri(10 if depth < 2 else 7)
        if kind == 0:
            return self.text()
        if kind == 1:
            return self.rng.bytes(self.ri(0, 48))
        if kind == 2:
            return self.choice(INTS) if self.u() < 0.7 else self.ri(-(1 << 62), 1 << 62)
        if kind == 3:
            return self.choice(FLOATS) if self.u() < 0.7 else (self.u() - 0.5) * 10 ** self.ri(-3, 12)
        if kind == 4:
            return None
        if kind == 5:
            return self.u() < 0.5
        if kind == 6:
            return 4.0 * self.u() - 2.0
        if kind == 7:
            return [self.value(depth + 1) for _ in range(self.ri(0, 5))]
        if kind == 8:
            return {self.text(): self.value(depth + 1) for _ in range(self.ri(0, 4))}
        return self.seed_copy(self.ri(len(self.seeds)))

    def seed_copy(self, i: int) -> dict:
        return msgpack.unpackb(self.packed[i], raw=False)

    # -- structure

    @staticmethod
    def slots(obj, out=None):
        """(container, key) of every value inside ``obj``."""
        out = [] if out is None else out
        items = obj.items() if isinstance(obj, dict) else enumerate(obj) if isinstance(obj, list) else ()
        for k, v in items:
            if len(out) >= 64:  # an oversized list is one slot's worth, not 16k
                break
            out.append((obj, k))
            if isinstance(v, (dict, list)):
                Fuzzer.slots(v, out)
        return out

    def mutate_object(self, obj: dict) -> dict:
        for _ in range(self.ri(1, 4)):
            slots = self.slots(obj)
            op = self.ri(9)
            if not slots and op < 5:
                op = 5
            if op < 5:
                parent, key = slots[self.ri(len(slots))]
            if op == 0:  # type confusion
                parent[key] = self.value()
                self.ops["confuse"] += 1
            elif op == 1:  # limits, huge, negative, NaN, inf
                parent[key] = self.choice(INTS) if self.u() < 0.5 else self.choice(FLOATS)
                self.ops["number"] += 1
            elif op == 2:  # deep nesting
                v = parent[key]
                for _ in range(self.ri(1, 400)):
                    v = [v] if self.u() < 0.7 else {"k": v}
                parent[key] = v
                self.ops["nest"] += 1
            elif op == 3:  # oversized lists
                n = int(self.choice([3, 4, 5, 100, 4096, 16_000]))
                if self.u() < 0.5:
                    parent[key] = self.rng.integers(0, 1 << 31, n).tolist()
                else:
                    parent[key] = self.rng.normal(0, 1e6, n).tolist()
                self.ops["oversize"] += 1
            elif op == 4:  # drop a field
                if isinstance(parent, dict):
                    del parent[key]
                elif parent:
                    parent.pop()
                self.ops["drop"] += 1
            elif op == 5:  # unknown keys, some very long, some bytes
                name = self.choice([self.text(), "x" * 5000, b"bytes-key", "__class__", "model_config", "type "])
                obj[name] = self.value()
                self.ops["unknown_key"] += 1
            elif op == 6:  # retype: the fields of one message under another's name
                obj["type"] = self.choice(TYPES)
                self.ops["retype"] += 1
            elif op == 7:  # held manifests: bombs, truncations, random bytes, wrong types
                obj["held"] = self.choice(self.blobs) if self.u() < 0.8 else self.value()
                self.ops["held"] += 1
            else:  # resume with hostile tokens
                obj["resume"] = self.choice([{"session": self.text(), "token": self.text()},
                                             {"session": "s", "token": "A" * 16, "extra": 1},
                                             {"session": "0" * 128, "token": "B" * 129}, self.value()])
                self.ops["resume"] += 1
        return obj

    def pack(self, obj) -> bytes | None:
        try:
            return msgpack.packb(obj, use_bin_type=bool(self.u() < 0.9))
        except (ValueError, TypeError, OverflowError):
            return None

    def mutate_bytes(self, data: bytes) -> bytes:
        op = self.ri(8)
        b = bytearray(data)
        if op == 0 and b:  # bit and byte flips
            k = self.ri(1, 9)
            pos = self.rng.integers(0, len(b), k)
            for p, x in zip(pos.tolist(), self.rng.integers(1, 256, k).tolist()):
                b[p] ^= x
            self.ops["flip"] += 1
        elif op == 1:  # truncation
            b = b[: self.ri(0, len(b) + 1)]
            self.ops["truncate"] += 1
        elif op == 2:  # splice two frames
            other = self.choice(self.packed)
            b = b[: self.ri(0, len(b) + 1)] + other[self.ri(0, len(other) + 1):]
            self.ops["splice"] += 1
        elif op == 3:  # parser magic at a random place
            p = self.ri(0, len(b) + 1)
            b[p:p + self.ri(0, 3)] = self.choice(MAGIC)
            self.ops["magic"] += 1
        elif op == 4:  # random bytes, sometimes behind a map header
            b = bytearray(self.rng.bytes(self.ri(0, 300)))
            if self.u() < 0.5:
                b[:0] = bytes([0x80 | self.ri(16)])
            self.ops["random"] += 1
        elif op == 5:  # nesting far deeper than a packer allows, within the size limit
            depth = int(self.choice([100, 1000, 5000, 30_000, 60_000]))
            b = bytearray(self.choice([b"\x91", b"\x81\xa1k", b"\xdc\x00\x01"]) * (depth // 3 + 1))[:60_000] + b
            self.ops["deep"] += 1
        elif op == 6:  # past the size limit
            b = b + bytes(max(0, MAX_CLIENT_FRAME + 1 - len(b)) + self.ri(0, 100))
            self.ops["too_large"] += 1
        else:  # a frame twice, or trailing bytes
            b = b + (b if self.u() < 0.5 else self.rng.bytes(self.ri(1, 9)))
            self.ops["trailing"] += 1
        return bytes(b)

    def frame(self) -> bytes | str:
        r = self.u()
        i = self.ri(len(self.seeds))
        if r < 0.08:  # valid messages keep the state machines moving (hellos accepted, acks of real deltas)
            self.ops["valid"] += 1
            return self.packed[i]
        if r < 0.09:  # text frames
            self.ops["text"] += 1
            return self.text()
        if r < 0.55:
            data = self.pack(self.mutate_object(self.seed_copy(i)))
            if data is not None:
                return data if self.u() < 0.85 else self.mutate_bytes(data)
        return self.mutate_bytes(self.packed[i])


# --------------------------------------------------------------------------- the campaign


@pytest.fixture(scope="module")
def scenes(demo_store):
    store = SceneStore.open(demo_store)
    yield {store.index.name: store}
    store.close()


def _hello_frame(scenes, **kw) -> bytes:
    name = next(iter(scenes))
    return encode(Hello(**{**dict(protocol=PROTOCOL_VERSION, scene=name, viewport=[640, 360]), **kw}))


def _camera_frame(scenes, t: float, dx: float = 0.0) -> bytes:
    start = next(iter(scenes.values())).index.start
    return encode(Camera(t=t, eye=[start["eye"][0] + dx, *start["eye"][1:]], forward=start["forward"], up=start["up"]))


def _active_session(scenes, sid: str, **hello) -> Session:
    s = Session(scenes, sid, SessionConfig(), stopwatch=time.perf_counter)
    welcome, ping = s.receive(_hello_frame(scenes, **hello), 0.0)
    assert isinstance(welcome, Welcome) and isinstance(ping, Ping)
    assert s.receive(encode(Pong(id=ping.id, sent=ping.sent, t=0.0)), 0.0) == []
    return s


@dataclass
class Campaign:
    frames: int = 0
    seconds: float = 0.0
    decoded: Counter = field(default_factory=Counter)  # message type → frames that validated
    codes: Counter = field(default_factory=Counter)  # error code → frames the decoder refused with it
    session_codes: Counter = field(default_factory=Counter)  # error code → error frames the sessions answered
    decode_failures: list = field(default_factory=list)  # (frame, exception): anything but ProtocolError
    receive_failures: list = field(default_factory=list)  # (frame, exception) raised by Session.receive
    bad_outputs: list = field(default_factory=list)  # (frame, what) a session answered that is not wire-valid
    poll_failures: Counter = field(default_factory=Counter)  # exception signature → polls that raised
    held_failures: list = field(default_factory=list)  # (blob, exception) unpack_held raised other than bad_held
    held_checked: int = 0
    hellos_accepted: int = 0
    deltas: int = 0
    polls: int = 0
    ops: Counter = field(default_factory=Counter)

    def summary(self) -> str:
        return (f"{self.frames} frames in {self.seconds:.1f} s ({self.frames / max(self.seconds, 1e-9):.0f} frames/s); "
                f"decoded {dict(self.decoded)}; refused {dict(self.codes)}; sessions answered {dict(self.session_codes)}; "
                f"hellos accepted {self.hellos_accepted}; polls {self.polls}, deltas {self.deltas}")


def _check_output(out, frame, camp: Campaign) -> None:
    """Everything a session answers must be a server message that survives the wire."""
    if not isinstance(out, list):
        camp.bad_outputs.append((frame, f"not a list: {type(out).__name__}"))
        return
    for m in out:
        if not isinstance(m, SERVER_CLASSES):
            camp.bad_outputs.append((frame, f"not a server message: {type(m).__name__}"))
            continue
        if isinstance(m, Error):  # built validated; a sample also crosses the wire below
            camp.session_codes[m.code] += 1
            if m.code not in ERROR_CODES:
                camp.bad_outputs.append((frame, f"unknown error code {m.code!r}"))
            if camp.session_codes.total() % 64:
                continue
        try:
            back = decode_server(encode(m))
        except Exception as exc:  # noqa: BLE001 — the point is to catch anything
            camp.bad_outputs.append((frame, f"{type(m).__name__} does not survive the wire: {exc!r}"[:500]))
            continue
        if back != m:
            camp.bad_outputs.append((frame, f"{type(m).__name__} changed on the wire"))
        if isinstance(back, Delta):
            camp.deltas += 1


def run_campaign(scenes, frames: int, seed: int) -> Campaign:
    index = next(iter(scenes.values())).index
    fuzz = Fuzzer(seed_messages(index), seed)
    camp = Campaign()
    n_reps = int(index.n_representations)
    # The hostile sessions: one waiting for its hello, and two that said one (different options).
    fresh = Session(scenes, "fresh", SessionConfig(), stopwatch=time.perf_counter)
    active = [_active_session(scenes, "hostile-a"),
              _active_session(scenes, "hostile-b", predict=False, morph=False, algorithms=["flat", "lit", "textured"])]
    for s in active:
        s.receive(_camera_frame(scenes, 0.0), 0.0)
    now, renewed, seen_hello = 0.0, 0, None
    began = time.perf_counter()
    for i in range(frames):
        frame = fuzz.frame()
        now += 0.002
        # 1. The decoder: a message, or a ProtocolError with a known code; nothing else.
        try:
            msg = decode_client(frame)
        except ProtocolError as exc:
            camp.codes[exc.code] += 1
            msg = None
        except Exception as exc:  # noqa: BLE001
            camp.decode_failures.append((frame, exc))
            msg = None
        if msg is not None:
            if not isinstance(msg, CLIENT_CLASSES):
                camp.decode_failures.append((frame, TypeError(f"decoded to {type(msg).__name__}")))
            camp.decoded[msg.type] += 1
            if isinstance(msg, Hello) and msg.held is not None:  # what a server does with the manifest
                camp.held_checked += 1
                try:
                    ids = unpack_held(msg.held, n_reps)
                    assert ids.dtype == np.int64 and (ids.size == 0 or (ids[0] >= 0 and ids[-1] < n_reps))
                except ProtocolError as exc:
                    if exc.code != "bad_held":
                        camp.held_failures.append((msg.held, exc))
                except Exception as exc:  # noqa: BLE001
                    camp.held_failures.append((msg.held, exc))
        # 2. Live sessions: answer with messages, never raise.
        for s in (fresh, active[i % 2]):
            try:
                out = s.receive(frame, now)
            except Exception as exc:  # noqa: BLE001
                camp.receive_failures.append((frame, exc))
                continue
            _check_output(out, frame, camp)
        if fresh.state is SessionState.ACTIVE:
            camp.hellos_accepted += fresh.hello is not seen_hello
            seen_hello = fresh.hello
            if i - renewed >= 100:  # a hostile hello got through: have one waiting again (not too often: cost)
                fresh, renewed = Session(scenes, f"fresh-{i}", SessionConfig(), stopwatch=time.perf_counter), i
        # 3. The hostile sessions' own selections, now and then (they run what the hostile input left).
        if i % 500 == 499:
            for s in active:
                camp.polls += 1
                try:
                    _check_output(s.poll(now), b"<poll>", camp)
                except Exception as exc:  # noqa: BLE001
                    first = str(exc).splitlines()
                    camp.poll_failures[f"{type(exc).__name__}: {' '.join(first[:3])}"[:300]] += 1
    camp.seconds = time.perf_counter() - began
    camp.frames = frames
    camp.ops = fuzz.ops
    print("\nfuzz campaign:", camp.summary(), "\nmutations:", dict(fuzz.ops))
    return camp


@pytest.fixture(scope="module")
def campaign(scenes) -> Campaign:
    # Hostile acks make the session log a warning each (mirror mismatches); 100k of them would only cost time.
    logger = logging.getLogger("walkstream")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        return run_campaign(scenes, FRAMES, SEED)
    finally:
        logger.setLevel(level)


def _show(failures, n=5) -> str:
    return "\n".join(f"{frame[:120]!r} -> {type(exc).__name__}: {str(exc)[:300]}" for frame, exc in failures[:n])


def test_decoder_returns_a_message_or_a_protocol_error(campaign):
    assert campaign.frames >= 100_000 or FRAMES < 100_000
    assert not campaign.decode_failures, _show(campaign.decode_failures)
    assert set(campaign.codes) <= set(ERROR_CODES)
    # The fuzzer reaches every layer: the parser, the size limit, dispatch and field validation ...
    assert {"bad_msgpack", "too_large", "not_binary", "unknown_type", "invalid"} <= set(campaign.codes)
    # ... and enough mutants still validate that the sessions behind the decoder see hostile *messages*.
    assert set(campaign.decoded) == set(CLIENT_TYPES), campaign.decoded
    assert sum(campaign.decoded.values()) > 0.1 * campaign.frames
    assert not campaign.held_failures, campaign.held_failures[:3]
    assert campaign.held_checked > 100


def test_sessions_answer_every_frame_with_messages(campaign):
    assert not campaign.receive_failures, _show(campaign.receive_failures)
    assert not campaign.bad_outputs, campaign.bad_outputs[:5]
    assert campaign.hellos_accepted > 10  # hostile hellos (held, resume, options) were taken in
    assert {"bad_state", "invalid", "bad_msgpack"} <= set(campaign.session_codes)


def test_hostile_sessions_selections_never_raise(campaign):
    """What hostile (but valid) messages left in a session must not make its selection fail.

    The server's loop turns an exception in ``poll`` into an ``internal`` error;
    a session whose selection keeps failing gets it on every poll. Fails today
    (see the reproducers below): Delta times past the protocol's 1e9 after
    hostile clock stamps, and a fractional mesh morph level.
    """
    assert campaign.polls > 100
    assert not campaign.poll_failures, dict(campaign.poll_failures)


# --------------------------------------------------------------------------- targeted reproducers


def test_error_sentences_fit_an_error_frame_whatever_the_keys(scenes):
    """A 5000-character unknown key once made the error sentence too long for ``Error`` (receive raised)."""
    s = Session(scenes, "long-keys", stopwatch=time.perf_counter)
    for key in ("k" * 5000, b"k" * 5000, "é" * 3000):
        frame = msgpack.packb({"type": "pong", "id": 1, "sent": 0.0, "t": 0.0, key: 1}, use_bin_type=True)
        (err,) = s.receive(frame, 0.0)
        assert isinstance(err, Error) and err.code == "invalid" and len(err.message) <= 1024
        assert decode_server(encode(err)) == err


@pytest.mark.parametrize(
    "hostile",
    [
        pytest.param(lambda sc: msgpack.packb({"type": "pong", "id": 1, "sent": -1e308, "t": 0.0}), id="pong-sent-far-past"),
        pytest.param(lambda sc: msgpack.packb({"type": "pong", "id": 1, "sent": 0.0, "t": 1e9}), id="pong-t-end-of-time"),
        pytest.param(lambda sc: msgpack.packb({**msgpack.unpackb(_camera_frame(sc, 0.0)), "t": 1e9}),
                     id="camera-t-end-of-time"),
        pytest.param(lambda sc: _camera_frame(sc, 1e8), id="camera-t-at-the-client-limit"),
    ],
)
def test_hostile_clock_stamps_do_not_break_selection(scenes, hostile):
    """Valid stamps at the protocol's limits must not push a delta's times out of the protocol's range.

    Found by the campaign: ``poll`` raised a pydantic ValidationError building
    the Delta (t0 > 1e9), on every poll after — a spinning session on the server.
    """
    s = Session(scenes, "stamps", SessionConfig(), stopwatch=time.perf_counter)
    s.receive(_hello_frame(scenes), 0.0)
    out = s.receive(hostile(scenes), 0.01)
    assert all(isinstance(m, SERVER_CLASSES) for m in out)
    s.receive(_camera_frame(scenes, 0.0), 0.02)
    for now in (0.03, 1.0, 2.0, 5.0):
        for m in s.poll(now):  # must not raise
            decode_server(encode(m))


def test_a_sudden_fast_frame_does_not_break_the_morph_schedule(scenes):
    """Found by the campaign (minimised from 10k frames to these four messages and seven polls).

    Two frame reports, the second far faster, and a 1 m step: the next
    selection's Delta carried a mesh morph between fractional levels, so
    building it raised ``ValidationError: mesh morphs go between whole levels``
    inside ``poll``. The times are the campaign's own (sums of 0.002 s steps):
    with round ones it does not happen, so a schedule boundary's rounding is
    the likely cause — plausible input for any client, not only a hostile one.
    """
    s = _active_session(scenes, "morphs")
    terms = dict(triangles=[1000, 200, 30], vertices=[600, 100, 20], pixels=[50_000, 9_000, 100], draws=[10, 2, 1])
    report = dict(frame=1, t=0.1, triangles=20_000, vertices=10_000, draws=12, selection=1, pixels=100_000, splats=10)
    s.receive(_camera_frame(scenes, 0.0), 0.0)
    s.receive(encode(FrameReport(time=0.02, gpu_time=0.01, cpu_time=0.002, terms=AlgorithmTerms(**terms), **report)),
              0.21800000000000017)
    for now in (1.0000000000000007, 2.0000000000000013, 2.999999999999891, 3.999999999999781):
        s.poll(now)
    fast = AlgorithmTerms(**{**terms, "triangles": [1000, 200, 127]})
    s.receive(encode(FrameReport(time=0.0003887939453125, gpu_time=0.010000000000027534,
                                 cpu_time=0.00013262939453125, terms=fast, **report)), 4.549999999999721)
    s.receive(_camera_frame(scenes, 0.5, dx=1.0), 4.569999999999719)
    for now in (4.999999999999671, 5.999999999999561, 6.999999999999451):
        for m in s.poll(now):  # must not raise
            decode_server(encode(m))


# --------------------------------------------------------------------------- other sessions are unaffected


class _Client:
    """A well-behaved client's side of an in-process session: answers pings, acks deltas with its holdings."""

    def __init__(self, scenes) -> None:
        self.index = next(iter(scenes.values())).index
        self.held: dict[int, int] = {}
        self.deltas: list[tuple] = []

    def answer(self, out: list[BaseModel], now: float) -> list[bytes]:
        replies = []
        for m in out:
            assert not isinstance(m, Error), m
            if isinstance(m, Ping):
                replies.append(encode(Pong(id=m.id, sent=m.sent, t=now)))
            elif isinstance(m, Delta):
                for rep in m.drop:
                    self.held.pop(rep, None)
                for a in m.add:
                    self.held[a.rep] = len(a.geometry)
                self.deltas.append((m.seq, m.reset, tuple(m.selection), tuple(sorted(a.rep for a in m.add)), tuple(m.drop)))
                reps = np.fromiter(self.held, np.int64, len(self.held))
                replies.append(encode(Ack(seq=m.seq, t=now, held=len(self.held), digest=digest(reps),
                                          held_bytes=sum(self.held.values()))))
        return replies


def _tour_pose(index, u: float) -> dict:
    """A pose along the scene's tour, ``u`` in [0, 1]: the script both good sessions follow."""
    keys = index.tour
    ts = np.array([k["t"] for k in keys])
    t = u * ts[-1]
    j = int(np.clip(np.searchsorted(ts, t) - 1, 0, len(keys) - 2))
    w = float(np.clip((t - ts[j]) / max(ts[j + 1] - ts[j], 1e-9), 0.0, 1.0))
    a, b = keys[j], keys[j + 1]
    out = {k: ((1 - w) * np.asarray(a[k], float) + w * np.asarray(b[k], float)).tolist() for k in ("eye", "forward", "up")}
    return out


def test_a_good_session_is_unaffected_by_a_hostile_one_beside_it(scenes):
    """The same script into a session beside a hostile one and into a control: identical deltas.

    A selection's wall time feeds the session's lead estimate and its anytime
    solver's deadline, so on a loaded machine two runs of one script differ;
    the sessions' selection stopwatch is a step counter here (1 ms a reading)
    so that any difference left is the hostile session's doing.
    """
    def stopwatch():
        ticks = iter(range(1 << 62))
        return lambda: next(ticks) * 1e-3

    index = next(iter(scenes.values())).index
    fuzz = Fuzzer(seed_messages(index), SEED + 1)
    good = Session(scenes, "good", SessionConfig(), stopwatch=stopwatch())
    control = Session(scenes, "control", SessionConfig(), stopwatch=stopwatch())
    hostile = [Session(scenes, "hostile-fresh", SessionConfig(), stopwatch=stopwatch()),
               _active_session(scenes, "hostile")]
    clients = {good: _Client(scenes), control: _Client(scenes)}
    fed = 0

    def storm(now: float) -> None:
        nonlocal fed
        for _ in range(15):
            frame = fuzz.frame()
            for h in hostile:
                out = h.receive(frame, now)
                assert all(isinstance(m, SERVER_CLASSES) for m in out)
            fed += 1

    def both(frame: bytes, now: float) -> None:
        for s in (good, control):
            storm(now) if s is good else None
            replies = clients[s].answer(s.receive(frame, now), now)
            for r in replies:
                if s is good:
                    storm(now)
                assert clients[s].answer(s.receive(r, now), now) == []

    both(_hello_frame(scenes), 0.0)
    steps = 100
    for k in range(steps):
        now = 0.05 * (k + 1)
        pose = _tour_pose(index, k / steps)
        both(encode(Camera(t=now, **pose)), now)
        both(encode(FrameReport(frame=k, t=now, time=0.03, triangles=30_000, vertices=16_000, draws=20)), now)
        for s in (good, control):
            if s is good:
                storm(now)
            for r in clients[s].answer(s.poll(now), now):
                assert clients[s].answer(s.receive(r, now), now) == []
    assert fed > 3_000
    got, want = clients[good].deltas, clients[control].deltas
    assert len(want) >= 5 and want[0][1]  # the script produced a stream (a reset first) ...
    assert got == want  # ... and the good session's is the control's, delta for delta
    assert good.errors == control.errors == 0 and good.stats["mirror_mismatch"] == 0


def test_a_hostile_session_stays_usable_after_garbage(scenes):
    """After thousands of refused frames, a session that said hello still answers a camera with a delta."""
    index = next(iter(scenes.values())).index
    fuzz = Fuzzer(seed_messages(index), SEED + 2)
    s = _active_session(scenes, "garbage")
    refused = 0
    while refused < 3_000:
        frame = fuzz.frame()
        try:
            decode_client(frame)
            continue  # a valid message is not garbage: it may legitimately change the session
        except ProtocolError:
            pass
        (err,) = s.receive(frame, 0.01)
        assert isinstance(err, Error) and err.code in ERROR_CODES
        refused += 1
    assert s.state is SessionState.ACTIVE and s.errors == refused and s.camera is None
    assert s.receive(_camera_frame(scenes, 0.1), 0.1) == []
    deltas = [m for m in s.poll(0.1) if isinstance(m, Delta)]
    assert len(deltas) == 1 and deltas[0].seq == 1 and deltas[0].reset and deltas[0].selection


# --------------------------------------------------------------------------- hypothesis: near-valid maps


_finite = st.floats(allow_nan=False, allow_infinity=False)
_junk = st.one_of(st.none(), st.booleans(), st.integers(-(1 << 63), (1 << 64) - 1), st.floats(), st.text(max_size=8),
                  st.binary(max_size=8), st.lists(st.integers(-3, 3), max_size=4),
                  st.dictionaries(st.text(max_size=3), st.integers(), max_size=2))
_vec = st.lists(st.one_of(_finite, st.integers(-10, 10)), min_size=2, max_size=4)
_count = st.one_of(st.integers(0, 1 << 32), st.integers(-5, -1), st.integers((1 << 32) + 1, (1 << 64) - 1))
_time = st.one_of(st.floats(-2e9, 2e9), st.sampled_from([0.0, 1e9, -1e9, 60.0, NAN, INF]))
_name = st.one_of(st.sampled_from(["demo", "greedy", "x"]), st.text(max_size=6), st.text(min_size=127, max_size=130))
_ids = st.lists(st.one_of(st.integers(0, (1 << 31) - 1), st.integers(-2, -1), st.just(1 << 31)), max_size=6)
_terms = st.fixed_dictionaries({}, optional={k: st.lists(_count, max_size=4)
                                             for k in ("triangles", "vertices", "pixels", "draws")})

FIELDS = {
    "hello": {"protocol": st.sampled_from([PROTOCOL_VERSION, 3, 5, -1]), "scene": _name,
              "viewport": st.lists(st.integers(0, 20000), min_size=1, max_size=3),
              "fov_y": st.floats(0, 200), "target_frame_time": st.floats(0, 3), "solver": _name,
              "client": st.text(max_size=130), "predict": st.booleans(), "morph": st.booleans(),
              "max_speed": st.one_of(st.none(), st.floats(-1, 2e4)), "max_turn": st.one_of(st.none(), st.floats(-1, 4000)),
              "cache_bytes": st.one_of(st.none(), st.integers(0, 1 << 41)),
              "algorithms": st.lists(st.sampled_from(["flat", "lit", "textured", "wire"]), max_size=4),
              "resume": st.one_of(st.none(), st.fixed_dictionaries({"session": st.text(max_size=130),
                                                                   "token": st.text(min_size=10, max_size=140)})),
              "held": st.one_of(st.none(), st.binary(max_size=64), st.builds(lambda ids: pack_held(np.asarray(ids, np.int64)),
                                                                             st.lists(st.integers(0, 5000), max_size=30)))},
    "camera": {"t": _time, "eye": _vec, "forward": _vec, "up": _vec},
    "frame_report": {"frame": _count, "t": _time, "time": st.floats(-1, 70), "triangles": _count, "vertices": _count,
                     "draws": _count, "selection": st.integers(-3, 1 << 31), "pixels": _count, "splats": _count,
                     "gpu_time": st.one_of(st.none(), st.floats(-1, 70)), "cpu_time": st.floats(-1, 70),
                     "terms": st.one_of(st.none(), _terms)},
    "pong": {"id": _count, "sent": st.one_of(st.floats(), st.integers(-(1 << 63), (1 << 63) - 1)), "t": _time},
    "heartbeat": {"kiosk": st.one_of(st.from_regex(r"[A-Za-z0-9_.\-]{1,64}", fullmatch=True), st.text(max_size=70)),
                  "t": _time, "interval": st.floats(0, 700), "frames": _count,
                  "state": st.sampled_from(["attract", "visitor", "countdown", "closed", "reconnecting", "off", ""]),
                  "fps": st.floats(-1, 2e4), "frame_p95": st.floats(-1, 70),
                  "recent": st.lists(st.floats(-1, 70), max_size=125), "rss": st.integers(-1, (1 << 42) + 1),
                  "gpu_memory": st.one_of(st.none(), st.integers(-1, (1 << 42) + 1)),
                  "cache_bytes": st.integers(-1, (1 << 42) + 1), "reconnects": _count,
                  "tour": st.text(max_size=130), "stop": st.integers(-2, (1 << 16) + 1)},
    "ack": {"seq": _count, "t": _time, "rejected": _ids, "held": st.integers(-3, (1 << 20) + 2),
            "digest": st.one_of(st.integers(0, (1 << 64) - 1), st.integers(-3, -1)), "held_bytes": _count},
}


@st.composite
def near_valid(draw):
    """A map with a client type and that type's fields, each drawn near and past its limits, some replaced or missing."""
    kind = draw(st.sampled_from(sorted(FIELDS)))
    obj = {"type": kind}
    for name, strat in FIELDS[kind].items():
        roll = draw(st.integers(0, 19))
        if roll == 0:
            continue  # missing
        obj[name] = draw(_junk) if roll == 1 else draw(strat)
    if draw(st.integers(0, 9)) == 0:
        obj[draw(st.text(min_size=1, max_size=5))] = draw(_junk)  # an unknown key (or a known one overwritten)
    if draw(st.integers(0, 19)) == 0:
        obj["type"] = draw(st.sampled_from(sorted(FIELDS) + ["delta", "welcome", "nope"]))
    return obj


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(near_valid())
def test_near_valid_maps_validate_fully_or_are_refused_with_a_known_code(obj):
    try:
        frame = msgpack.packb(obj, use_bin_type=True)
    except OverflowError:  # an integer msgpack cannot carry never reaches the wire
        assume(False)
    try:
        msg = decode_client(frame)
    except ProtocolError as exc:
        assert exc.code in ERROR_CODES and exc.message
        assert len(Error(code=exc.code, message=exc.message).message) <= 4096
        return
    # Validated fully: the type is right, every field obeys the contract and it re-encodes to itself.
    assert isinstance(msg, CLIENT_TYPES[obj["type"]])
    assert decode_client(encode(msg)) == msg
    assert type(msg).model_validate(msg.model_dump()) == msg
    for v in msg.model_dump().values():
        if isinstance(v, float):
            assert math.isfinite(v)


# --------------------------------------------------------------------------- over a real server


#: Hostile frames over the real server's websocket, the burst sent at once and the rate after it. The server
#: runs with its per-session rate limit raised to 1000/s (burst 1000; the default is 200/s, burst 400) so that a
#: few thousand frames take seconds, and they are paced under it so they reach the decoder, not the limiter.
HOSTILE_FRAMES, HOSTILE_BURST, HOSTILE_RATE = 3_000, 800, 900.0
# Within every limit but the one under test: the frames must reach the decoder and the session, not be cut
# off by the bad-frame count, the byte rate or the reconnect rate (tests/integration/test_limits_hostile.py
# tests those).
SERVER_LIMITS = ["--rate", "1000", "--burst", "1000", "--max-bad-frames", "1000000", "--byte-rate", "1e9",
                 "--connect-rate", "1e6"]


def test_real_server_hostile_socket_beside_a_good_one(demo_store):
    """Thousands of hostile frames over one websocket of a real server while a real good session streams."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    from bench.demo import ServerProcess

    with SceneStore.open(demo_store) as store:
        index = store.index
    fuzz = Fuzzer(seed_messages(index), SEED + 3)
    # A valid hello first, so the frames after it reach an active session's handlers too.
    hostile_frames = [_hello_frame({index.name: None})] + [fuzz.frame() for _ in range(HOSTILE_FRAMES - 1)]
    with ServerProcess([demo_store], extra=SERVER_LIMITS) as srv:
        good_deltas: list[tuple[float, int]] = []
        good_errors: list[Error] = []
        hostile_codes: Counter = Counter()
        hostile_sent = 0
        reconnects = 0
        first_delta, hostile_done, stop = threading.Event(), threading.Event(), threading.Event()
        hostile_window: list[float] = []

        def hostile() -> None:
            nonlocal hostile_sent, reconnects
            first_delta.wait(30)
            hostile_window.append(time.monotonic())
            i = 0
            # One pace for the whole storm: a frame over the protocol's limit closes its socket (1009), and a
            # new socket's bucket starts full, so the pace need not restart with it.
            began = time.monotonic()
            try:
                while i < len(hostile_frames):
                    try:
                        with connect(srv.url, max_size=None, open_timeout=10) as ws:
                            def drain() -> None:
                                try:
                                    for raw in ws:
                                        m = decode_server(raw)
                                        if isinstance(m, Error):
                                            hostile_codes[m.code] += 1
                                except ConnectionClosed:
                                    pass
                            reader = threading.Thread(target=drain, daemon=True)
                            reader.start()
                            while i < len(hostile_frames):
                                # Within the server's rate limit (the burst at once, then just under the rate),
                                # so the frames reach the decoder and the session rather than the limiter.
                                due = began + max(0, i - HOSTILE_BURST) / HOSTILE_RATE
                                if due > time.monotonic():
                                    stop.wait(due - time.monotonic())
                                ws.send(hostile_frames[i])
                                i += 1
                                hostile_sent += 1
                            ws.close()
                            reader.join(10)
                    except (ConnectionClosed, OSError):
                        reconnects += 1  # the hostile socket's fate is its own: go on over a new one
            finally:
                hostile_window.append(time.monotonic())
                hostile_done.set()

        attacker = threading.Thread(target=hostile, daemon=True)
        attacker.start()
        with connect(srv.url, max_size=None, open_timeout=10) as ws:
            ws.send(_hello_frame({index.name: None}))
            held: dict[int, int] = {}
            t0 = time.monotonic()
            frame_no = 0
            settle_until = None
            while True:
                now = time.monotonic() - t0
                if hostile_done.is_set() and settle_until is None:
                    settle_until = len(good_deltas) + 2  # the good session goes on after the storm: two more deltas
                if settle_until is not None and len(good_deltas) >= settle_until:
                    break
                assert now < 60, f"the good session ran out of time with {len(good_deltas)} deltas"
                ws.send(encode(Camera(t=now, **_tour_pose(index, min(now / 30.0, 1.0)))))
                ws.send(encode(FrameReport(frame=frame_no, t=now, time=0.03, triangles=30_000, vertices=16_000, draws=20)))
                frame_no += 1
                deadline = time.monotonic() + 0.05
                while (left := deadline - time.monotonic()) > 0:  # read what came, for one frame's time
                    try:
                        m = decode_server(ws.recv(timeout=left))
                    except TimeoutError:
                        break
                    if isinstance(m, Ping):
                        ws.send(encode(Pong(id=m.id, sent=m.sent, t=time.monotonic() - t0)))
                    elif isinstance(m, Delta):
                        for rep in m.drop:
                            held.pop(rep, None)
                        for a in m.add:
                            held[a.rep] = len(a.geometry)
                        reps = np.fromiter(held, np.int64, len(held))
                        ws.send(encode(Ack(seq=m.seq, t=time.monotonic() - t0, held=len(held), digest=digest(reps),
                                           held_bytes=sum(held.values()))))
                        good_deltas.append((time.monotonic(), m.seq))
                        first_delta.set()
                    elif isinstance(m, Error):
                        good_errors.append(m)
        attacker.join(30)
        health = httpx.get(srv.http + "/health", timeout=10)
    print(f"\nhostile: {hostile_sent} frames sent, {reconnects} reconnects, answered {dict(hostile_codes)}; "
          f"good: {len(good_deltas)} deltas at {[round(t - hostile_window[0], 2) for t, _ in good_deltas]} s "
          f"from the storm's start (it lasted {hostile_window[1] - hostile_window[0]:.1f} s)")
    assert not attacker.is_alive() and hostile_sent == len(hostile_frames)
    assert not good_errors, good_errors[:3]
    seqs = [s for _, s in good_deltas]
    assert seqs == list(range(1, len(seqs) + 1))  # every delta, in order, none lost
    start, end = hostile_window
    assert sum(start <= t <= end for t, _ in good_deltas) >= 1  # deltas kept coming under fire ...
    assert sum(t > end for t, _ in good_deltas) >= 2  # ... and after it
    assert health.status_code == 200 and health.json()["status"] == "ok"
    assert set(hostile_codes) <= set(ERROR_CODES) and hostile_codes  # the hostile socket was answered
    assert "internal" not in hostile_codes, f"the server failed on hostile input: {dict(hostile_codes)}"
