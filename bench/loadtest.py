"""``walkstream loadtest``: many simulated clients against one server, and what it cost the server.

Each simulated client speaks protocol 4 like the real one (hello, camera poses
along the scene's tour, a frame report per frame, pongs at once, an ack with
``held``/``held_bytes``/``digest`` after every delta) but draws nothing: its
frame time comes from a renderer model (``RendererModel``) applied to the
vertex and face counts of what its selection draws. All clients share one
asyncio loop in this process, so the load generator must stay cheap next to
the server it measures (they share the machine's cores):

- outgoing messages are msgpack maps built by hand to match ``proto.messages``
  (no pydantic per message; the test checks them against the real decoder);
- incoming frames are unpacked with msgpack only; a payload's vertex and face
  counts are read from its map header, the geometry is never decoded;
- poses come from the tour in vectorised chunks, not one ``pose_at`` per frame.

The server's side of the story comes from its ``/metrics`` (Prometheus text):
the selection-latency histogram over the measured window, CPU seconds
(``process_cpu_seconds_total``) and bytes out. A one-client reference is
measured in the same run first, because a shared machine's absolute figures
drift; the ratios against it are what to read.
"""

from __future__ import annotations

import asyncio
import math
import os
import time
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import msgpack
import numpy as np

from proto.manifest import mix
from proto.messages import ALGORITHMS, PROTOCOL_VERSION

__all__ = [
    "LoadtestError",
    "RendererModel",
    "HeldSet",
    "payload_counts",
    "unframe",
    "Scrape",
    "parse_metrics",
    "histogram_quantile",
    "PhaseResult",
    "LoadSummary",
    "run_loadtest",
    "format_summary",
    "GOAL_SESSIONS_PER_CORE",
    "GOAL_P99_MS",
]

#: Issue 7's benchmark goal: sessions per server core, and the p99 selection latency (ms).
GOAL_SESSIONS_PER_CORE = 100.0
GOAL_P99_MS = 100.0
#: Viewports the simulated clients pick from (a mix of screens, as real users bring).
VIEWPORTS = ((640, 360), (800, 600), (1280, 720), (1920, 1080))
CLIENT_NAME = "walkstream-loadtest/0.1"
#: Poses and noise are drawn this many frames at a time (one vectorised ``Tour.pose_at`` per chunk).
_CHUNK = 64
_ALGS = len(ALGORITHMS)


class LoadtestError(RuntimeError):
    """The load test cannot run (no server, no /metrics, an unknown scene)."""


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


# --------------------------------------------------------------------------- the server's /metrics


@dataclass
class Scrape:
    """One reading of ``/metrics`` at monotonic time ``at``.

    hist : histogram name → (le (b,) float64 with +inf last, cumulative counts (b,) float64), summed over labels
    values : sample name (counters with ``_total``) → value, summed over labels
    errors : ``walkstream_errors_total`` by ``code``
    """

    at: float
    hist: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    values: dict[str, float] = field(default_factory=dict)
    errors: dict[str, float] = field(default_factory=dict)


def parse_metrics(text: str, at: float = 0.0) -> Scrape:
    """Prometheus text → ``Scrape`` (prometheus_client's parser)."""
    from prometheus_client.parser import text_string_to_metric_families

    out = Scrape(at=at)
    buckets: dict[str, dict[float, float]] = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            if family.type == "histogram" and s.name.endswith("_bucket"):
                le = float(s.labels["le"])
                b = buckets.setdefault(s.name[: -len("_bucket")], {})
                b[le] = b.get(le, 0.0) + float(s.value)
                continue
            out.values[s.name] = out.values.get(s.name, 0.0) + float(s.value)
            if s.name == "walkstream_errors_total" and "code" in s.labels:
                out.errors[s.labels["code"]] = out.errors.get(s.labels["code"], 0.0) + float(s.value)
    for name, b in buckets.items():
        le = np.array(sorted(b), np.float64)
        out.hist[name] = (le, np.array([b[x] for x in le], np.float64))
    return out


def histogram_quantile(le: np.ndarray, cumulative: np.ndarray, q: float) -> float:
    """The q-quantile of a cumulative histogram by linear interpolation within its bucket (Prometheus' rule).

    Returns NaN for an empty histogram, and the largest finite bound when the
    quantile falls in the +Inf bucket.
    """
    le = np.asarray(le, np.float64)
    cum = np.asarray(cumulative, np.float64)
    if cum.size == 0 or cum[-1] <= 0:
        return math.nan
    rank = q * cum[-1]
    i = int(np.searchsorted(cum, rank, side="left"))
    i = min(i, cum.size - 1)
    if math.isinf(le[i]):
        finite = le[np.isfinite(le)]
        return float(finite[-1]) if finite.size else math.nan
    lo = le[i - 1] if i > 0 else 0.0
    c_lo = cum[i - 1] if i > 0 else 0.0
    if cum[i] <= c_lo:
        return float(le[i])
    return float(lo + (le[i] - lo) * (rank - c_lo) / (cum[i] - c_lo))


def _hist_delta(a: Scrape | None, b: Scrape, name: str) -> tuple[np.ndarray, np.ndarray] | None:
    """The histogram's observations between two scrapes (b − a), or None when the server lacks it."""
    hb = b.hist.get(name)
    if hb is None:
        return None
    ha = a.hist.get(name) if a is not None else None
    if ha is None or ha[0].shape != hb[0].shape or not np.array_equal(ha[0], hb[0]):
        return hb
    return hb[0], np.maximum(hb[1] - ha[1], 0.0)


def _quantiles_ms(a: Scrape | None, b: Scrape, name: str) -> tuple[float | None, float | None, int]:
    h = _hist_delta(a, b, name)
    if h is None or h[1][-1] <= 0:
        return None, None, 0
    return (histogram_quantile(*h, 0.5) * 1e3, histogram_quantile(*h, 0.99) * 1e3, int(h[1][-1]))


def _proc_cpu(pid: int) -> float | None:
    """utime + stime of a local process (s): the fallback when /metrics has no process collector."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


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
class _Config:
    url: str
    http: str
    scene: str
    rate: float
    target: float
    algorithms: tuple[str, ...]
    model: RendererModel
    seed: int
    timeout: float = 10.0


class _Client:
    """One simulated session: a sender paced at ``rate`` Hz and a receiver answering pings and acking deltas."""

    def __init__(self, index: int, n: int, cfg: _Config) -> None:
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
        from client.navigation import Tour

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
            await ws.send(packb(camera))
            await ws.send(packb(report))
            self.frame_at.append(loop.time())
            self.frame_time.append(ft)
            self.frames += 1
            k += 1


# --------------------------------------------------------------------------- a phase: N clients for S seconds


class _Totals:
    """What the clients of a phase did so far, summed (for the live table and the window's start and end)."""

    def __init__(self, clients: list[_Client]) -> None:
        self.clients = clients
        self.notes: list[str] = []

    def note(self, text: str) -> None:
        if len(self.notes) < 20:
            self.notes.append(text)

    def snapshot(self) -> dict:
        errors: Counter[str] = Counter()
        for c in self.clients:
            errors.update(c.errors)
        return {
            "connected": sum(c.connected for c in self.clients),
            "opened": sum(c.opened for c in self.clients),
            "deltas": sum(c.deltas for c in self.clients),
            "bytes": sum(c.bytes for c in self.clients),
            "errors": errors,
            "cpu": time.process_time(),  # this process: the load generator's own cost
        }


@dataclass
class PhaseResult:
    """One measured run of ``clients`` simulated sessions; figures over the window after the ramp.

    Latencies are the server's ``walkstream_selection_seconds`` histogram over
    the window (None when it saw no selection); ``errors`` are the clients'
    (error frames by code, and connect_failed / connection_lost / no_welcome);
    ``mirror_*`` come from the server's ``/sessions`` just before the clients
    left (None when it would not say).
    """

    clients: int
    sessions_opened: int
    connected_at_end: int
    window_s: float
    deltas: int
    selections_per_s: float
    selections_due_share: float | None
    selection_p50_ms: float | None
    selection_p99_ms: float | None
    selections_measured: int
    selection_cpu_p50_ms: float | None
    selection_cpu_p99_ms: float | None
    delta_interarrival_p99_ms: float | None
    bytes_per_s: float
    server_bytes_out_per_s: float | None
    server_cpu_s: float | None
    server_cpu_per_session_s: float | None
    sessions_per_core: float | None
    errors: dict[str, int]
    server_errors: dict[str, int]
    frame_p95_ms: float | None
    frame_target_ms: float
    frame_p95_over_target: float | None
    clients_with_deltas: int
    min_deltas_per_client: int
    acks: int
    pongs: int
    generator_cpu_per_session_s: float | None = None
    frames_skipped: int = 0
    mirror_checks: int | None = None
    mirror_mismatch: int | None = None
    resyncs: int | None = None
    notes: list[str] = field(default_factory=list)


@dataclass
class LoadSummary(PhaseResult):
    """The load test's result: the N-client phase's figures, its setting, and the one-client reference."""

    scene: str = ""
    url: str = ""
    tau: float | None = None
    rate: float = 0.0
    duration_s: float = 0.0
    ramp_s: float = 0.0
    server_pid: int | None = None
    reference: PhaseResult | None = None
    cpu_per_session_ratio: float | None = None
    p99_ratio: float | None = None
    goal_sessions_per_core: float = GOAL_SESSIONS_PER_CORE
    goal_p99_ms: float = GOAL_P99_MS
    goal_met: bool = False

    def as_dict(self) -> dict:
        return asdict(self)


class _Monitor:
    """Scrapes /metrics every second and keeps the live table's figures; the window's ends are scrapes too."""

    def __init__(self, http, base: str, pid: int | None, headers: dict | None) -> None:
        self.http, self.base, self.pid, self.headers = http, base, pid, headers
        self.first: Scrape | None = None
        self.last: Scrape | None = None

    async def scrape(self) -> Scrape:
        import httpx

        loop = asyncio.get_running_loop()
        try:
            r = await self.http.get(f"{self.base}/metrics")
        except httpx.HTTPError as exc:
            raise LoadtestError(f"lost the server's /metrics ({self.base}/metrics): "
                                f"{type(exc).__name__}: {exc}") from None
        if r.status_code == 404:
            raise LoadtestError(f"the server has no /metrics ({self.base}/metrics: 404)")
        if r.status_code != 200:
            raise LoadtestError(f"the server's /metrics answered {r.status_code}")
        s = parse_metrics(r.text, loop.time())
        if "process_cpu_seconds_total" not in s.values and self.pid is not None:
            cpu = _proc_cpu(self.pid)
            if cpu is not None:
                s.values["process_cpu_seconds_total"] = cpu
        if self.first is None:
            self.first = s
        self.last = s
        return s

    async def sessions(self, ids: set[str]) -> dict | None:
        """Mirror checks of our sessions from ``/sessions`` (None when it refuses or lacks them)."""
        try:
            r = await self.http.get(f"{self.base}/sessions", headers=self.headers or {})
        except Exception:
            return None
        if r.status_code != 200:
            return None
        body = r.json()
        rows = body.get("sessions", []) if isinstance(body, dict) else body
        ours = [s for s in rows if isinstance(s, dict) and s.get("session") in ids]
        if not ours or any("mirror_mismatch" not in s for s in ours):
            return None
        return {k: int(sum(int(s.get(k, 0)) for s in ours)) for k in ("mirror_checks", "mirror_mismatch", "resyncs")}


class _Display:
    """The live table (rich.live on stderr), refreshed twice a second."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self.live = None
        self.rows: dict[str, str] = {}

    def __enter__(self) -> "_Display":
        if self.enabled:
            from rich.console import Console
            from rich.live import Live

            self.live = Live(self._table(), console=Console(stderr=True), auto_refresh=False, transient=False)
            self.live.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        if self.live is not None:
            self.live.update(self._table(), refresh=True)
            self.live.__exit__(*exc)

    def _table(self):
        from rich.table import Table

        table = Table(title="walkstream loadtest", show_header=False, min_width=48)
        for k, v in self.rows.items():
            table.add_row(k, v)
        return table

    def update(self, rows: dict[str, str]) -> None:
        self.rows = rows
        if self.live is not None:
            self.live.update(self._table(), refresh=True)


def _fmt(x: float | None, spec: str = ".1f") -> str:
    return "—" if x is None or not math.isfinite(x) else format(x, spec)


async def _phase(cfg: _Config, name: str, n: int, duration: float, ramp: float, *, monitor_args, display: _Display,
                 ) -> PhaseResult:
    import httpx

    loop = asyncio.get_running_loop()
    clients = [_Client(i, n, cfg) for i in range(n)]
    totals = _Totals(clients)
    stop = asyncio.Event()
    settle = min(2.0, 0.4 * (duration - ramp))  # past the last clients' first, largest deltas
    async with httpx.AsyncClient(timeout=10.0) as http:
        monitor = _Monitor(http, *monitor_args)
        first = await monitor.scrape()
        t0 = loop.time()
        w0, w1 = t0 + ramp + settle, t0 + duration
        tasks = [asyncio.create_task(c.run(t0 + ramp * i / n, stop, totals)) for i, c in enumerate(clients)]
        window_start: tuple[Scrape, dict] | None = None
        prev = (t0, totals.snapshot())
        ticks = 0
        try:
            while (now := loop.time()) < w1:
                if window_start is None and now >= w0:
                    window_start = (await monitor.scrape(), totals.snapshot())
                elif ticks % 2 == 0:  # the table twice a second, the scrape once
                    await monitor.scrape()
                ticks += 1
                snap = totals.snapshot()
                dt = max(now - prev[0], 1e-3)
                p50, p99, _ = _quantiles_ms(first, monitor.last, "walkstream_selection_seconds")
                display.update({
                    "phase": f"{name}: {now - t0:5.1f} / {duration:g} s" + ("  (ramp)" if now < t0 + ramp else ""),
                    "clients connected": f"{snap['connected']} / {n}",
                    "deltas/s": f"{(snap['deltas'] - prev[1]['deltas']) / dt:.1f}",
                    "selection latency p50 / p99 (server)": f"{_fmt(p50)} / {_fmt(p99)} ms",
                    "MB/s received": f"{(snap['bytes'] - prev[1]['bytes']) / dt / 1e6:.2f}",
                    "errors": ", ".join(f"{k} {v}" for k, v in sorted(snap["errors"].items())) or "0",
                })
                prev = (now, snap)
                wake = min(now + 0.5, w1, w0 if window_start is None and w0 > now else math.inf)
                await asyncio.sleep(max(0.0, wake - loop.time()))
            end = await monitor.scrape()
            end_totals = totals.snapshot()
            mirror = await monitor.sessions({c.session for c in clients if c.connected})
        finally:
            stop.set()
            await asyncio.gather(*tasks, return_exceptions=True)
    if window_start is None:  # a window too short to reach: measure from the start
        window_start = (first, {"deltas": 0, "bytes": 0, "cpu": end_totals["cpu"]})
    return _result(cfg, clients, totals, first, window_start, end, end_totals, mirror, w0, w1)


def _result(cfg: _Config, clients: list[_Client], totals: _Totals, first: Scrape, window_start, end: Scrape,
            end_totals: dict, mirror: dict | None, w0: float, w1: float) -> PhaseResult:
    a, a_totals = window_start
    wall = max(end.at - a.at, 1e-6)
    n = len(clients)
    p50, p99, measured = _quantiles_ms(a, end, "walkstream_selection_seconds")
    h = _hist_delta(a, end, "walkstream_selection_seconds")
    if h is not None and h[1].size > 1 and h[1][-1] - h[1][-2] > 0.01 * h[1][-1]:
        totals.note(f"over 1 % of the selections took longer than the histogram's largest bucket "
                    f"({h[0][-2]:g} s): the p99 shown is a lower bound")
    cpu50, cpu99, _ = _quantiles_ms(a, end, "walkstream_selection_cpu_seconds")
    def within(at: list[float], values: np.ndarray) -> np.ndarray:
        at_ = np.asarray(at, np.float64)
        return values[(at_ >= w0) & (at_ <= w1)]

    gaps = [np.diff(within(c.arrivals, np.asarray(c.arrivals, np.float64))) for c in clients]
    gaps_all = np.concatenate(gaps) if gaps else np.zeros(0)
    frames = np.concatenate([within(c.frame_at, np.asarray(c.frame_time, np.float64)) for c in clients])
    cpu = None
    if "process_cpu_seconds_total" in end.values and "process_cpu_seconds_total" in a.values:
        cpu = end.values["process_cpu_seconds_total"] - a.values["process_cpu_seconds_total"]
    sessions = end_totals["connected"]
    tau = next((c.tau for c in clients if c.tau), None)
    deltas = end_totals["deltas"] - a_totals["deltas"]
    # Selections the sessions were owed (one per τ each): a server that falls behind delivers fewer, and its CPU
    # per session then understates what the load would cost it.
    share = deltas / (sessions * wall / tau) if tau and sessions else None
    if share is not None and share < 0.9:
        totals.note(f"the server delivered {share:.0%} of the selections due (one per τ = {tau:g} s per session): "
                    "it is saturated or starved by other processes, so sessions per core overstates its capacity")
    cpu_self = (end_totals["cpu"] - a_totals["cpu"]) / wall
    skipped = sum(c.skipped for c in clients)
    if skipped > 0.01 * max(1, sum(c.frames for c in clients)):
        totals.note(f"the load generator skipped {skipped} frames for falling behind while using {cpu_self:.0%} of "
                    "a core: " + ("it is the bottleneck" if cpu_self > 0.7 else "the machine is overloaded"))
    bout = None
    if "walkstream_bytes_out_total" in end.values:
        bout = (end.values["walkstream_bytes_out_total"] - a.values.get("walkstream_bytes_out_total", 0.0)) / wall
    server_errors = {k: int(v - first.errors.get(k, 0.0)) for k, v in end.errors.items()
                     if v - first.errors.get(k, 0.0) > 0}
    target_ms = cfg.target * 1e3
    frame_p95 = float(np.percentile(frames, 95)) * 1e3 if frames.size else None
    per_client = [c.deltas for c in clients]
    return PhaseResult(
        clients=n,
        sessions_opened=end_totals["opened"],
        connected_at_end=sessions,
        window_s=round(wall, 3),
        deltas=deltas,
        selections_per_s=deltas / wall,
        selections_due_share=share,
        selection_p50_ms=p50,
        selection_p99_ms=p99,
        selections_measured=measured,
        selection_cpu_p50_ms=cpu50,
        selection_cpu_p99_ms=cpu99,
        delta_interarrival_p99_ms=float(np.percentile(gaps_all, 99)) * 1e3 if gaps_all.size else None,
        bytes_per_s=(end_totals["bytes"] - a_totals["bytes"]) / wall,
        server_bytes_out_per_s=bout,
        server_cpu_s=cpu,
        server_cpu_per_session_s=cpu / (sessions * wall) if cpu is not None and sessions else None,
        sessions_per_core=sessions / (cpu / wall) if cpu and sessions else None,
        errors=dict(sorted(end_totals["errors"].items())),
        server_errors=server_errors,
        frame_p95_ms=frame_p95,
        frame_target_ms=target_ms,
        frame_p95_over_target=frame_p95 / target_ms if frame_p95 is not None else None,
        clients_with_deltas=sum(d > 0 for d in per_client),
        min_deltas_per_client=min(per_client) if per_client else 0,
        acks=sum(c.acks for c in clients),
        pongs=sum(c.pongs for c in clients),
        frames_skipped=skipped,
        generator_cpu_per_session_s=(end_totals["cpu"] - a_totals["cpu"]) / (sessions * wall) if sessions else None,
        mirror_checks=None if mirror is None else mirror["mirror_checks"],
        mirror_mismatch=None if mirror is None else mirror["mirror_mismatch"],
        resyncs=None if mirror is None else mirror["resyncs"],
        notes=list(totals.notes),
    )


# --------------------------------------------------------------------------- the whole test


def _http_base(url: str) -> str:
    if url.startswith("ws://"):
        base = "http://" + url[len("ws://"):]
    elif url.startswith("wss://"):
        base = "https://" + url[len("wss://"):]
    else:
        raise LoadtestError(f"expected a ws:// or wss:// URL, got {url!r}")
    base = base.split("?", 1)[0]
    if base.endswith("/ws"):
        base = base[: -len("/ws")]
    return base.rstrip("/")


def _preflight(base: str, scene: str | None, headers: dict | None) -> str:
    """Check /metrics is there and pick the scene; returns the scene's name."""
    import httpx

    try:
        r = httpx.get(f"{base}/metrics", timeout=10.0)
    except httpx.HTTPError as exc:
        raise LoadtestError(f"cannot reach the server at {base}: {exc}") from None
    if r.status_code == 404:
        raise LoadtestError(f"the server has no /metrics ({base}/metrics: 404); walkstream loadtest reads the "
                            "selection latency and the server's CPU time from it")
    if r.status_code != 200:
        raise LoadtestError(f"the server's /metrics answered {r.status_code}")
    try:
        names = [s["name"] for s in httpx.get(f"{base}/scenes", timeout=10.0, headers=headers or {}).json()]
    except Exception as exc:
        raise LoadtestError(f"cannot list the server's scenes ({base}/scenes): {exc}") from None
    if scene is None:
        if not names:
            raise LoadtestError("the server serves no scene")
        return names[0]
    if scene not in names:
        raise LoadtestError(f"the server does not serve scene {scene!r}; it serves {', '.join(names) or 'none'}")
    return scene


def _ratio(a: float | None, b: float | None) -> float | None:
    return a / b if a is not None and b else None


def run_loadtest(
    *,
    clients: int,
    duration: float,
    url: str | None = None,
    stores: Sequence[Path] | None = None,
    scene: str | None = None,
    tau: float = 0.5,
    rate: float = 10.0,
    target_ms: float = 50.0,
    algorithms: Sequence[str] = ("flat",),
    ramp: float | None = None,
    seed: int = 0,
    reference: float = 5.0,
    model: RendererModel | None = None,
    admin_headers: dict | None = None,
    live: bool = False,
    log: Callable[[str], None] | None = None,
) -> LoadSummary:
    """Run ``clients`` simulated sessions for ``duration`` seconds (the ramp included) and measure the server.

    Without ``url`` a server (``bench.demo.ServerProcess``) is started on
    ``stores`` (default: the Den Haag store) with ``--tau``; with it, that
    server is used (``tau`` is then whatever it runs with) and its ``/metrics``
    is read from the same host. ``ramp`` (default: a quarter of the duration,
    at most 10 s) spreads the connections; the figures are over the rest.
    ``reference`` seconds of one client are measured first (0: skip).
    Raises ``LoadtestError`` when the server cannot be used.
    """
    if clients < 1:
        raise ValueError(f"clients must be at least 1, got {clients}")
    if not 0 < rate <= 120:
        raise ValueError(f"rate must lie in (0, 120] Hz, got {rate}")
    if not 1 <= target_ms <= 2000:
        raise ValueError(f"target_ms must lie in [1, 2000], got {target_ms}")
    bad = [a for a in algorithms if a not in ALGORITHMS]
    if bad or not algorithms or len(set(algorithms)) != len(algorithms):
        raise ValueError(f"algorithms must be distinct names among {', '.join(ALGORITHMS)}, got {list(algorithms)}")
    ramp = min(10.0, 0.25 * duration) if ramp is None else float(ramp)
    if ramp < 0 or duration <= ramp:
        raise ValueError(f"duration ({duration} s) must exceed the ramp ({ramp} s)")
    if reference < 0:
        raise ValueError(f"reference must be non-negative, got {reference}")
    model = model or RendererModel()
    say = log or (lambda s: None)
    server = None
    try:
        pid = None
        if url is None:
            from bench.demo import ServerProcess

            if not stores:
                from bench.correspondence import cached_store

                stores = [cached_store(quiet=not live)]
            missing = [str(p) for p in stores if not Path(p).exists()]
            if missing:
                raise LoadtestError(f"no such store: {', '.join(missing)}")
            say(f"starting a server on {', '.join(map(str, stores))} (τ = {tau:g} s)")
            extra = ["--tau", str(tau)]
            if clients > 256:  # the server's default max_sessions: past it, it would refuse them (busy)
                extra += ["--max-sessions", str(clients)]
            server = ServerProcess(list(map(Path, stores)), extra=extra)
            url, pid = server.url, server.proc.pid
            admin_headers = admin_headers or getattr(server, "admin_headers", None)
        base = _http_base(url)
        scene = _preflight(base, scene, admin_headers)
        cfg = _Config(url=url, http=base, scene=scene, rate=float(rate), target=target_ms / 1e3,
                      algorithms=tuple(algorithms), model=model, seed=int(seed))
        monitor_args = (base, pid, admin_headers)

        async def main() -> tuple[PhaseResult | None, PhaseResult]:
            with _Display(live) as display:
                ref = None
                if reference > 0:
                    ref = await _phase(cfg, "reference, 1 client", 1, reference, 0.0, monitor_args=monitor_args,
                                       display=display)
                run = await _phase(cfg, f"{clients} clients", clients, duration, ramp, monitor_args=monitor_args,
                                   display=display)
            return ref, run

        say(f"scene {scene!r} at {url}: {clients} clients for {duration:g} s (ramp {ramp:g} s)"
            + (f" after a {reference:g} s one-client reference" if reference > 0 else ""))
        ref, run = asyncio.run(main())
        p99_ok = run.selection_p99_ms is not None and run.selection_p99_ms <= GOAL_P99_MS
        spc_ok = run.sessions_per_core is not None and run.sessions_per_core >= GOAL_SESSIONS_PER_CORE
        kept_up = run.selections_due_share is not None and run.selections_due_share >= 0.9
        return LoadSummary(
            **asdict(run),
            scene=scene, url=url, tau=tau if server is not None else None, rate=float(rate),
            duration_s=float(duration), ramp_s=ramp, server_pid=pid, reference=ref,
            cpu_per_session_ratio=_ratio(run.server_cpu_per_session_s, ref and ref.server_cpu_per_session_s),
            p99_ratio=_ratio(run.selection_p99_ms, ref and ref.selection_p99_ms),
            goal_met=bool(p99_ok and spc_ok and kept_up and not run.errors),
        )
    finally:
        if server is not None:
            server.close()


def _pct(x: float | None) -> float | None:
    return None if x is None else 100.0 * x


def format_summary(s: LoadSummary) -> list[str]:
    """The summary as lines for people."""
    lines = [
        f"walkstream loadtest: scene {s.scene!r}, {s.clients} clients, {s.duration_s:g} s (ramp {s.ramp_s:g} s, "
        f"measured {s.window_s:.1f} s), camera and frame reports at {s.rate:g} Hz",
        f"  sessions opened {s.sessions_opened} / {s.clients}, connected at the end {s.connected_at_end}",
        f"  selections {s.selections_per_s:.1f}/s ({_fmt(_pct(s.selections_due_share), '.0f')} % of those due); "
        f"latency p50 {_fmt(s.selection_p50_ms)} ms, p99 "
        f"{_fmt(s.selection_p99_ms)} ms (server, {s.selections_measured} selections; worker CPU p99 "
        f"{_fmt(s.selection_cpu_p99_ms)} ms); delta inter-arrival p99 {_fmt(s.delta_interarrival_p99_ms)} ms (client)",
        f"  received {s.bytes_per_s / 1e6:.3f} MB/s; server CPU {_fmt(s.server_cpu_per_session_s, '.4f')} s per "
        f"session-second → {_fmt(s.sessions_per_core)} sessions per server core",
        f"  load generator CPU {_fmt(s.generator_cpu_per_session_s, '.4f')} s per session-second, "
        f"{s.frames_skipped} frames skipped for falling behind",
        f"  modelled frame time p95 {_fmt(s.frame_p95_ms)} ms against {s.frame_target_ms:g} ms "
        f"({_fmt(s.frame_p95_over_target, '.2f')} × target)",
        f"  errors: {', '.join(f'{k} {v}' for k, v in s.errors.items()) or 'none'}"
        f" (server counted: {', '.join(f'{k} {v}' for k, v in s.server_errors.items()) or 'none'})",
    ]
    if s.mirror_checks is not None:
        lines.append(f"  client-cache mirror: {s.mirror_checks} checks, {s.mirror_mismatch} mismatches")
    if s.reference is not None:
        r = s.reference
        lines.append(
            f"  reference (1 client, same run): CPU {_fmt(r.server_cpu_per_session_s, '.4f')} s per session-second, "
            f"p99 {_fmt(r.selection_p99_ms)} ms → ratios at {s.clients}: CPU per session "
            f"{_fmt(s.cpu_per_session_ratio, '.2f')}, p99 {_fmt(s.p99_ratio, '.2f')}")
    lines.append(f"  goal (≥ {s.goal_sessions_per_core:g} sessions per core, p99 ≤ {s.goal_p99_ms:g} ms, "
                 "≥ 90 % of the selections due delivered, no errors): "
                 + ("met" if s.goal_met else "NOT met"))
    lines += [f"  note: {n}" for n in s.notes]
    return lines
