"""One simulated client of the load test: a session that speaks the protocol like the real client
but draws nothing — its frame time comes from a renderer model (``RendererModel``) applied to the
vertex and face counts of what it holds (``HeldSet``), read from the payloads' map headers.
"""

from __future__ import annotations

import asyncio
import math
from collections import Counter
from dataclasses import dataclass

import msgpack
import numpy as np

from proto.manifest import mix
from proto.messages import ALGORITHMS, PROTOCOL_VERSION

__all__ = [
    "RendererModel", "HeldSet", "payload_counts", "unframe", "ClientConfig", "SimulatedClient", "VIEWPORTS",
    "CLIENT_NAME",
]


#: Viewports the simulated clients pick from (a mix of screens, as real users bring).
VIEWPORTS = ((640, 360), (800, 600), (1280, 720), (1920, 1080))
CLIENT_NAME = "walkstream-loadtest/0.1"
#: Poses and noise are drawn this many frames at a time (one vectorised ``Tour.pose_at`` per chunk).
_CHUNK = 64
_ALGS = len(ALGORITHMS)


# --------------------------------------------------------------------------- renderer model


@dataclass(frozen=True)
class RendererModel:
    """Frame time of a simulated GPU: (overhead + c_vertex·V + c_face·F + c_splat·S) × lognormal(0, sigma).

    Linear in the drawn vertices, as the server's cost model assumes, so a
    server whose fitted model tracks the client holds the budget; the noise is
    what a real frame's time varies by. ``c_face`` and ``c_splat`` are off by
    default (set them to exercise the server's staged model).
    """

    overhead: float = 2.0e-3
    c_vertex: float = 1.5e-7
    c_face: float = 0.0
    c_splat: float = 0.0
    sigma: float = 0.05

    def __post_init__(self) -> None:
        for name in ("overhead", "c_vertex", "c_face", "c_splat", "sigma"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be finite and non-negative, got {value!r}")

    def time(self, vertices: float, faces: float, splats: float = 0.0, noise: float = 1.0) -> float:
        """Seconds for one frame (``noise``: a lognormal factor drawn by the caller), within the protocol's (0, 60]."""
        t = (self.overhead + self.c_vertex * vertices + self.c_face * faces + self.c_splat * splats) * noise
        return min(max(t, 1e-6), 60.0)


# --------------------------------------------------------------------------- what a client holds


def payload_counts(blob: bytes) -> tuple[int, int, int]:
    """(vertices, faces, instances) of a representation payload, read from its msgpack map without decoding it.

    Meshes (``proto.geometry``) carry ``nv`` and ``nf``, tree groups
    (``proto.points`` instance lists) ``k``; the buffers are skipped, not copied.
    A payload that is not such a map counts as empty.
    """
    u = msgpack.Unpacker(raw=False)
    u.feed(blob)
    out = {"nv": 0, "nf": 0, "k": 0}
    try:
        n = u.read_map_header()
        found = 0
        for _ in range(n):
            key = u.unpack()
            if key in out:
                value = u.unpack()
                out[key] = int(value) if isinstance(value, int) else 0
                found += 1
                if found == 2 or key == "k":
                    break
            else:
                u.skip()
    except Exception:  # not a map, truncated: nothing to draw
        return 0, 0, 0
    return out["nv"], out["nf"], out["k"]


class HeldSet:
    """The representations a simulated client holds, as arrays indexed by id, kept like ``client.cache``.

    Adds first (a re-added rep replaces its bytes), then drops; nothing is
    refused (the simulated cache has no budget of its own: the server's mirror
    keeps to its default). ``held``, ``held_bytes`` and ``digest`` are what an
    ack reports; the digest is updated by XOR of the ids that entered or left.
    """

    def __init__(self, size: int = 1024) -> None:
        self.mask = np.zeros(size, bool)
        self.nbytes = np.zeros(size, np.int64)
        self.vertices = np.zeros(size, np.int64)
        self.faces = np.zeros(size, np.int64)
        self.instances = np.zeros(size, np.int64)
        self.held = 0
        self.held_bytes = 0
        self.digest = 0

    def _grow(self, top: int) -> None:
        if top < self.mask.size:
            return
        size = max(top + 1, 2 * self.mask.size)
        for name in ("mask", "nbytes", "vertices", "faces", "instances"):
            old = getattr(self, name)
            new = np.zeros(size, old.dtype)
            new[: old.size] = old
            setattr(self, name, new)

    def apply(self, reps: np.ndarray, sizes: np.ndarray, counts: np.ndarray, drop: np.ndarray) -> None:
        """Apply one delta's adds (ids, payload bytes, (n, 3) vertices/faces/instances) and then its drops."""
        reps = np.asarray(reps, np.int64)
        drop = np.asarray(drop, np.int64)
        if reps.size and reps.min() < 0 or drop.size and drop.min() < 0:
            raise ValueError("representation ids are ≥ 0")
        top = max(int(reps.max()) if reps.size else -1, int(drop.max()) if drop.size else -1)
        self._grow(top)
        toggled = np.zeros(0, np.int64)
        if reps.size:
            # The last add of a rep wins (np.unique on the reversed ids keeps last occurrences).
            last = reps.size - 1 - np.unique(reps[::-1], return_index=True)[1]
            ids = reps[last]
            toggled = ids[~self.mask[ids]]
            self.mask[ids] = True
            self.nbytes[ids] = np.asarray(sizes, np.int64)[last]
            c = np.asarray(counts, np.int64).reshape(-1, 3)[last]
            self.vertices[ids], self.faces[ids], self.instances[ids] = c[:, 0], c[:, 1], c[:, 2]
        if drop.size:
            gone = np.unique(drop)
            gone = gone[self.mask[gone]]
            self.mask[gone] = False
            toggled = np.concatenate([toggled, gone])
        if toggled.size:
            self.digest ^= int(np.bitwise_xor.reduce(mix(toggled)))
        self.held = int(self.mask.sum())
        self.held_bytes = int(self.nbytes[self.mask].sum())

    def ids(self) -> np.ndarray:
        return np.flatnonzero(self.mask)

    def draws(self, selection: np.ndarray, algorithm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per rendering algorithm: (faces, vertices, draws) of the held reps of ``selection``, each (3,) int64."""
        sel = np.asarray(selection, np.int64)
        ok = (sel >= 0) & (sel < self.mask.size)
        ok[ok] = self.mask[sel[ok]]
        reps = sel[ok]
        alg = np.asarray(algorithm, np.int64)[ok] if len(algorithm) == sel.size else np.zeros(reps.size, np.int64)
        alg = np.clip(alg, 0, _ALGS - 1)
        faces = np.bincount(alg, weights=self.faces[reps], minlength=_ALGS).astype(np.int64)
        verts = np.bincount(alg, weights=self.vertices[reps], minlength=_ALGS).astype(np.int64)
        draws = np.bincount(alg, minlength=_ALGS).astype(np.int64)
        return faces, verts, draws


# --------------------------------------------------------------------------- one simulated client

#: zstd's frame magic: a server frame that starts with it is a zstd-compressed msgpack map (``proto.codec``).
_ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
#: The largest frame the client inflates (``proto.codec.MAX_SERVER_FRAME``).
_MAX_FRAME = 256 * 1024 * 1024


_inflate = None  # one zstd decompressor: every client runs on this process's one event-loop thread


def unframe(data: bytes) -> dict:
    """A server frame's msgpack map (inflating a zstd frame first, bounded by its declared size)."""
    global _inflate
    if data[:4] == _ZSTD_MAGIC:
        import zstandard

        size = zstandard.frame_content_size(data)
        if not 0 <= size <= _MAX_FRAME:
            raise ValueError(f"compressed frame declares {size} bytes")
        if _inflate is None:
            _inflate = zstandard.ZstdDecompressor()
        data = _inflate.decompress(data, max_output_size=size)
    obj = msgpack.unpackb(data, raw=False)
    if not isinstance(obj, dict):
        raise ValueError(f"a server frame is a map, got {type(obj).__name__}")
    return obj


@dataclass(frozen=True)
class ClientConfig:
    url: str
    http: str
    scene: str
    rate: float
    target: float
    algorithms: tuple[str, ...]
    model: RendererModel
    seed: int
    timeout: float = 10.0
    separate: bool = False  # each frame's report in a message of its own, as clients did before ``Camera.report``


class SimulatedClient:
    """One simulated session: a sender paced at ``rate`` Hz and a receiver answering pings and acking deltas."""

    def __init__(self, index: int, n: int, cfg: ClientConfig) -> None:
        self.index, self.n, self.cfg = index, n, cfg
        self.rng = np.random.default_rng([cfg.seed, index])
        w, h = VIEWPORTS[int(self.rng.integers(len(VIEWPORTS)))]
        self.viewport = (w, h)
        self.held = HeldSet()
        self.opened = False
        self.connected = False
        self.session = ""
        self.errors: Counter[str] = Counter()
        self.deltas = 0
        self.bytes = 0
        self.acks = 0
        self.pongs = 0
        self.frames = 0
        self.skipped = 0  # frames the sender skipped because this process fell behind
        self.arrivals: list[float] = []  # loop time of each delta
        self.frame_at: list[float] = []  # loop time of each frame report ...
        self.frame_time: list[float] = []  # ... and its modelled time (s)
        self.stopping = False
        self.start = 0.0  # the client clock's origin (loop time)
        # The selection drawn now, and those still to come: (t0 on the client clock, seq, reps, algorithms,
        # tree groups, their resolutions); the current one without its t0.
        self._pending: list[tuple[float, int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        self._current: tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        self._work: tuple | None = None  # cached per-frame terms of the current selection
        self.seq_drawn = -1
        self.tau: float | None = None  # the server's τ, from the welcome

    # ---------------------------------------------------------------- messages (plain dicts, schema of proto.messages)

    def hello(self) -> bytes:
        from proto.codec import encode
        from proto.messages import Hello

        return encode(Hello(protocol=PROTOCOL_VERSION, scene=self.cfg.scene, viewport=list(self.viewport),
                            target_frame_time=self.cfg.target, client=CLIENT_NAME,
                            algorithms=list(self.cfg.algorithms)))

    def ack(self, seq: int, t: float) -> dict:
        h = self.held
        return {"type": "ack", "seq": seq, "t": t, "rejected": [], "held": h.held, "held_bytes": h.held_bytes,
                "digest": h.digest}

    def frame_report(self, frame: int, t: float, noise: float) -> tuple[dict, float]:
        """The frame report for client time ``t`` and the modelled frame time (s)."""
        self._advance(t)
        if self._work is None:
            self._work = self._terms()
        faces, verts, draws, splats = self._work
        ft = self.cfg.model.time(float(verts.sum()), float(faces.sum()), splats, noise)
        report = {
            "type": "frame_report", "frame": frame, "t": t, "time": ft,
            "triangles": int(faces.sum()), "vertices": int(verts.sum()), "draws": int(draws.sum()),
            "selection": self.seq_drawn, "pixels": 0, "splats": splats, "gpu_time": None, "cpu_time": 0.0,
            "terms": {"triangles": faces.tolist(), "vertices": verts.tolist(), "pixels": [0] * _ALGS,
                      "draws": draws.tolist()},
        }
        return report, ft

    # ---------------------------------------------------------------- deltas

    def apply_delta(self, d: dict, t: float) -> dict:
        """Apply a raw delta map (client time of arrival ``t``); returns its ack."""
        adds = d.get("add") or ()
        n = len(adds)
        reps = np.fromiter((a["rep"] for a in adds), np.int64, n)
        sizes = np.fromiter((len(a["geometry"]) for a in adds), np.int64, n)
        counts = np.array([payload_counts(a["geometry"]) for a in adds], np.int64).reshape(-1, 3)
        self.held.apply(reps, sizes, counts, np.asarray(d.get("drop") or (), np.int64))
        seq = int(d.get("seq", 0))
        sel = np.asarray(d.get("selection") or (), np.int64)
        alg = np.asarray(d.get("algorithm") or (), np.int64)
        veg = np.asarray(d.get("vegetation") or (), np.int64)
        res = np.asarray(d.get("resolution") or (), np.float64)
        t0 = float(d.get("t0", t))
        entry = (t0, seq, sel, alg, veg, res)
        if d.get("reset") or d.get("start") is None:  # replaces what is drawn at once
            self._pending = []
            self._current = entry[1:]
            self.seq_drawn = seq
        else:
            self._pending = [p for p in self._pending if p[0] < t0] + [entry]
        self._work = None  # what is held changed: the drawn work may have
        return self.ack(seq, t)

    def _advance(self, t: float) -> None:
        while self._pending and self._pending[0][0] <= t:
            entry = self._pending.pop(0)
            self._current = entry[1:]
            self.seq_drawn = entry[1]
            self._work = None

    def _terms(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        if self._current is None:
            z = np.zeros(_ALGS, np.int64)
            return z, z, z, 0
        _, sel, alg, veg, res = self._current
        faces, verts, draws = self.held.draws(sel, alg)
        splats = 0
        if veg.size and res.size == veg.size:
            ok = (veg >= 0) & (veg < self.held.mask.size)
            ok[ok] = self.held.mask[veg[ok]]
            splats = int(np.rint((self.held.instances[veg[ok]] * res[ok]).sum()))
        return faces, verts, draws, splats

    # ---------------------------------------------------------------- the session

    async def run(self, at: float, stop: asyncio.Event, counters: "_Totals") -> None:
        """Connect at loop time ``at`` and run until ``stop`` is set or the connection ends."""
        from websockets.asyncio.client import connect
        from websockets.exceptions import ConnectionClosed

        loop = asyncio.get_running_loop()
        self.totals = counters
        await asyncio.sleep(max(0.0, at - loop.time()))
        if stop.is_set():
            return
        self.start = loop.time()
        try:
            ws = await connect(self.cfg.url, max_size=None, open_timeout=self.cfg.timeout,
                               user_agent_header=CLIENT_NAME)
        except Exception as exc:
            self.errors["connect_failed"] += 1
            counters.note(f"client {self.index}: cannot connect: {type(exc).__name__}: {exc}")
            return
        try:
            if not await self._handshake(ws, counters):
                return
            self.connected = True
            receiver = asyncio.create_task(self._receive(ws, loop))
            try:
                await self._send(ws, loop, stop, receiver)
            except ConnectionClosed:
                pass  # the receiver saw it too, and counts it
            self.stopping = True
            await ws.close()
            await receiver
        except ConnectionClosed:  # during the handshake
            if not self.stopping:
                self.errors["connection_lost"] += 1
        finally:
            self.connected = False
            self.stopping = True
            await ws.close()

    async def _handshake(self, ws, counters: "_Totals") -> bool:
        from proto.codec import decode_server
        from proto.errors import ProtocolError
        from proto.messages import Error, Welcome

        from websockets.exceptions import ConnectionClosed

        try:
            await ws.send(self.hello())
        except ConnectionClosed:
            pass  # a refusing server (busy) may close at once: its error frame is still there to read
        try:
            data = await asyncio.wait_for(ws.recv(), self.cfg.timeout)
        except asyncio.TimeoutError:
            self.errors["no_welcome"] += 1
            return False
        except ConnectionClosed as exc:
            self.errors["connection_lost"] += 1
            counters.note(f"client {self.index}: closed before the welcome: {exc}")
            return False
        self.bytes += len(data)
        try:
            msg = decode_server(data)
        except ProtocolError as exc:
            self.errors["undecodable"] += 1
            counters.note(f"client {self.index}: the first frame does not decode: {exc}")
            return False
        if isinstance(msg, Error):
            self.errors[msg.code] += 1
            counters.note(f"client {self.index}: refused: {msg.code}: {msg.message}")
            return False
        if not isinstance(msg, Welcome):
            self.errors["unexpected"] += 1
            return False
        self.opened, self.session, self.tau = True, msg.session, float(msg.tau)
        from proto.tour import Tour

        self.tour = Tour(msg.tour) if msg.tour else Tour([{"t": 0.0, **msg.start.model_dump()}])
        # Each client its own stretch of the looped tour.
        self.phase = self.tour.t[0] + self.tour.duration * ((self.index / self.n + self.rng.random() * 0.01) % 1.0)
        return True

    async def _receive(self, ws, loop) -> None:
        from websockets.exceptions import ConnectionClosed

        packb = msgpack.packb
        try:
            async for data in ws:
                now = loop.time()
                t = now - self.start
                self.bytes += len(data)
                try:
                    obj = unframe(data)
                    kind = obj.get("type")
                except Exception as exc:
                    self.errors["undecodable"] += 1
                    self.totals.note(f"client {self.index}: a frame does not decode: {type(exc).__name__}: {exc}")
                    continue
                if kind == "ping":
                    await ws.send(packb({"type": "pong", "id": obj["id"], "sent": obj["sent"], "t": t}))
                    self.pongs += 1
                elif kind == "delta":
                    self.deltas += 1
                    self.arrivals.append(now)
                    await ws.send(packb(self.apply_delta(obj, t)))
                    self.acks += 1
                elif kind == "error":
                    self.errors[str(obj.get("code", "?"))[:64]] += 1
                else:
                    self.errors["unexpected"] += 1
        except ConnectionClosed:
            pass
        if not self.stopping:
            self.errors["connection_lost"] += 1

    async def _send(self, ws, loop, stop: asyncio.Event, receiver: asyncio.Task) -> None:
        packb = msgpack.packb
        period = 1.0 / self.cfg.rate
        camera = {"type": "camera", "t": 0.0, "eye": None, "forward": None, "up": None}
        k = 0
        chunk_at = -_CHUNK
        eyes = fwds = ups = noise = None
        while not stop.is_set() and not receiver.done():
            due = self.start + k * period
            wait = due - loop.time()
            if wait > 0:
                await asyncio.sleep(wait)
            elif wait < -period:  # behind by over a frame (an overloaded loop): skip, as a real client drops frames
                skip = int(-wait / period)
                self.skipped += skip
                k += skip
                continue
            if k >= chunk_at + _CHUNK:
                chunk_at = k
                ts = self.phase + (k + np.arange(_CHUNK)) * period
                e, f, u = self.tour.pose_at(ts)
                eyes, fwds, ups = e.tolist(), f.tolist(), u.tolist()
                noise = self.rng.lognormal(0.0, self.cfg.model.sigma, _CHUNK).tolist()
            j = k - chunk_at
            t = k * period
            camera["t"], camera["eye"], camera["forward"], camera["up"] = t, eyes[j], fwds[j], ups[j]
            report, ft = self.frame_report(self.frames, t, noise[j])
            if self.cfg.separate:
                await ws.send(packb(camera))
                await ws.send(packb(report))
            else:
                camera["report"] = report  # one message a frame, as the walkstream client sends
                await ws.send(packb(camera))
            self.frame_at.append(loop.time())
            self.frame_time.append(ft)
            self.frames += 1
            k += 1
