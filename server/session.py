"""One client's session as a sans-I/O state machine.

Theory of operation. A session starts in ``AWAIT_HELLO``. A valid ``hello``
naming a served scene and a known solver moves it to ``ACTIVE`` and is answered
with ``welcome``. From then on the client streams ``camera`` poses and
``frame_report`` measurements; every report folds into the cost model (the
feedback of Zach 2002, 4.2). Every τ seconds, once a pose is known, ``poll``
runs a selection for the latest pose under the budget (the client's target
frame time), diffs it against the mirror of what the client holds, and emits a
``delta``: the representations the client lacks with their geometry, the ones
it should drop, and the selection to draw.

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
    Camera,
    Delta,
    Error,
    FrameReport,
    Hello,
    Pose,
    RepresentationAdd,
    TourKey,
    Welcome,
)

from .select import solvers
from .select.benefit import importance_table
from .select.camera import View
from .select.cost import CostModel
from .select.selection import Memory, Scene, select
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
    """

    tau: float = 0.5
    margin_deg: float = 20.0
    cache_bytes: int = 512 * 1024 * 1024
    c_vertex: float = 2.0e-7
    alpha: float = 0.2
    select_limit: float = 0.1
    importance: dict = dataclasses.field(default_factory=dict)


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

    # ------------------------------------------------------------------ input

    def receive(self, data: bytes | str | BaseModel, now: float) -> list[BaseModel]:
        """Handle one frame (raw bytes, or an already decoded message); return the messages to send."""
        try:
            message = data if isinstance(data, BaseModel) else decode_client(data)
            if isinstance(message, Hello):
                return self._hello(message, now)
            if self.state is not SessionState.ACTIVE:
                raise ProtocolError("bad_state", f"'{message.type}' before 'hello'")
            if isinstance(message, Camera):
                self.camera = message
                if self.next_selection is None:
                    self.next_selection = now  # the first pose is answered at once
                return []
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
        self.state = SessionState.ACTIVE
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
            )
        ]

    # ------------------------------------------------------------------ timer

    def next_deadline(self) -> float | None:
        """When ``poll`` next has work (server clock), or None while waiting for the client."""
        return self.next_selection if self.state is SessionState.ACTIVE else None

    def poll(self, now: float) -> list[BaseModel]:
        """Run the selection if it is due; return the delta (or nothing)."""
        if self.state is not SessionState.ACTIVE or self.camera is None or self.next_selection is None:
            return []
        if now < self.next_selection:
            return []
        self.next_selection = max(self.next_selection + self.config.tau, now)
        return [self._select()]

    def _select(self) -> Delta:
        hello, camera = self.hello, self.camera
        assert hello is not None and camera is not None
        view = View.of_pose(camera.eye, camera.forward, camera.up, hello.fov_y, tuple(hello.viewport), self._bounds)
        budget = hello.target_frame_time
        # The only clock the selection sees: an anytime solver stops at select_limit with its best so far.
        limit = Limit(time.perf_counter, time.perf_counter() + self.config.select_limit)
        choice = select(self._scene, view, self.cost, budget, hello.solver, self.config.margin_deg,
                        memory=self._memory, t=camera.t, limit=limit)
        self.last_stats = choice.stats
        self.seq += 1
        reps = choice.reps
        new = reps[~self._resident[reps]]
        self._resident[new] = True
        self._last_used[reps] = self.seq
        drop = self._evict(keep=reps)
        blobs = self.scenes[self.scene_name].geometries(new.tolist()) if new.size else []
        index = self.scenes[self.scene_name].index
        add = [
            RepresentationAdd(rep=int(r), object=int(index.rep_object[r]), level=int(index.rep_level[r]), geometry=blob)
            for r, blob in zip(new.tolist(), blobs)
        ]
        self.bytes_sent += sum(len(b) for b in blobs)
        return Delta(
            seq=self.seq,
            t0=camera.t,
            t1=camera.t + self.config.tau,
            add=add,
            drop=drop.tolist(),
            selection=reps.tolist(),
            budget=budget,
            predicted_cost=choice.cost,
            cost_coeff=self.cost.c_vertex,
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
        }
