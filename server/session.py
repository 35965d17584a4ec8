"""One client's session as a sans-I/O state machine.

Theory of operation. A session starts in ``AWAIT_HELLO``. A valid ``hello``
naming a served scene and a known solver moves it to ``ACTIVE`` and is answered
with ``welcome`` and a ``ping``. From then on the client streams ``camera``
poses and ``frame_report`` measurements, answers pings with ``pong`` and acks
each delta; every report folds into the cost model (the feedback of Zach 2002,
4.2), every pose into the path predictor.

Time is the client's clock: pongs give its offset and the round trip, acks the
time a delta takes to arrive. Selections run Zach's three-stage pipeline
(2002, 3.4) on a grid of switch times s, s + τ, …: the selection for the
interval [s, s + τ) runs just early enough that its delta reaches the client
before its morph window [s − τ, s) opens (selection time + half a round trip +
bytes / bandwidth + a safety margin), with the camera predicted over the
interval and the conservative camera around it. The delta carries the
representations the client lacks (with their morph maps), the ones it may drop,
the selection and its morph schedule. The first delta, and the first after a
teleport, is a reset: it replaces what is drawn at once.

Nothing here touches a socket or reads a clock: the caller passes ``now`` and
sends what comes back (the style of the ``websockets`` and ``h11`` cores). A
bad message yields an ``error`` frame and changes nothing else.
"""

from __future__ import annotations

import dataclasses
import enum
import logging
import time
from dataclasses import dataclass
from typing import Mapping, Protocol

import numpy as np
from pydantic import BaseModel

from proto.codec import decode_client
from proto.errors import ProtocolError
from proto.messages import (
    PROTOCOL_VERSION,
    Ack,
    Camera,
    Delta,
    Error,
    FrameReport,
    Hello,
    Morphs,
    Ping,
    Pong,
    Pose,
    RepresentationAdd,
    TourKey,
    Welcome,
)

from .clock import ClockSync, Delivery
from .select import solvers
from .select.benefit import BenefitFactors, importance_table
from .select.camera import View
from .select.cost import CostModel
from .select.morph import MorphScheduler, mark, rep_parents
from .select.predict import Limits, Predictor, conservative_camera
from .select.selection import Interval, Memory, Scene, select
from .select.solvers.candidates import Limit

__all__ = ["Session", "SessionConfig", "SessionState", "SceneSource"]

log = logging.getLogger("walkstream.session")


class SceneSource(Protocol):
    """What a session needs of a scene store."""

    @property
    def index(self): ...

    def geometries(self, reps) -> list[bytes]: ...


class SessionState(enum.Enum):
    AWAIT_HELLO = "await_hello"
    ACTIVE = "active"
    CLOSED = "closed"


@dataclass(frozen=True)
class SessionConfig:
    """Per-server session settings.

    tau : seconds between selections (Zach's τ)
    margin_deg : extra field of view selected around the view, for the motion within τ
    cache_bytes : the client's cache budget the server's mirror keeps to
    c_vertex : the cost model's first guess, seconds per vertex
    alpha : weight of each measured frame in the cost model's running average
    select_limit : seconds a selection may take; an anytime solver returns its best so far then
    importance : Importance weight per semantic class name (F&S); unnamed classes weigh 1
    samples : predicted cameras sampled over the target interval (Zach uses three)
    conservative_weight : λ, the conservative camera's share of benefit (distrust of the prediction)
    predict_margin_deg : field of view added around each predicted camera
    ping_interval : seconds between clock pings
    safety : seconds a schedule is meant to arrive before its window opens, beyond the estimates
    clock_wait : seconds regular selections wait for the first pong (a client that never answers pings
        gets them after that, timed by a guess)
    factors : which F&S benefit factors the selection applies, and their weights (None: all, defaults)
    """

    tau: float = 0.5
    margin_deg: float = 20.0
    cache_bytes: int = 512 * 1024 * 1024
    c_vertex: float = 2.0e-7
    alpha: float = 0.2
    select_limit: float = 0.1
    importance: dict = dataclasses.field(default_factory=dict)
    samples: int = 3
    conservative_weight: float = 0.1
    predict_margin_deg: float = 0.0
    ping_interval: float = 1.0
    safety: float = 0.05
    clock_wait: float = 3.0
    factors: BenefitFactors | None = None


class Session:
    def __init__(self, scenes: Mapping[str, SceneSource], session_id: str, config: SessionConfig | None = None):
        self.scenes = scenes
        self.id = session_id
        self.config = config or SessionConfig()
        self.state = SessionState.AWAIT_HELLO
        self.hello: Hello | None = None
        self.scene_name = ""
        self.camera: Camera | None = None
        self.cost = CostModel(c_vertex=self.config.c_vertex, alpha=self.config.alpha)
        self.seq = 0
        self.next_selection: float | None = None
        # Counters for /sessions and the tests.
        self.frames = 0
        self.errors = 0
        self.bytes_sent = 0
        self.last_frame_time = 0.0
        self._memory = Memory()
        self.last_stats: dict = {}
        self.clock = ClockSync()
        self.delivery = Delivery()
        self.predictor: Predictor | None = None
        self._switch: float | None = None  # the last delta's switch time (client clock)
        self._planned = 0.0  # the next delta's switch time
        self._hello_at = 0.0
        self._reset = True  # the next delta replaces what is drawn (first, or after a teleport)
        self._next_ping: float | None = None
        self._ping_id = 0
        self._select_time = self.config.select_limit  # running estimate of a selection's wall time
        self._delta_bytes = 0.0  # running estimate of a (non-reset) delta's size
        self._starts: dict[int, tuple[float, bool]] = {}  # seq → (start, reset), for the late check
        self.late = 0
        self.teleports = 0
        self.acks = 0

    # ------------------------------------------------------------------ input

    def receive(self, data: bytes | str | BaseModel, now: float) -> list[BaseModel]:
        """Handle one frame (raw bytes, or an already decoded message) that arrived at server time ``now``;
        return the messages to send."""
        try:
            message = data if isinstance(data, BaseModel) else decode_client(data)
            if isinstance(message, Hello):
                return self._hello(message, now)
            if self.state is not SessionState.ACTIVE:
                raise ProtocolError("bad_state", f"'{message.type}' before 'hello'")
            if isinstance(message, Camera):
                self.camera = message
                self.clock.observe(message.t, now)
                if self.predictor is not None and self.predictor.add(message.t, message.eye, message.forward, message.up):
                    if self._switch is not None:  # a teleport: the pipeline restarts from here
                        self.teleports += 1
                        self._reset = True
                        self.next_selection = now
                if self.next_selection is None:
                    self.next_selection = now  # the first pose is answered at once
                return []
            if isinstance(message, Pong):
                if message.id <= self._ping_id:
                    self.clock.add(message.sent, message.t, now)
                return []
            if isinstance(message, Ack):
                return self._ack(message)
            if isinstance(message, FrameReport):
                self.frames += 1
                self.last_frame_time = message.time
                self._memory.frame_time = message.time
                self.cost.update(message.time, message.vertices)
                return []
            raise ProtocolError("unknown_type", f"'{message.type}' is not a client message")
        except ProtocolError as exc:
            self.errors += 1
            return [Error(code=exc.code, message=exc.message)]

    def _hello(self, hello: Hello, now: float) -> list[BaseModel]:
        if self.state is not SessionState.AWAIT_HELLO:
            raise ProtocolError("bad_state", "the session already said hello")
        if hello.protocol != PROTOCOL_VERSION:
            raise ProtocolError("version", f"protocol {hello.protocol} is not supported; this server speaks {PROTOCOL_VERSION}")
        if hello.scene not in self.scenes:
            known = ", ".join(sorted(self.scenes)) or "none"
            raise ProtocolError("unknown_scene", f"no scene {hello.scene!r}; served: {known}")
        if hello.solver not in solvers.SOLVERS:
            raise ProtocolError("unknown_solver", f"no solver {hello.solver!r}; known: {', '.join(sorted(solvers.SOLVERS))}")
        self.hello = hello
        self.scene_name = hello.scene
        index = self.scenes[hello.scene].index
        self._scene = Scene.of(index, importance_table(index.class_names, self.config.importance))
        self._memory = Memory()
        self._bounds = np.asarray(index.bounds, np.float64)
        m = index.n_representations
        self._rep_bytes = np.asarray(index.rep_bytes, np.int64)
        self._resident = np.zeros(m, dtype=bool)
        self._last_used = np.full(m, -1, dtype=np.int64)
        self._rep_level = np.asarray(index.rep_level, np.int64)
        self._rep_morph = np.asarray(index.rep_morph, bool)
        self._rep_parent = rep_parents(index.rep_level, index.rep_object, index.object_parent,
                                       index.rep_first, index.rep_count)
        self._drawn = np.zeros(0, np.int64)
        self._morph = MorphScheduler(self.config.tau, morph=hello.morph)
        self._ramp = MorphScheduler(self.config.tau, morph=hello.morph)
        if hello.predict:
            turn = None if hello.max_turn is None else float(np.radians(hello.max_turn))
            self.predictor = Predictor(Limits(speed=hello.max_speed, turn=turn))
        self.state = SessionState.ACTIVE
        self._next_ping = now + self.config.ping_interval
        self._hello_at = now
        return [
            Welcome(
                session=self.id,
                protocol=PROTOCOL_VERSION,
                scene=hello.scene,
                bounds=self._bounds.tolist(),
                start=Pose(**index.start),
                tau=self.config.tau,
                solver=hello.solver,
                tour=[TourKey(**key) for key in index.tour],
                predict=hello.predict,
                morph=hello.morph,
            ),
            self._ping(now),
        ]

    def _ping(self, now: float) -> Ping:
        self._ping_id += 1
        return Ping(id=self._ping_id, sent=now)

    def _ack(self, ack: Ack) -> list[BaseModel]:
        self.acks += 1
        took = self.delivery.acked(ack.seq, ack.t, self.clock)
        start = self._starts.pop(ack.seq, None)
        if start is not None and not start[1] and ack.t > start[0] + 1e-3:
            self.late += 1
            log.info("session %s: delta %d arrived %.3f s after its schedule started (took %s)",
                     self.id, ack.seq, ack.t - start[0], took)
        if ack.rejected:
            rejected = np.asarray(ack.rejected, np.int64)
            rejected = rejected[rejected < self._resident.size]
            self._resident[rejected] = False  # the mirror follows what the client really holds
        return []

    # ------------------------------------------------------------------ timer

    def lead(self) -> float:
        """Seconds from starting a selection to its delta's arrival, as the session expects it now."""
        return (self._select_time + self.delivery.estimate(self._delta_bytes, self.clock) + self.config.safety)

    def _window(self, switch: float) -> float:
        """When the schedule for ``switch`` takes over: one τ early with morphing (down-morphs), else at it."""
        return switch - self.config.tau if self._morph.morph else switch

    def _next_switch(self, client_now: float) -> float:
        """The first switch on the grid, after the last one, whose window a delta started now reaches in time."""
        tau = self.config.tau
        switch = self._switch + tau
        earliest = client_now + self.lead()
        behind = earliest - self._window(switch)
        if behind > 1e-6:  # a poll at its deadline lands on the boundary: rounding is not lateness
            switch += np.ceil(behind / tau - 1e-6) * tau
        return float(switch)

    def next_deadline(self) -> float | None:
        """When ``poll`` next has work (server clock), or None while waiting for the client."""
        if self.state is not SessionState.ACTIVE:
            return None
        due = [d for d in (self._next_ping, self._selection_due()) if d is not None]
        return min(due) if due else None

    def _selection_due(self) -> float | None:
        if self.camera is None or self.next_selection is None:
            return None
        if self._reset or self._switch is None:
            return self.next_selection
        # As late as still arrives in time: the prediction is then as short as it can be.
        due = self.clock.server_time(self._window(self._planned) - self.lead())
        if not self.clock.known:  # the lead is a guess until the first pong: wait for it, a while
            due = max(due, self._hello_at + self.config.clock_wait)
        return due

    def poll(self, now: float) -> list[BaseModel]:
        """Send a ping and run the selection if they are due; return what to send."""
        if self.state is not SessionState.ACTIVE:
            return []
        out: list[BaseModel] = []
        if self._next_ping is not None and now >= self._next_ping:
            out.append(self._ping(now))
            self._next_ping = now + self.config.ping_interval
        due = self._selection_due()
        if due is not None and now >= due:
            out.append(self._select(now))
        return out

    def _interval(self, client_now: float, t0: float, t1: float):
        """The cameras for [t0, t1): predicted samples and the conservative camera, or the last pose."""
        hello, camera = self.hello, self.camera
        vp = tuple(hello.viewport)
        if self.predictor is None or self.predictor.latest is None:
            return View.of_pose(camera.eye, camera.forward, camera.up, hello.fov_y, vp, self._bounds), self.config.margin_deg
        k = max(1, self.config.samples)
        samples = self.predictor.samples(t0, t1, k)
        views = tuple(View.of_pose(p.eye, p.forward, p.up, hello.fov_y, vp, self._bounds) for _, p in samples)
        # Zach's conservative camera covers every view reachable by the end of the interval.
        horizon = max(t1 - client_now, 1e-3)
        now_pose = self.predictor.pose(max(client_now, self.predictor.latest))
        stages = 3 if self._morph.morph else 2
        pose, fov = conservative_camera(now_pose, hello.fov_y, vp[0] / vp[1], horizon / stages,
                                        self.predictor.theta, self.predictor.omega, stages=stages)
        conservative = View.of_pose(pose.eye, pose.forward, pose.up, fov, vp, self._bounds)
        interval = Interval(views, conservative, self.config.conservative_weight, tuple(t for t, _ in samples))
        return interval, self.config.predict_margin_deg

    def _select(self, now: float) -> Delta:
        hello, camera = self.hello, self.camera
        assert hello is not None and camera is not None
        tau = self.config.tau
        c_now = self.clock.client_time(now)
        reset = self._reset or self._switch is None
        if reset:
            # Drawn from its arrival: select for the stretch until the pipeline's first regular switch.
            start = switch = c_now
            t0, t1 = c_now + self.lead(), c_now + 2 * tau
        else:
            switch = self._next_switch(c_now)
            start = self._window(switch)
            t0, t1 = switch, switch + tau
        view, margin = self._interval(c_now, t0, t1)
        budget = hello.target_frame_time
        # The only clock the selection sees: an anytime solver stops at select_limit with its best so far.
        began = time.perf_counter()
        limit = Limit(time.perf_counter, began + self.config.select_limit)
        choice = select(self._scene, view, self.cost, budget, hello.solver, margin,
                        memory=self._memory, t=t0, limit=limit, factors=self.config.factors)
        self.last_stats = dict(choice.stats)
        self.seq += 1
        reps = choice.reps
        level = self._rep_level[reps]
        key = reps - level
        kind, _ = mark(self._rep_parent, self._drawn, reps)
        tr = self._morph.schedule(key, level.astype(np.float64), start, switch, reset=reset, kind=kind)
        self._drawn = reps
        needed = _expand(tr.needed_key, tr.needed_lo, tr.needed_hi)
        new = needed[~self._resident[needed]]
        self._resident[new] = True
        self._last_used[needed] = self.seq
        drop = self._evict(keep=needed)
        store = self.scenes[self.scene_name]
        blobs = store.geometries(new.tolist()) if new.size else []
        morph_maps = [None] * new.size
        if self._morph.morph and new.size:
            with_map = new[self._rep_morph[new]]
            maps = dict(zip(with_map.tolist(), store.morphs(with_map.tolist()))) if with_map.size else {}
            morph_maps = [maps.get(r) for r in new.tolist()]
        index = store.index
        add = [
            RepresentationAdd(rep=int(r), object=int(index.rep_object[r]), level=int(index.rep_level[r]),
                              geometry=blob, morph=mm)
            for r, blob, mm in zip(new.tolist(), blobs, morph_maps)
        ]
        nbytes = sum(len(b) for b in blobs) + sum(len(m) for m in morph_maps if m)
        self.bytes_sent += nbytes
        morphs = Morphs(
            rep=(tr.key + tr.level_to.astype(np.int64)).tolist(), level_from=tr.level_from.tolist(),
            level_to=tr.level_to.tolist(), t0=tr.t0.tolist(), t1=tr.t1.tolist(),
        )
        vegetation, resolution, ramps = [], [], Morphs()
        if choice.x is not None and choice.x_reps is not None:
            rt = self._ramp.schedule(choice.x_reps, choice.x, start, switch, reset=reset)
            vegetation, resolution = choice.x_reps.tolist(), np.clip(choice.x, 0.0, 1.0).tolist()
            ramps = Morphs(rep=rt.key.tolist(), level_from=np.clip(rt.level_from, 0, 1).tolist(),
                           level_to=np.clip(rt.level_to, 0, 1).tolist(), t0=rt.t0.tolist(), t1=rt.t1.tolist())
        # Keep the timing estimates: this selection's wall time, and (for regular deltas) the size.
        took = time.perf_counter() - began
        self._select_time = max(took, 0.7 * self._select_time + 0.3 * took)
        if not reset:
            self._delta_bytes = 0.7 * self._delta_bytes + 0.3 * nbytes if self._delta_bytes else float(nbytes)
        self.delivery.sent(self.seq, now, nbytes, took)
        self._starts[self.seq] = (start, reset)
        if len(self._starts) > 64:
            self._starts.pop(min(self._starts))
        self._switch, self._reset = switch, False
        self._planned = self._next_switch(c_now)
        self.next_selection = now
        self.last_stats.update(tr.stats, late=self.late, lead=self.lead())
        return Delta(
            seq=self.seq,
            t0=float(switch),
            t1=float(switch + tau),
            start=float(start),
            reset=reset,
            add=add,
            drop=drop.tolist(),
            selection=reps.tolist(),
            budget=budget,
            predicted_cost=choice.cost,
            cost_coeff=self.cost.c_vertex,
            morphs=morphs,
            vegetation=vegetation,
            resolution=resolution,
            ramps=ramps,
        )

    def _evict(self, keep: np.ndarray) -> np.ndarray:
        """Drop least recently selected representations until the client's cache fits its budget."""
        held = self._resident.copy()
        total = int(self._rep_bytes[held].sum())
        if total <= self.config.cache_bytes:
            return np.zeros(0, np.int64)
        held[keep] = False
        candidates = np.nonzero(held)[0]
        candidates = candidates[np.argsort(self._last_used[candidates], kind="stable")]
        freed = np.cumsum(self._rep_bytes[candidates])
        n = min(int(np.searchsorted(freed, total - self.config.cache_bytes)) + 1, candidates.size)
        drop = candidates[:n]
        self._resident[drop] = False
        return drop

    # ------------------------------------------------------------------ state

    def close(self) -> None:
        self.state = SessionState.CLOSED

    @property
    def stats(self) -> dict:
        return {
            "session": self.id,
            "state": self.state.value,
            "scene": self.scene_name,
            "solver": self.hello.solver if self.hello else "",
            "frames": self.frames,
            "selections": self.seq,
            "errors": self.errors,
            "cost_coeff": self.cost.c_vertex,
            "cost_updates": self.cost.updates,
            "last_frame_time": self.last_frame_time,
            "solver_stopped": self.last_stats.get("stopped", ""),
            "bytes_sent": self.bytes_sent,
            "resident": int(self._resident.sum()) if self.state is not SessionState.AWAIT_HELLO else 0,
            "predict": bool(self.hello.predict) if self.hello else False,
            "morph": bool(self.hello.morph) if self.hello else False,
            "rtt": self.clock.rtt,
            "clock_offset": self.clock.offset,
            "lead": self.lead(),
            "acks": self.acks,
            "late": self.late,
            "teleports": self.teleports,
            "morphs": {k: self.last_stats.get(k, 0) for k in ("up", "down", "collapsed", "switches")},
        }


def _expand(key: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Representation ids key + l for every whole level l in [floor(lo), ceil(hi)], per row."""
    if key.size == 0:
        return np.zeros(0, np.int64)
    first = np.floor(lo + 1e-9).astype(np.int64)
    count = np.ceil(hi - 1e-9).astype(np.int64) - first + 1
    count = np.maximum(count, 1)
    base = np.repeat(key + first, count)
    step = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
    return np.unique(base + step)
