"""One client's session as a sans-I/O state machine.

Theory of operation. A session starts in ``AWAIT_HELLO``. A valid ``hello``
naming a served scene and a known solver moves it to ``ACTIVE`` and is answered
with ``welcome`` and a ``ping``. From then on the client streams ``camera``
poses and ``frame_report`` measurements, answers pings with ``pong`` and acks
each delta; every report folds into the cost model (the feedback of Zach 2002,
4.2), every pose into the path predictor, and a ``tour_plan`` tells the predictor
the path ahead (``select.navigation``). Each message type has one handler
(``_HANDLERS``).

Time is the client's clock: pongs give its offset and the round trip, acks the
time a delta takes to arrive. Selections run Zach's three-stage pipeline
(2002, 3.4) on a grid of switch times s, s + τ, … (``timing``): the selection
for the interval [s, s + τ) runs just early enough that its delta reaches the
client before its morph window [s − τ, s) opens, with the camera predicted over
the interval and the conservative camera around it. The delta (``pipeline``)
carries the representations the client lacks (with their morph maps), the ones
it may drop (``mirror``), the selection and its morph schedule. The first
delta, and the first after a teleport, is a reset: it replaces what is drawn at
once.

Nothing here touches a socket or reads a clock: the caller passes ``now`` and
sends what comes back (the style of the ``websockets`` and ``h11`` cores), and
the selection's own time is measured by the ``stopwatch`` the caller injects,
so a session driven by a scripted stopwatch is deterministic. A bad message
yields an ``error`` frame and changes nothing else.

The parts own their state: the cost model, the clock sync and the link's
delivery estimate (``server.clock``), the timer, the selection pipeline and
the client-cache mirror; the state machine holds the counters and the
handshake. A snapshot is each part's ``to_state`` in one blob; a restore builds
a fresh set of parts from it, and a hello that does not resume it starts from
another fresh set.
"""

from __future__ import annotations

import math

import secrets
from types import SimpleNamespace
from typing import Callable, Mapping

import numpy as np
from pydantic import BaseModel

from proto.codec import decode_client
from proto.errors import ProtocolError
from proto.manifest import unpack_held
from proto.messages import ALGORITHMS, PROTOCOL_VERSION, Ack, Camera, Error, FrameReport, Hello, Ping, Pong, Pose
from proto.messages import Heartbeat, TourKey, TourPlan, Welcome

from .. import state as _blob
from ..clock import ClockSync, Delivery
from ..scene.tour import tour_for
from ..select import solvers
from ..select.cost import CostModel, FrameCostModel
from ..select.cost_online import OnlineCostModel
from ..select.navigation import Navigable, check_plan
from ..select.predict import MotionLimits, Predictor, tour_speed
from ..select.snapshot import dump_fields, load_fields
from .config import TAIL_MIN_SHARE, SceneSource, SessionConfig, SessionState
from .mirror import CacheMirror
from .pipeline import Pipeline
from .table import SceneTable
from .timing import Timing

__all__ = ["Session"]


def _figure(part: str, name: str, doc: str) -> property:
    return property(lambda self: getattr(getattr(self, part), name), doc=doc)


class Session:
    """scenes : the served scene stores by name; session_id, token : the session's name and resume secret
    stopwatch : seconds from an arbitrary origin (a zero-argument callable): the selection's deadline and the
        ``compute`` time that feeds the lead are read from it, and from nothing else. The server passes its
        wall clock; None runs every selection to completion and reports no compute time.
    """

    #: The state machine's own fields a snapshot holds (among the session's fields).
    STATE = ("seq", "frames", "errors", "bytes_sent", "last_frame_time", "teleports", "acks", "_ping_id")

    def __init__(self, scenes: Mapping[str, SceneSource], session_id: str, config: SessionConfig | None = None,
                 token: str | None = None, *, stopwatch: Callable[[], float] | None = None):
        self.scenes = scenes
        self.id = session_id
        # The secret a resume must present with ``id`` (proto Resume.token); a resumed session keeps its own.
        self.token = token or secrets.token_urlsafe(24)
        if not _blob.TOKEN.fullmatch(self.token):
            raise ValueError("a session token is 16–128 characters of [A-Za-z0-9_-]")
        self.config = config or SessionConfig()
        self._stopwatch = stopwatch
        self.state = SessionState.AWAIT_HELLO
        self.hello: Hello | None = None
        self.scene_name = ""
        self.camera: Camera | None = None
        self.heartbeat: Heartbeat | None = None  # a kiosk's latest report (``server.fleet`` keeps the fleet)
        self.fence: str | None = None  # the token this session was resumed from (``StateStore.save``)
        # Counters for /sessions and the tests; ``seq`` numbers the deltas.
        self.seq = self.frames = self.errors = self.bytes_sent = self.teleports = self.acks = 0
        self.last_frame_time = 0.0
        self.cost, self.clock, self.delivery, self.timing, self.pipeline, self.mirror = self._new_parts()
        self.predictor: Predictor | None = None
        self._next_ping: float | None = None
        self._ping_id = 0
        self._pings: dict[int, float] = {}  # id → stamp of each ping not yet answered
        self._observe_due = -np.inf  # client time from which the next frame report is folded into the cost model
        self._last_reset = -math.inf  # when the last reset selection began (server clock)
        self._restored: dict | None = None  # what ``restore`` took in that the hello applies or discards
        self._saved: tuple | None = None  # ``_progress()`` at the last snapshot (see ``dirty``)
        self._framed: tuple | None = None  # the selection framed at a time (``_frame``), until it runs

    def _new_parts(self) -> tuple:
        """A fresh cost model, clock sync, delivery estimate, timer, pipeline and (empty) mirror."""
        c = self.config
        return (self._cost_model(c.c_vertex), ClockSync(), Delivery(bandwidth=c.bandwidth),
                Timing(c.tau, c.safety, c.select_limit, c.clock_wait), Pipeline(c),
                CacheMirror(None, c.cache_bytes, self.id))

    def _cost_model(self, c_vertex: float) -> FrameCostModel:
        """A fresh cost model of the configured kind, its first guess ``c_vertex`` seconds per vertex."""
        c = self.config
        if c.cost_model == "zach":
            return CostModel(c_vertex=c_vertex, alpha=c.alpha)
        return OnlineCostModel(algorithms=len(ALGORITHMS), c_vertex=c_vertex, batch=True)

    # ------------------------------------------------------------------ input

    def receive(self, data: bytes | str | BaseModel, now: float) -> list[BaseModel]:
        """Handle one frame (raw bytes, or an already decoded message) that arrived at server time ``now``;
        return the messages to send."""
        try:
            message = data if isinstance(data, BaseModel) else decode_client(data)
            if not isinstance(message, Hello) and self.state is not SessionState.ACTIVE:
                raise ProtocolError("bad_state", f"'{message.type}' before 'hello'")
            handler = _HANDLERS.get(type(message))
            if handler is None:
                raise ProtocolError("unknown_type", f"'{message.type}' is not a client message")
            return handler(self, message, now)
        except ProtocolError as exc:
            self.errors += 1
            return [Error(code=exc.code, message=exc.message)]

    def _on_camera(self, message: Camera, now: float) -> list[BaseModel]:
        if message.report is not None:
            self._on_frame_report(message.report, now)
            message = message.model_copy(update={"report": None})  # the session keeps the pose, not the frame
        self.camera = message
        self.clock.observe(message.t, now)
        if self.predictor is not None and self.predictor.add(message.t, message.eye, message.forward, message.up):
            if self.timing.teleport(now):  # a teleport: the pipeline restarts from here
                self.teleports += 1
                # At most one reset selection per τ/2: a camera jumping on every message costs what two do.
                self.timing.next_selection = max(now, self._last_reset + self.config.tau / 2)
        if self.timing.next_selection is None:
            self.timing.next_selection = now  # the first pose is answered at once
        return []

    def _on_tour_plan(self, message: TourPlan, now: float) -> list[BaseModel]:
        if self.predictor is None:  # nothing predicts: the plan is checked, and has no use
            check_plan(message, self.pipeline.table.bounds)
        else:
            self.predictor.set_plan(message, self.pipeline.table.bounds)
        return []

    def _on_pong(self, message: Pong, now: float) -> list[BaseModel]:
        # Only the stamp we sent under that id counts: a forged one would skew the clock (a pong claiming a ping
        # from the far past would push every schedule past the end of time).
        if self._pings.pop(message.id, None) == message.sent:
            self.clock.add(message.sent, message.t, now)
        return []

    def _on_ack(self, ack: Ack, now: float) -> list[BaseModel]:
        self.acks += 1
        took = self.delivery.acked(ack.seq, ack.t, self.clock)
        self.timing.acked(ack.seq, ack.t, took, self.id)
        self.mirror.on_ack(ack, self.seq)
        return []

    def _on_frame_report(self, message: FrameReport, now: float) -> list[BaseModel]:
        self.frames += 1
        self.last_frame_time = message.time
        self.pipeline.memory.frame_time = message.time
        # Consecutive frames of a fast client say nearly the same thing, and each fit costs the server time:
        # fold in an even sample of them in time (≤ observe_hz per second), which is unbiased.
        period = 1.0 / self.config.observe_hz
        if message.t >= self._observe_due - 1e-6 or message.t < self._observe_due - 2 * period:
            # On a grid of the period (not "a period after the last"): the average rate is observe_hz
            # whatever the client's frame rate; a client clock that went back restarts the grid.
            self._observe_due = max(self._observe_due, message.t - period) + period
            self._observe(message)
        return []

    def _on_heartbeat(self, message: Heartbeat, now: float) -> list[BaseModel]:
        # One session is one kiosk: a second id on it would make two fleet rows share one session's fate.
        if self.heartbeat is not None and message.kiosk != self.heartbeat.kiosk:
            raise ProtocolError("bad_state", f"this session reports kiosk {self.heartbeat.kiosk!r}; kiosk "
                                             f"{message.kiosk!r} needs a session of its own")
        self.heartbeat = message
        return []

    def _observe(self, report: FrameReport) -> None:
        """Fold one measured frame into the cost model, and the covered pixels into the fill estimate."""
        terms = report.terms
        if terms is None:
            self.cost.observe_frame(report.time, report.vertices)
        else:
            r = len(ALGORITHMS)

            def col(values: list[int]) -> list[float]:  # one entry per algorithm the server knows
                return [float(v) for v in values[:r]] + [0.0] * (r - len(values))

            columns = (col(terms.triangles), col(terms.vertices), col(terms.pixels), col(terms.draws))
            self.cost.observe_frame(report.time, report.vertices, columns, report.splats)
        self.pipeline.observe_pixels(report)
        self.pipeline.observe_governor(report)

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
        store = self.scenes[hello.scene]
        index = store.index
        try:
            tour, start = tour_for(index, hello.tour)  # an unknown tour is refused before anything changes
        except KeyError as exc:
            raise ProtocolError("unknown_tour", exc.args[0]) from None
        # A bad ``held`` is refused (bad_held) before anything changes.
        held = None if hello.held is None else unpack_held(hello.held, index.n_representations)
        if hello.plan is not None and hello.resume is None:
            check_plan(hello.plan, index.bounds)  # a bad plan is refused before anything changes, too
        resumed = self._resumes(hello)
        restored, self._restored = self._restored, None
        self.hello = hello
        self.scene_name = hello.scene
        if not resumed and hello.c_vertex is not None:
            # The client measured its renderer: a better first guess than the server's (a resumed session
            # keeps the model it has learnt).
            self.cost = self._cost_model(hello.c_vertex)
        # The budget's tail is that of frames the budget is about: a near-empty view's frame far over its
        # prediction (the overhead's noise) says nothing of how a frame at the target strays.
        self.cost.tail_min_time = TAIL_MIN_SHARE * hello.target_frame_time
        if hello.governor and isinstance(self.cost, OnlineCostModel):
            self.cost.within = max(self.cost.within, self.config.governed_within)
        table = SceneTable.of(index)
        self.pipeline.start(table, store, hello)
        self.timing.morph = hello.morph
        # The client-cache mirror: what the client holds, within the smaller of its budget and ours.
        budget = int(self.config.cache_bytes if hello.cache_bytes is None
                     else min(hello.cache_bytes, self.config.cache_bytes))
        if hello.predict:
            # A denormal limit in degrees underflows to 0 in radians: keep it the least positive turn rate.
            turn = None if hello.max_turn is None else max(float(np.radians(hello.max_turn)), math.ulp(0.0))
            # Without a stated speed limit, a jump is a teleport only if it outruns the scene's own tour by 3×.
            teleport = max(200.0, 3.0 * tour_speed(tour)) if hello.max_speed is None else 200.0
            self.predictor = Predictor(MotionLimits(speed=hello.max_speed, turn=turn), teleport_speed=teleport)
        if resumed:
            if hello.resume.seq is not None:
                # The save may predate the last deltas sent: number on after what the client applied.
                self.seq = max(self.seq, hello.resume.seq)
            self.mirror.budget = budget
            self.mirror.restart(self.seq)  # acks of deltas before the resume are stale
            if self.predictor is not None and restored["predictor"] is not None:
                self.predictor.from_state(restored["predictor"])  # the new hello's limits stay
            # The offsets were measured against the old replica's clock (another host's monotonic time): the
            # welcome's ping measures them afresh. Round trip and bandwidth (``delivery``) are the link's and stay.
            self.clock = ClockSync()
            self.timing.restart()  # a reset delta, as after a teleport; seq numbers continue
        else:
            self.mirror = CacheMirror(table, budget, self.id)
        if self.predictor is not None:
            self._navigation(hello, store)
        if held is not None:
            self.mirror.adopt(held)
        else:
            self.mirror.recount()
        self._saved = None
        self.state = SessionState.ACTIVE
        self._next_ping = now + self.config.ping_interval
        self.timing.hello_at = now
        return [
            Welcome(
                session=self.id,
                protocol=PROTOCOL_VERSION,
                scene=hello.scene,
                bounds=table.bounds.tolist(),
                start=Pose(**start),
                tau=self.config.tau,
                solver=hello.solver,
                tour=[TourKey(**key) for key in tour],
                predict=hello.predict,
                morph=hello.morph,
                token=self.token,
                resumed=resumed,
                held=self.mirror.held[0],
                walkable=store.walkable_encoded() if hello.walkable else None,
                sun=index.meta.get("sun"),
            ),
            self._ping(now),
        ]

    def _navigation(self, hello: Hello, store: SceneSource) -> None:
        """The hello's navigation and tour plan, for the predictor: a resumed session keeps the plan it held
        unless the hello's is newer (a redial may repeat the first hello's plan)."""
        walk = hello.navigation is not None and hello.navigation.mode == "walk"
        self.predictor.navigable = Navigable.of(hello.navigation, store.walkable() if walk else None)
        plan, held = hello.plan, self.predictor.plan
        if plan is not None and (held is None or plan.t > held.issued):
            try:
                self.predictor.set_plan(plan, store.index.bounds)
            except ProtocolError:  # only a resume gets here (a fresh hello's plan was checked): keep what it held
                pass

    def _ping(self, now: float) -> Ping:
        self._ping_id += 1
        self._pings[self._ping_id] = now
        if len(self._pings) > 16:  # pings never answered are forgotten
            self._pings.pop(min(self._pings))
        return Ping(id=self._ping_id, sent=now)

    # ------------------------------------------------------------------ timer

    def lead(self) -> float:
        """Seconds from starting a selection to its delta's arrival, as the session expects it now."""
        return self.timing.lead(self.delivery, self.clock)

    def next_deadline(self) -> float | None:
        """When ``poll`` next has work (server clock), or None while waiting for the client."""
        if self.state is not SessionState.ACTIVE:
            return None
        due = [d for d in (self._next_ping, self._selection_due()) if d is not None]
        return min(due) if due else None

    def _selection_due(self) -> float | None:
        return self.timing.selection_due(self.camera is not None, self.lead(), self.clock)

    def poll(self, now: float, culled=None) -> list[BaseModel]:
        """Send a ping and run the selection if they are due; return what to send. ``culled``: the culling
        and projection of this selection, done by a batch of sessions (``selection_request``)."""
        if self.state is not SessionState.ACTIVE:
            return []
        out: list[BaseModel] = []
        if self._next_ping is not None and now >= self._next_ping:
            out.append(self._ping(now))
            self._next_ping = now + self.config.ping_interval
        due = self._selection_due()
        if due is not None and now >= due:
            out.append(self._select(now, culled))
        return out

    def selection_request(self, now: float) -> tuple | None:
        """What a batch needs to cull and project for this session's selection due at ``now``
        (``selection.cull_many``'s request), or None when none is due. Changes nothing ``poll`` sees."""
        if self.state is not SessionState.ACTIVE:
            return None
        due = self._selection_due()
        if due is None or now < due:
            return None
        _, _, _, _, t0, _, view, margin = self._frame(now)
        return self.pipeline.scene, view, self.hello.solver, margin, self.pipeline.memory, t0

    def _frame(self, now: float) -> tuple:
        """(client now, reset, start, switch, t0, t1, view, margin) of the selection started at ``now``: the
        same until the session changes (kept, so a batch's request and the poll share one computation)."""
        p = self.predictor
        key = (now, self.seq, self.acks, self.clock.offset, p.resets if p else 0, p.latest if p else None,
               p.revision if p else 0, self.timing.switch, self.timing.reset)
        if self._framed is not None and self._framed[0] == key:
            return self._framed[1]
        hello, camera = self.hello, self.camera
        assert hello is not None and camera is not None
        c_now = self.clock.client_time(now)
        reset, start, switch, t0, t1 = self.timing.plan(c_now, self.lead())
        view, margin = self.timing.cameras(self.config, hello, camera, self.predictor, self.pipeline.table.bounds,
                                           c_now, t0, t1)
        self._framed = (key, (c_now, reset, start, switch, t0, t1, view, margin))
        return self._framed[1]

    def _select(self, now: float, culled=None):
        hello = self.hello
        c_now, reset, start, switch, t0, t1, view, margin = self._frame(now)
        self._framed = None
        if reset:
            self._last_reset = now
        self.seq += 1
        delta, nbytes, took = self.pipeline.select(self.seq, now, hello, view, margin, t0, start, switch, reset,
                                                   self.cost, self.mirror, self.delivery, self._stopwatch, culled)
        self.bytes_sent += nbytes
        self.delivery.sent(self.seq, now, nbytes, took)
        self.timing.selected(self.seq, now, c_now, start, switch, reset, took, nbytes, self.delivery, self.clock)
        self.pipeline.last_stats.update(late=self.timing.late, lead=self.lead())
        return delta

    # ------------------------------------------------------------------ state

    def close(self) -> None:
        self.state = SessionState.CLOSED

    # The figures the parts keep, read-only, under the names /sessions reports them by.
    cache_budget = _figure("mirror", "budget", "the most bytes the client's cache holds, as the mirror keeps it")
    evicted = _figure("mirror", "evicted", "reps the mirror dropped to keep within the budget")
    over_budget = _figure("mirror", "over_budget", "needed reps left unsent for want of budget, summed over deltas")
    refused = _figure("mirror", "refused", "reps the client refused (acks' ``rejected``)")
    mirror_checks = _figure("mirror", "checks", "acks whose held/held_bytes/digest were compared with the mirror")
    mirror_mismatch = _figure("mirror", "mismatch", "... and did not match (each triggers a resync)")
    resyncs = _figure("mirror", "resyncs", "deltas that dropped everything and restarted the mirror empty")
    late = _figure("timing", "late", "deltas that arrived after their schedule started")
    deferred = _figure("pipeline", "deferred", "choices the byte gate held back")
    fallbacks = _figure("pipeline", "fallbacks", "... and drew with a coarser resident level meanwhile")
    last_gate = _figure("pipeline", "last_gate", "the byte gate's figures at the last selection")
    last_stats = _figure("pipeline", "last_stats", "the solver's and the morph scheduler's at the last selection")

    @property
    def stats(self) -> dict:
        report = self.cost.report()  # why the online model is the one chosen, and its coefficients
        why = {} if report is None else {"cost_why": report["why"],
                                         "cost_coefficients": report["models"][report["chosen"]]["coefficients"]}
        pipeline, mirror, last = self.pipeline, self.mirror, self.pipeline.last_stats
        return {
            "session": self.id,
            "state": self.state.value,
            "scene": self.scene_name,
            "solver": self.hello.solver if self.hello else "",
            "kiosk": self.heartbeat.kiosk if self.heartbeat else "",
            "frames": self.frames,
            "selections": self.seq,
            "errors": self.errors,
            "cost_coeff": self.cost.c_vertex,
            "cost_updates": self.cost.updates,
            "cost_model": self.cost.chosen,
            **why,
            "cost_overhead": float(self.cost.overhead),
            "tail_ratio": pipeline.last_tail,
            "pixel_scale": pipeline.pixel_scale,
            "last_frame_time": self.last_frame_time,
            "solver_stopped": last.get("stopped", ""),
            "bytes_sent": self.bytes_sent,
            "resident": int(mirror.resident.sum()) if self.state is not SessionState.AWAIT_HELLO else 0,
            "predict": bool(self.hello.predict) if self.hello else False,
            "morph": bool(self.hello.morph) if self.hello else False,
            "rtt": self.clock.rtt,
            "clock_offset": self.clock.offset,
            "lead": self.lead(),
            "acks": self.acks,
            "late": self.timing.late,
            "teleports": self.teleports,
            "morphs": {k: last.get(k, 0) for k in ("up", "down", "collapsed", "switches")},
            "cache_budget": mirror.budget,
            "held_bytes": mirror.held[1],
            "evicted": mirror.evicted,
            "over_budget": mirror.over_budget,
            "refused": mirror.refused,
            "mirror_checks": mirror.checks,
            "mirror_mismatch": mirror.mismatch,
            "resyncs": mirror.resyncs,
            "bandwidth": self.delivery.bandwidth,
            "deferred": pipeline.deferred,
            "fallbacks": pipeline.fallbacks,
            "ahead_spare": pipeline.spare,
            "gate": dict(pipeline.last_gate),
        }

    # ------------------------------------------------------------------ persistence (``server.state``)

    def _progress(self) -> tuple:
        """What moves when state worth saving changes: deltas, acks, frame reports, teleports, refusals."""
        return (self.seq, self.acks, self.frames, self.teleports, self.mirror.refused, self.mirror.resyncs)

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
        pipeline = self.pipeline.to_state()
        state = {
            "session": self.id,
            "scene": self.scene_name,
            "n_reps": int(self.mirror.resident.size),
            "hello": self.hello.model_dump(exclude={"held", "resume"}),
            "fields": {**dump_fields(self, self.STATE), **self.mirror.counters(), **self.timing.to_state(),
                       **pipeline["fields"]},
            "optional": pipeline["optional"],
            "cost": self.cost.to_state(),
            "predictor": None if self.predictor is None else self.predictor.to_state(),
            "clock": self.clock.to_state(),
            "delivery": self.delivery.to_state(),
            "mirror": self.mirror.to_state(),
        }
        blob = _blob.pack_snapshot(state)
        self._saved = self._progress()
        return blob

    @property
    def restored_scene(self) -> str | None:
        """The scene of the snapshot ``restore`` took in (None before one): a resume must name the same."""
        return None if self._restored is None else self._restored["scene"]

    def restore(self, blob: bytes) -> None:
        """Take in a ``snapshot`` of this session, before its hello; ValueError (session unchanged) if the blob
        is bad, of another session, or of a scene this server does not serve as it was.

        Counters, seq, cost model, clock and mirror are set now, from a fresh set
        of parts; the hello keeps them and applies the camera history if it
        resumes (``hello.resume``), and otherwise starts afresh.
        """
        if self.state is not SessionState.AWAIT_HELLO or self.hello is not None:
            raise RuntimeError("restore comes before the hello")
        st = _blob.unpack_snapshot(blob)
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
        # Everything is decoded into fresh parts first: a bad blob leaves this session as it was.
        fields = st.get("fields")
        own = SimpleNamespace(**{n: getattr(self, n) for n in self.STATE})
        load_fields(own, fields, self.STATE, "session")
        cost, clock, delivery, timing, pipeline, _ = self._new_parts()
        timing.from_state(fields)
        pipeline.from_state(fields, st.get("optional", {}))
        cost.from_state(st.get("cost"))
        clock.from_state(st.get("clock"))
        delivery.from_state(st.get("delivery"))
        predictor = st.get("predictor")
        if predictor is not None:
            Predictor().from_state(predictor)  # checked now, taken in by the hello's predictor
        mirror = CacheMirror.from_state(st.get("mirror"), fields, SceneTable.of(index), self.config.cache_bytes,
                                        self.id)
        for n in self.STATE:
            setattr(self, n, getattr(own, n))
        self.cost, self.clock, self.delivery, self.timing, self.pipeline, self.mirror = (
            cost, clock, delivery, timing, pipeline, mirror)
        self.scene_name = scene
        self._restored = {"scene": scene, "hello": hello, "predictor": predictor}
        self._saved = None

    def _resumes(self, hello: Hello) -> bool:
        """Whether this hello continues the restored snapshot; if not, whatever ``restore`` took in is forgotten
        and the session starts from a fresh set of parts (it still replaces the state it was loaded from:
        ``fence`` stays)."""
        r = self._restored
        if r is None:
            return False
        resume = hello.resume
        # The token presented is the one the state was saved under: the fence, when the app rotated it.
        expected = self.fence or self.token
        if (resume is not None and resume.session == self.id and hello.scene == r["scene"]
                and secrets.compare_digest(resume.token, expected)):
            return True
        self.seq = self.frames = self.errors = self.bytes_sent = self.teleports = self.acks = self._ping_id = 0
        self.last_frame_time = 0.0
        self.cost, self.clock, self.delivery, self.timing, self.pipeline, self.mirror = self._new_parts()
        self.scene_name = ""
        self._restored = None
        return False


#: Each client message type and its handler (a hello before the others; the rest only once active).
_HANDLERS: dict[type, Callable[[Session, BaseModel, float], list[BaseModel]]] = {
    Hello: Session._hello,
    Camera: Session._on_camera,
    Pong: Session._on_pong,
    Ack: Session._on_ack,
    FrameReport: Session._on_frame_report,
    Heartbeat: Session._on_heartbeat,
    TourPlan: Session._on_tour_plan,
}
