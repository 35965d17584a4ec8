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
import secrets
import time
import zlib
from dataclasses import dataclass
from typing import Mapping, Protocol

import numpy as np
from pydantic import BaseModel

from proto.codec import decode_client
from proto.errors import ProtocolError
from proto.manifest import digest, mix, unpack_held
from proto.messages import (
    ALGORITHMS,
    PROTOCOL_VERSION,
    Ack,
    Camera,
    Delta,
    Error,
    FrameReport,
    Hello,
    ModelAdd,
    Morphs,
    Ping,
    Pong,
    Pose,
    RepresentationAdd,
    TourKey,
    Welcome,
)

from . import state as _snap
from .clock import ClockSync, Delivery
from .select import solvers
from .select.benefit import BenefitFactors, importance_table
from .select.camera import View
from .select.cost import CostModel
from .select.cost_online import OnlineCostModel
from .select.morph import MorphScheduler, mark, rep_parents
from .select.predict import Limits, Predictor, conservative_camera, tour_speed
from .select.selection import Interval, Memory, Scene, select
from .select.solvers.candidates import Limit
from .stream import gain, gate, realise_bytes, resident_fallback

__all__ = ["Session", "SessionConfig", "SessionState", "SceneSource"]

log = logging.getLogger("walkstream.session")

#: Frames under this share of the target frame time (measured and predicted) are left out of the budget's tail
#: ratio and move only the cost model's fixed overhead, not its per-unit prices (``OnlineCostModel.tail_min_time``).
TAIL_MIN_SHARE = 0.25


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
    cache_bytes : the most payload a client's cache holds, as the mirror keeps it (a hello may ask for less)
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
    observe_hz : at most this many frame reports a second are folded into the cost model (evenly in client time)
    budget_quantile : the share of frames that should meet the target — the budget is divided by the cost model's
        recent measured ÷ predicted ratio at this quantile (0: budget the mean frame, as F&S and Zach do)
    bandwidth : the link's first guess, bytes/s, until acks of large deltas measure it
    link_share : share of the measured bandwidth × τ one delta's new representations may take (the rest is
        headroom for morph intermediates, pings and estimation error); what is still in flight counts against it
    cost_model : "online" — F&S's coefficients fitted to the frame reports by robust recursive least
        squares, the simplest adequate model chosen (``select.cost_online``); "zach" — the running
        c_vertex average alone (Zach 2002, 4.2), for comparison
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
    cost_model: str = "online"
    link_share: float = 0.8
    budget_quantile: float = 0.95
    observe_hz: float = 20.0
    bandwidth: float = 10.0e6

    def __post_init__(self) -> None:
        if not self.observe_hz > 0:
            raise ValueError(f"observe_hz must be positive, got {self.observe_hz}")
        if self.cost_model not in ("online", "zach"):
            raise ValueError(f"cost_model must be 'online' or 'zach', got {self.cost_model!r}")


class Session:
    def __init__(self, scenes: Mapping[str, SceneSource], session_id: str, config: SessionConfig | None = None,
                 token: str | None = None):
        self.scenes = scenes
        self.id = session_id
        # The secret a resume must present with ``id`` (proto Resume.token); a resumed session keeps its own.
        self.token = token or secrets.token_urlsafe(24)
        if not _snap.TOKEN.fullmatch(self.token):
            raise ValueError("a session token is 16–128 characters of [A-Za-z0-9_-]")
        self.config = config or SessionConfig()
        self.state = SessionState.AWAIT_HELLO
        self.hello: Hello | None = None
        self.scene_name = ""
        self.camera: Camera | None = None
        if self.config.cost_model == "zach":
            self.cost = CostModel(c_vertex=self.config.c_vertex, alpha=self.config.alpha)
        else:
            self.cost = OnlineCostModel(algorithms=len(ALGORITHMS), c_vertex=self.config.c_vertex)
        self._algorithms: tuple = (0,)
        self._pixel_scale = 1.0  # covered pixels per pixel of box screen area, measured
        self._pixels_predicted: dict[int, float] = {}  # seq → box pixels its selection was priced with
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
        self.delivery = Delivery(bandwidth=self.config.bandwidth)
        self.predictor: Predictor | None = None
        self._switch: float | None = None  # the last delta's switch time (client clock)
        self._planned = 0.0  # the next delta's switch time
        self._hello_at = 0.0
        self._reset = True  # the next delta replaces what is drawn (first, or after a teleport)
        self._next_ping: float | None = None
        self._ping_id = 0
        self._pings: dict[int, float] = {}  # id → stamp of each ping not yet answered
        self.fence: str | None = None  # the token this session was resumed from (``StateStore.save``)
        self._observe_due = -np.inf  # client time from which the next frame report is folded into the cost model
        self._select_time = self.config.select_limit  # running estimate of a selection's wall time
        self._delta_bytes = 0.0  # running estimate of a (non-reset) delta's size
        self._starts: dict[int, tuple[float, bool]] = {}  # seq → (start, reset), for the late check
        self.late = 0
        self.teleports = 0
        self.acks = 0
        # The client-cache mirror's counters (see ``_mirror_ack``).
        self.cache_budget = self.config.cache_bytes
        self.evicted = 0  # reps the mirror dropped to keep within the budget
        self.over_budget = 0  # needed reps left unsent for want of budget, summed over deltas
        self.refused = 0  # reps the client refused (acks' ``rejected``)
        self.mirror_checks = 0  # acks whose held/held_bytes/digest were compared with the mirror
        self.mirror_mismatch = 0  # ... and did not match (each triggers a resync)
        self.resyncs = 0  # deltas that dropped everything and restarted the mirror empty
        # The streaming gate's counters (``_gate``): choices that waited for bytes, drawn coarser or not at all.
        self.deferred = 0
        self.fallbacks = 0
        self.last_gate: dict = {}
        self._morph_share = 0.1  # morph-map bytes per geometry byte sent, learned from the adds
        self._held = [0, 0, 0]  # the mirror's count, bytes and digest (set up by the hello)
        self._restored: dict | None = None  # a snapshot ``restore`` took in, that the hello applies or discards
        self._saved: tuple | None = None  # ``_progress()`` at the last snapshot (see ``dirty``)

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
                # Only the stamp we sent under that id counts: a forged one would skew the clock (fuzzing found
                # a pong claiming a ping from 1e308 s ago pushing every schedule past the end of time).
                if self._pings.pop(message.id, None) == message.sent:
                    self.clock.add(message.sent, message.t, now)
                return []
            if isinstance(message, Ack):
                return self._ack(message)
            if isinstance(message, FrameReport):
                self.frames += 1
                self.last_frame_time = message.time
                self._memory.frame_time = message.time
                # The fit costs ~0.5 ms a frame; consecutive frames of a 60 Hz client say nearly the same thing.
                # Fold in an even sample of them in time (≤ observe_hz per second): unbiased, and a 60 fps
                # client no longer costs the server 30 ms a second for its cost model alone.
                period = 1.0 / self.config.observe_hz
                if message.t >= self._observe_due - 1e-6 or message.t < self._observe_due - 2 * period:
                    # On a grid of the period (not "a period after the last"): the average rate is observe_hz
                    # whatever the client's frame rate; a client clock that went back restarts the grid.
                    self._observe_due = max(self._observe_due, message.t - period) + period
                    self._observe(message)
                return []
            raise ProtocolError("unknown_type", f"'{message.type}' is not a client message")
        except ProtocolError as exc:
            self.errors += 1
            return [Error(code=exc.code, message=exc.message)]

    def _observe(self, report: FrameReport) -> None:
        """Fold one measured frame into the cost model, and the covered pixels into the fill estimate."""
        terms = report.terms
        if terms is None or not hasattr(self.cost, "observe"):
            self.cost.update(report.time, report.vertices)
        else:
            r = len(ALGORITHMS)

            def col(values: list[int]) -> np.ndarray:
                out = np.zeros(r)
                out[: len(values)] = values
                return out

            self.cost.observe(report.time, col(terms.triangles), col(terms.vertices), col(terms.pixels),
                              col(terms.draws), report.splats)
        predicted = self._pixels_predicted.get(report.selection, 0.0)
        if report.pixels > 0 and predicted > 0:
            # Boxes overstate what a mesh covers (and depth-tested overdraw understates nothing): learn the ratio.
            ratio = float(np.clip(report.pixels / predicted, 0.02, 4.0))
            self._pixel_scale += 0.1 * (ratio - self._pixel_scale)

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
        n_reps = self.scenes[hello.scene].index.n_representations
        held = None if hello.held is None else unpack_held(hello.held, n_reps)  # bad_held: nothing changed yet
        resumed = self._resumes(hello)
        self.hello = hello
        self.scene_name = hello.scene
        if hasattr(self.cost, "tail_min_time"):
            # The budget's tail is that of frames the budget is about: a 5 ms frame 60 % over its prediction
            # (an empty view's overhead) says nothing of how a 50 ms one strays.
            self.cost.tail_min_time = TAIL_MIN_SHARE * hello.target_frame_time
        self._algorithms = tuple(ALGORITHMS.index(a) for a in hello.algorithms)
        index = self.scenes[hello.scene].index
        self._scene = Scene.of(index, importance_table(index.class_names, self.config.importance))
        self._memory = Memory()
        self._bounds = np.asarray(index.bounds, np.float64)
        m = index.n_representations
        self._rep_bytes = np.asarray(index.rep_bytes, np.int64)
        # The client-cache mirror: what the client holds, within the smaller of its budget and ours.
        self.cache_budget = int(self.config.cache_bytes if hello.cache_bytes is None
                                else min(hello.cache_bytes, self.config.cache_bytes))
        self._resident = np.zeros(m, dtype=bool)
        self._sent = np.zeros(m, dtype=bool)  # every rep sent this session: what a resync drops
        self._mix = mix(np.arange(m))  # each rep's digest term (proto.manifest), so updates are XORs
        self._held = [0, 0, 0]  # the mirror's count, bytes and digest, kept incrementally
        self._records: dict[int, _Sent] = {}  # seq → the mirror right after that delta, until acked
        self._epoch = 0  # acks of seqs before this predate the last resync
        self._acked = 0  # the last delta acked
        self._resync = False
        self._models_sent = False
        from .scene.index import TREES
        self._rep_trees = np.asarray(index.object_kind, np.int64)[np.asarray(index.rep_object, np.int64)] == TREES
        self._last_used = np.full(m, -1, dtype=np.int64)
        self._rep_level = np.asarray(index.rep_level, np.int64)
        self._rep_morph = np.asarray(index.rep_morph, bool)
        self._rep_parent = rep_parents(index.rep_level, index.rep_object, index.object_parent,
                                       index.rep_first, index.rep_count)
        self._rep_object = np.asarray(index.rep_object, np.int64)
        self._rep_first_of = np.asarray(index.rep_first, np.int64)[self._rep_object]
        self._rep_faces = np.asarray(index.rep_faces, np.int64)
        self._object_lo = np.asarray(index.object_lo, np.float64)
        self._object_hi = np.asarray(index.object_hi, np.float64)
        self._prev_rep = np.full(int(index.n_objects), -1, np.int64)  # the rep each object drew last delta
        self._obj_rank = None
        self._drawn = np.zeros(0, np.int64)
        self._morph = MorphScheduler(self.config.tau, morph=hello.morph)
        self._ramp = MorphScheduler(self.config.tau, morph=hello.morph)
        if hello.predict:
            turn = None if hello.max_turn is None else float(np.radians(hello.max_turn))
            # Without a stated speed limit, a jump is a teleport only if it outruns the scene's own tour by 3×.
            teleport = max(200.0, 3.0 * tour_speed(index.tour)) if hello.max_speed is None else 200.0
            self.predictor = Predictor(Limits(speed=hello.max_speed, turn=turn), teleport_speed=teleport)
        self._adopt(held, resumed)
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
                token=self.token,
                resumed=resumed,
                held=self._held[0],
            ),
            self._ping(now),
        ]

    def _ping(self, now: float) -> Ping:
        self._ping_id += 1
        self._pings[self._ping_id] = now
        if len(self._pings) > 16:  # pings never answered are forgotten
            self._pings.pop(min(self._pings))
        return Ping(id=self._ping_id, sent=now)

    def _ack(self, ack: Ack) -> list[BaseModel]:
        self.acks += 1
        took = self.delivery.acked(ack.seq, ack.t, self.clock)
        start = self._starts.pop(ack.seq, None)
        if start is not None and not start[1] and ack.t > start[0] + 1e-3:
            self.late += 1
            log.info("session %s: delta %d arrived %.3f s after its schedule started (took %s)",
                     self.id, ack.seq, ack.t - start[0], took)
        self._mirror_ack(ack)
        return []

    def _mirror_ack(self, ack: Ack) -> None:
        """Follow the client's refusals, then check the mirror against what the client says it holds.

        A refused add stays out of the mirror — now, and in the records of the
        deltas sent since (unless one of them dropped it), so later acks compare
        exactly. A mismatch means the two sides diverged beyond repair by
        bookkeeping: the next delta resyncs.
        """
        if not self._acked < ack.seq <= self.seq:
            return  # never sent, or a repeat (acks come in order): nothing to follow
        self._acked = ack.seq
        record = self._records.pop(ack.seq, None)
        if record is None:
            # From before the last resync: nothing to follow. A record lost to pruning (a client that left
            # hundreds of deltas unacked), though, may hide refusals: resync rather than trust the mirror.
            if ack.rejected and ack.seq >= self._epoch and not self._resync:
                log.warning("session %s: refusals in an ack of delta %d the mirror no longer tracks; resyncing",
                            self.id, ack.seq)
                self._begin_resync()
            return
        for seq in [s for s in self._records if s < ack.seq]:
            del self._records[seq]  # acks come in order: those will not come
        rejected = np.unique(np.asarray(ack.rejected, np.int64))
        alive = rejected[np.isin(rejected, record.add)]  # only this delta's adds can have been refused
        if alive.size:
            self.refused += int(alive.size)
            record.remove(alive, self._rep_bytes, self._mix)
            for seq in sorted(self._records):
                alive = alive[~np.isin(alive, self._records[seq].drop)]  # a later drop ended it anyway
                if not alive.size:
                    break
                self._records[seq].remove(alive, self._rep_bytes, self._mix)
            self._mark(alive, False)
        if ack.held < 0:
            return  # a client that does not report what it holds: nothing to check
        self.mirror_checks += 1
        if (ack.held, ack.held_bytes, ack.digest) != (record.held, record.bytes, record.digest):
            self.mirror_mismatch += 1
            log.warning("session %s: after delta %d the client holds %d reps, %d bytes (digest %016x); the mirror "
                        "says %d, %d (%016x); resyncing", self.id, ack.seq, ack.held, ack.held_bytes, ack.digest,
                        record.held, record.bytes, record.digest)
            self._begin_resync()

    def _begin_resync(self) -> None:
        """Make the next delta drop everything ever sent and restart the mirror; acks until then are stale."""
        self._resync = True
        self._records.clear()
        self._epoch = self.seq + 1

    def _mark(self, reps: np.ndarray, held: bool) -> None:
        """Set reps (each currently the opposite) held or not in the mirror, updating count, bytes and digest."""
        if reps.size == 0:
            return
        sign = 1 if held else -1
        self._resident[reps] = held
        self._held[0] += sign * int(reps.size)
        self._held[1] += sign * int(self._rep_bytes[reps].sum())
        self._held[2] ^= int(np.bitwise_xor.reduce(self._mix[reps]))

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
        # A poll wakes a little after its deadline (the event loop, a busy worker pool): lateness within the
        # safety margin the lead already holds still arrives in time. Counting it as late skipped every other
        # slot on a real server — one selection per 2τ.
        if behind > max(self.config.safety, 1e-6):
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
        # The fitted model's fixed per-frame cost (clear, finish) is spent whatever is drawn.
        # And the frame at the budget quantile, not the mean one, meets the target: the model's recent held-out
        # measured ÷ predicted ratio at that quantile shrinks what the selection may spend.
        tail = self.cost.tail_ratio(self.config.budget_quantile) if (
            self.config.budget_quantile > 0 and hasattr(self.cost, "tail_ratio")) else 1.0
        self._tail = tail
        budget = max(hello.target_frame_time / tail - getattr(self.cost, "overhead", 0.0),
                     0.25 * hello.target_frame_time)
        # The only clock the selection sees: an anytime solver stops at select_limit with its best so far.
        began = time.perf_counter()
        limit = Limit(time.perf_counter, began + self.config.select_limit)
        choice = select(self._scene, view, self.cost, budget, hello.solver, margin,
                        memory=self._memory, t=t0, limit=limit, factors=self.config.factors,
                        algorithms=self._algorithms, pixel_scale=self._pixel_scale)
        self.last_stats = dict(choice.stats)
        self._pixels_predicted[self.seq + 1] = choice.pixels
        if len(self._pixels_predicted) > 64:
            self._pixels_predicted.pop(min(self._pixels_predicted))
        self.seq += 1
        reps, algorithm = self._gate(choice.reps, choice.algorithm, view, now)
        level = self._rep_level[reps]
        key = reps - level
        kind, _ = mark(self._rep_parent, self._drawn, reps)
        tr = self._morph.schedule(key, level.astype(np.float64), start, switch, reset=reset, kind=kind)
        self._drawn = reps
        self._prev_rep[:] = -1
        self._prev_rep[self._rep_object[reps]] = reps
        needed = _expand(tr.needed_key, tr.needed_lo, tr.needed_hi)
        vegetation, resolution, ramps = [], [], Morphs()
        drawn_groups = groups = np.zeros(0, np.int64)
        if choice.x is not None and choice.x_reps is not None:
            rt = self._ramp.schedule(choice.x_reps, choice.x, start, switch, reset=reset)
            vegetation, resolution = choice.x_reps.tolist(), np.clip(choice.x, 0.0, 1.0).tolist()
            ramps = Morphs(rep=rt.key.tolist(), level_from=np.clip(rt.level_from, 0, 1).tolist(),
                           level_to=np.clip(rt.level_to, 0, 1).tolist(), t0=rt.t0.tolist(), t1=rt.t1.tolist())
            # Tree groups drawn now, and those a ramp still draws from the window on, must be resident too.
            drawn_groups = np.asarray(choice.x_reps, np.int64)[np.asarray(choice.x) > 0]
            groups = np.union1d(drawn_groups, rt.needed_key[rt.needed_hi > 0]).astype(np.int64)
        new, drop = self._mirror(np.concatenate([reps, drawn_groups]), np.concatenate([needed, groups]))
        if new.size and self._obj_rank is not None:
            # Best benefit per byte first (a chain's intermediates with their target, coarse before fine).
            rank = self._obj_rank[self._rep_object[new]]
            new = new[np.lexsort((self._rep_level[new], rank))]
        add, models, nbytes = self._adds(new)
        self.bytes_sent += nbytes
        morphs = Morphs(
            rep=(tr.key + tr.level_to.astype(np.int64)).tolist(), level_from=tr.level_from.tolist(),
            level_to=tr.level_to.tolist(), t0=tr.t0.tolist(), t1=tr.t1.tolist(),
        )
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
            models=models,
            selection=reps.tolist(),
            algorithm=[] if algorithm is None else algorithm.tolist(),
            budget=budget,
            predicted_cost=choice.cost,
            cost_coeff=self.cost.c_vertex,
            compute=min(max(took, 0.0), 3600.0),
            morphs=morphs,
            vegetation=vegetation,
            resolution=resolution,
            ramps=ramps,
        )

    def _byte_budget(self, now: float) -> float:
        """Bytes this delta's new representations may take: bandwidth × τ × link_share, less what is in flight."""
        link = self.delivery.bandwidth * self.config.tau * self.config.link_share
        self._in_flight = self.delivery.in_flight(now, horizon=max(4 * self.config.tau, 1.0))
        left = max(link - self._in_flight, 0.0)
        self.last_gate["link"] = left
        return left / (1.0 + self._morph_share)  # the gate counts geometry; morph maps ride along

    def _gate(self, reps: np.ndarray, algorithm: np.ndarray | None, view, now: float):
        """The selection as the link allows it (``stream``).

        Each object whose choice needs bytes offers two increments over its best
        resident ancestor: a coarse stand-in (the next level up from what is held)
        and the full choice, merged into one where the full choice is the denser
        (F&S's concave hull). The gate sends the densest within the byte budget;
        an object whose choice does not go is drawn with what it got, or what it
        held, or not at all — never costlier than chosen.
        """
        self._obj_rank = None
        lacking = ~self._resident[reps]
        self.last_gate = {}
        budget = self._byte_budget(now)
        self.last_gate |= {"budget": budget, "bandwidth": self.delivery.bandwidth, "lacking": int(lacking.sum()),
                          "deferred": 0, "fallback": 0, "stand_in": 0, "bytes": 0}
        if not lacking.any():
            return reps, algorithm
        idx = np.nonzero(lacking)[0]
        r = reps[idx]
        k = r.size
        obj = self._rep_object[r]
        first = self._rep_first_of[r]
        previous = self._prev_rep[obj]
        fallback = resident_fallback(r, first, self._resident)
        coarse = np.where(fallback >= 0, fallback + 1, first)  # the next level up from what is held
        nb_full = realise_bytes(r, previous, first, self._rep_bytes, self._resident)
        nb_coarse = realise_bytes(coarse, previous, first, self._rep_bytes, self._resident)
        cam = view.views[0] if hasattr(view, "views") else view
        faces = self._rep_faces
        held_faces = np.where(fallback >= 0, faces[np.maximum(fallback, 0)], 0)
        lo, hi, clip = self._object_lo[obj], self._object_hi[obj], cam.matrix()
        g_full = gain(lo, hi, clip, cam.width, cam.height, faces[r], held_faces)
        g_coarse = gain(lo, hi, clip, cam.width, cam.height, faces[coarse], held_faces)
        # Two increments where the stand-in is a real step and the denser one; else the full choice alone.
        two = (coarse < r) & (g_coarse * np.maximum(nb_full, 1) >= (g_full - g_coarse) * np.maximum(nb_coarse, 1))
        n2 = int(two.sum())
        gains = np.concatenate([np.where(two, g_full - g_coarse, g_full), g_coarse[two]])
        sizes = np.concatenate([nb_full, nb_coarse[two]])
        requires = np.full(k + n2, -1, np.int64)
        requires[np.nonzero(two)[0]] = k + np.arange(n2)  # the full choice builds on its stand-in
        decision = gate(gains, sizes, budget, at_least_one=self._in_flight == 0, requires=requires)
        full_sent = decision.send[:k]
        coarse_sent = np.zeros(k, bool)
        coarse_sent[np.nonzero(two)[0]] = decision.send[k:]
        shown = np.where(full_sent, r, np.where(coarse_sent, coarse, fallback))
        # Send order, per object: by its first increment in the gate's density order.
        pos = np.empty(k + n2, np.int64)
        pos[decision.order] = np.arange(k + n2)
        first_pos = pos[:k].copy()
        first_pos[np.nonzero(two)[0]] = pos[k:]
        rank = np.full(self._prev_rep.size, k + n2, np.int64)
        rank[obj] = first_pos
        self._obj_rank = rank
        out = reps.copy()
        out[idx] = shown
        keep = out >= 0
        held_back = ~full_sent
        self.deferred += int(held_back.sum())
        self.fallbacks += int((held_back & (shown >= 0)).sum())
        self.last_gate.update(deferred=int(held_back.sum()), fallback=int((held_back & (shown >= 0)).sum()),
                              stand_in=int(coarse_sent[held_back].sum()), bytes=decision.bytes)
        return out[keep], (None if algorithm is None else np.asarray(algorithm)[keep])

    def _mirror(self, selected: np.ndarray, needed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Bring the mirror to what this delta needs, within the budget; returns (reps to add, reps to drop).

        selected : reps the selection draws (meshes, drawn tree groups) — first in line when not all fits
        needed : every rep the schedule draws from its window on (ramp intermediates, morph sources, …)

        When what is needed alone exceeds the budget, it is sent in priority
        order (the selection before the rest, coarse before fine, small before
        large so the most objects show) as far as the budget allows and the rest
        counted in ``over_budget``: the client never receives more than it can
        keep, so it never has to refuse for room.
        """
        want = np.union1d(needed, selected).astype(np.int64)
        later = ~np.isin(want, selected)
        want = want[np.lexsort((self._rep_bytes[want], self._rep_level[want], later))]
        keep = want
        sizes = self._rep_bytes[want]
        if int(sizes.sum()) > self.cache_budget:
            keep = want[: int(np.searchsorted(np.cumsum(sizes), self.cache_budget, side="right"))]
        if self._resync:  # the client's holdings are unknown: forget them, send afresh what is kept
            self._mark(np.nonzero(self._resident)[0], False)
        new = keep[~self._resident[keep]]
        self._mark(new, True)
        self._sent[new] = True
        self._last_used[want] = self.seq
        drop = self._evict(keep)
        if self._resync:
            # Everything the client may hold but what this delta re-sends (an add and a drop of one rep
            # in one delta would leave it dropped).
            drop = np.nonzero(self._sent & ~self._resident)[0]
            self._resync, self._epoch = False, self.seq
            self.resyncs += 1
        self.over_budget += int((~self._resident[want]).sum())
        self._records[self.seq] = _Sent(*self._held, add=new, drop=drop)
        if len(self._records) > 256:  # a client that stopped acking must not grow this without bound
            self._records.pop(min(self._records))
        return new, drop

    def _evict(self, keep: np.ndarray) -> np.ndarray:
        """Drop least recently selected representations (never ``keep``) until the mirror fits the budget."""
        total = self._held[1]
        if total <= self.cache_budget:
            return np.zeros(0, np.int64)
        held = self._resident.copy()
        held[keep] = False
        candidates = np.nonzero(held)[0]
        candidates = candidates[np.argsort(self._last_used[candidates], kind="stable")]
        freed = np.cumsum(self._rep_bytes[candidates])
        n = min(int(np.searchsorted(freed, total - self.cache_budget)) + 1, candidates.size)
        drop = candidates[:n]
        self._mark(drop, False)
        self.evicted += int(drop.size)
        return drop

    def _adds(self, new: np.ndarray) -> tuple[list[RepresentationAdd], list[ModelAdd], int]:
        """The adds for ``new`` (meshes with their morph maps, tree groups' instance lists), the store's tree
        models with the session's first tree group, and the payload bytes of both."""
        store = self.scenes[self.scene_name]
        index = store.index
        blobs = store.geometries(new.tolist()) if new.size else []
        trees = self._rep_trees[new]
        morph_maps = [None] * new.size
        if self._morph.morph and new.size:
            with_map = new[self._rep_morph[new] & ~trees]
            maps = dict(zip(with_map.tolist(), store.morphs(with_map.tolist()))) if with_map.size else {}
            morph_maps = [maps.get(r) for r in new.tolist()]
        add = [
            RepresentationAdd(rep=int(r), object=int(index.rep_object[r]), level=int(index.rep_level[r]),
                              geometry=blob, morph=mm, kind="trees" if t else "mesh")
            for r, blob, mm, t in zip(new.tolist(), blobs, morph_maps, trees.tolist())
        ]
        models: list[ModelAdd] = []
        if trees.any() and not self._models_sent:  # the groups' instances name these: sent once, kept
            self._models_sent = True
            n = int(index.model_points.shape[0])
            models = [ModelAdd(model=i, points=b) for i, b in enumerate(store.model_geometries(range(n)))]
        geometry = sum(len(b) for b in blobs)
        maps = sum(len(m) for m in morph_maps if m)
        nbytes = geometry + maps + sum(len(m.points) for m in models)
        if geometry:  # what morph maps add to the geometry they come with, as this session sees it
            self._morph_share += 0.3 * (maps / geometry - self._morph_share)
        return add, models, nbytes

    # ------------------------------------------------------------------ state

    def close(self) -> None:
        self.state = SessionState.CLOSED

    def _cost_report(self) -> dict:
        """Why the online model is the one chosen, and its coefficients (issue 6: say which model and why)."""
        report = getattr(self.cost, "report", None)
        if report is None:
            return {}
        r = report()
        return {"cost_why": r["why"], "cost_coefficients": r["models"][r["chosen"]]["coefficients"]}

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
            "cost_model": getattr(self.cost, "chosen", "zach"),
            **self._cost_report(),
            "cost_overhead": float(getattr(self.cost, "overhead", 0.0)),
            "tail_ratio": getattr(self, "_tail", 1.0),
            "pixel_scale": self._pixel_scale,
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
            "cache_budget": self.cache_budget,
            "held_bytes": self._held[1],
            "evicted": self.evicted,
            "over_budget": self.over_budget,
            "refused": self.refused,
            "mirror_checks": self.mirror_checks,
            "mirror_mismatch": self.mirror_mismatch,
            "resyncs": self.resyncs,
            "bandwidth": self.delivery.bandwidth,
            "deferred": self.deferred,
            "fallbacks": self.fallbacks,
            "gate": dict(self.last_gate),
        }

    # ------------------------------------------------------------------ persistence (``server.state``)

    #: Session attributes a snapshot carries as they are: counters, estimates, the pipeline stage.
    _SAVED = ("seq", "frames", "errors", "bytes_sent", "last_frame_time", "late", "teleports", "acks", "evicted",
              "over_budget", "refused", "mirror_checks", "mirror_mismatch", "resyncs", "_pixel_scale", "_ping_id",
              "_select_time", "_delta_bytes", "_switch", "_planned")
    #: ... and those that may come and go with the streaming code (a snapshot without them still loads).
    _SAVED_OPTIONAL = ("deferred", "fallbacks")

    def _progress(self) -> tuple:
        """What moves when state worth saving changes: deltas, acks, frame reports, teleports, refusals."""
        return (self.seq, self.acks, self.frames, self.teleports, self.refused, self.resyncs)

    @property
    def dirty(self) -> bool:
        """True when the session has state worth saving that its last ``snapshot()`` does not hold."""
        return self.hello is not None and self._progress() != self._saved

    @dirty.setter
    def dirty(self, value: bool) -> None:
        self._saved = None if value else self._progress()

    def snapshot(self) -> bytes:
        """The session's state as msgpack (a few kB): enough for ``restore`` on any replica to resume it.

        Cost model, camera history, clock, counters and pipeline stage, and the
        client-cache mirror (bitsets; the last use of each held rep). Not the
        in-flight bookkeeping (unacked deltas): a resume restarts the pipeline.
        """
        if self.hello is None:
            raise RuntimeError(f"session {self.id} has said no hello yet: nothing to snapshot")
        resident = self._resident
        state = {
            "session": self.id,
            "scene": self.scene_name,
            "n_reps": int(resident.size),
            "hello": self.hello.model_dump(exclude={"held", "resume"}),
            "fields": _snap.save_attrs(self, self._SAVED),
            "optional": _snap.save_attrs(self, self._SAVED_OPTIONAL, optional=True),
            "cost": _snap.cost_state(self.cost),
            "predictor": None if self.predictor is None else _snap.predictor_state(self.predictor),
            "clock": _snap.save_attrs(self.clock, _snap.CLOCK, optional=True),
            "delivery": _snap.save_attrs(self.delivery, _snap.DELIVERY, optional=True),
            "mirror": {
                "resident": np.packbits(resident).tobytes(),
                "sent": np.packbits(self._sent).tobytes(),
                "used": zlib.compress(self._last_used[resident].astype("<i4").tobytes(), 1),  # runs of equal seqs
                "held": [int(x) for x in self._held],
                "models_sent": bool(self._models_sent),
                "resync": bool(self._resync),
            },
        }
        blob = _snap.pack_snapshot(state)
        self._saved = self._progress()
        return blob

    def restore(self, blob: bytes) -> None:
        """Take in a ``snapshot`` of this session, before its hello; ValueError (session unchanged) if the blob
        is bad, of another session, or of a scene this server does not serve as it was.

        Counters, seq, cost model and clock are set now; the hello applies the
        mirror and the camera history if it resumes (``hello.resume``), and
        otherwise starts afresh.
        """
        if self.state is not SessionState.AWAIT_HELLO or self.hello is not None:
            raise RuntimeError("restore comes before the hello")
        st = _snap.unpack_snapshot(blob)
        if st.get("session") != self.id:
            raise ValueError(f"the snapshot is of session {st.get('session')!r}, not {self.id!r}")
        scene = st.get("scene")
        if not isinstance(scene, str) or scene not in self.scenes:
            raise ValueError(f"the snapshot's scene {scene!r} is not served here")
        index = self.scenes[scene].index
        m = int(index.n_representations)
        if st.get("n_reps") != m:
            raise ValueError(f"the snapshot's scene {scene!r} had {st.get('n_reps')!r} representations; it has {m}")
        try:
            hello = Hello.model_validate(st.get("hello"))
        except Exception as exc:
            raise ValueError(f"the snapshot's hello is invalid: {exc}") from None
        if hello.scene != scene:
            raise ValueError("the snapshot's hello names another scene")
        # Decode everything into a scratch session first: a bad blob leaves this one as it was.
        scratch = Session(self.scenes, self.id, self.config, token=self.token)
        _snap.load_attrs(scratch, st.get("fields"), self._SAVED, "session", variable=())
        _snap.load_attrs(scratch, st.get("optional", {}), self._SAVED_OPTIONAL, "session", optional=True)
        _snap.load_cost(scratch.cost, st.get("cost"))
        _snap.load_attrs(scratch.clock, st.get("clock"), _snap.CLOCK, "clock", optional=True)
        _snap.load_attrs(scratch.delivery, st.get("delivery"), _snap.DELIVERY, "delivery", optional=True)
        predictor = st.get("predictor")
        if predictor is not None:
            _snap.load_predictor(Predictor(), predictor)  # checked now, loaded into the hello's predictor
        mirror = self._unpack_mirror(st.get("mirror"), index)
        for name in self._SAVED + self._SAVED_OPTIONAL:
            if hasattr(scratch, name):
                setattr(self, name, getattr(scratch, name))
        self.cost, self.clock, self.delivery = scratch.cost, scratch.clock, scratch.delivery
        self.scene_name = scene
        self._restored = {"scene": scene, "hello": hello, "predictor": predictor, "mirror": mirror}
        self._saved = None

    @staticmethod
    def _unpack_mirror(d, index) -> dict:
        """The snapshot's mirror as arrays, checked: bitsets of the scene's size, totals that add up."""
        if not isinstance(d, dict):
            raise ValueError("the snapshot has no mirror")
        m = int(index.n_representations)

        def bits(name: str) -> np.ndarray:
            b = d.get(name)
            if not isinstance(b, bytes) or len(b) != (m + 7) // 8:
                raise ValueError(f"mirror.{name}: expected a bitset of {m} representations")
            flags = np.unpackbits(np.frombuffer(b, np.uint8))
            if flags[m:].any():
                raise ValueError(f"mirror.{name}: bits beyond the scene's representations")
            return flags[:m].astype(bool)

        resident, sent = bits("resident"), bits("sent")
        ids = np.flatnonzero(resident)
        try:
            inflate = zlib.decompressobj()
            used = inflate.decompress(d.get("used"), 4 * ids.size + 1)
        except (TypeError, zlib.error):
            used = b""
        if len(used) != 4 * ids.size or not inflate.eof:
            raise ValueError("mirror.used: expected one last use per held representation")
        held = d.get("held")
        rep_bytes = np.asarray(index.rep_bytes, np.int64)
        if held != [int(ids.size), int(rep_bytes[ids].sum()), digest(ids)]:
            raise ValueError("mirror.held: the count, bytes and digest do not match the bitset")
        flags = (d.get("models_sent"), d.get("resync"))
        if not all(isinstance(f, bool) for f in flags):
            raise ValueError("mirror: models_sent and resync are booleans")
        return {"resident": resident, "sent": sent, "used": np.frombuffer(used, "<i4").astype(np.int64),
                "models_sent": flags[0], "resync": flags[1]}

    def _resumes(self, hello: Hello) -> bool:
        """Whether this hello continues the restored snapshot; if not, whatever ``restore`` took in is forgotten."""
        r = self._restored
        if r is None:
            return False
        resume = hello.resume
        # The token presented is the one the state was saved under: the fence, when the app rotated it.
        expected = self.fence or self.token
        if (resume is not None and resume.session == self.id and hello.scene == r["scene"]
                and secrets.compare_digest(resume.token, expected)):
            return True
        fence = self.fence
        Session.__init__(self, self.scenes, self.id, self.config, token=self.token)  # a fresh start after all
        self.fence = fence  # it still replaces the state it was loaded from
        return False

    def _adopt(self, held: np.ndarray | None, resumed: bool) -> None:
        """Set up the mirror from the hello's ``held`` (the client's word) or a resumed snapshot's, and restart
        the pipeline of a resumed session; called by the hello once the scene's arrays are in place."""
        if resumed:
            r, self._restored = self._restored, None
            mirror = r["mirror"]
            self._resident, self._sent = mirror["resident"], mirror["sent"]
            self._last_used[mirror["resident"]] = mirror["used"]
            self._models_sent, self._resync = mirror["models_sent"], mirror["resync"]
            if self.predictor is not None and r["predictor"] is not None:
                _snap.load_predictor(self.predictor, r["predictor"])  # the new hello's limits stay
            # The offsets were measured against the old replica's clock (another host's monotonic time): the
            # welcome's ping measures them afresh. Round trip and bandwidth (``delivery``) are the link's and stay.
            self.clock = ClockSync()
            # The pipeline restarts with a reset delta, as after a teleport; seq numbers continue.
            self._switch, self._reset, self.next_selection = None, True, None
            self._acked, self._epoch = self.seq, self.seq + 1  # acks of deltas before the resume are stale
        if held is not None:  # what the client says it holds is the mirror: nothing of it is sent again
            resident = np.zeros(self._resident.size, bool)
            resident[held] = True
            self._resident, self._sent, self._resync = resident, resident.copy(), False
            self._models_sent = bool(self._rep_trees[held].any()) or (resumed and self._models_sent)
        ids = np.flatnonzero(self._resident)
        self._held = [int(ids.size), int(self._rep_bytes[ids].sum()), digest(ids)]
        self._saved = None


@dataclass
class _Sent:
    """The mirror right after one delta (what its ack must report), and what that delta added and dropped."""

    held: int
    bytes: int
    digest: int
    add: np.ndarray
    drop: np.ndarray

    def remove(self, reps: np.ndarray, rep_bytes: np.ndarray, terms: np.ndarray) -> None:
        """Take refused reps out of this record (they were counted as held)."""
        self.held -= int(reps.size)
        self.bytes -= int(rep_bytes[reps].sum())
        self.digest ^= int(np.bitwise_xor.reduce(terms[reps]))


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
