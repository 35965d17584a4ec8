"""The wire contract: every message either side may send, validated on construction.

Messages are frozen pydantic models in strict mode: a string is never taken
for a number, NaN and infinity are refused, lists have fixed or bounded
lengths, and unknown fields are errors. Each message is a msgpack map whose
``type`` field names its class (see ``proto.codec``).

Times are seconds. Client timestamps (``t``) are on the client's clock, which is
the time base of a session. Positions are in scene units (metres).
"""

from __future__ import annotations

import math
from typing import Annotated, Literal, Union

from pydantic import BaseModel, ConfigDict, Field, model_validator

__all__ = [
    "PROTOCOL_VERSION",
    "DEFAULT_SUN",
    "LADDER_DEPTH",
    "Hello",
    "Welcome",
    "Camera",
    "FrameReport",
    "Delta",
    "RepresentationAdd",
    "Error",
    "Morphs",
    "Ping",
    "Pong",
    "Ack",
    "Pose",
    "TourKey",
    "ModelAdd",
    "AlgorithmTerms",
    "Resume",
    "Navigation",
    "TourPlan",
    "Heartbeat",
    "KIOSK_STATES",
    "MAX_HELD_BYTES",
    "ALGORITHMS",
    "ClientMessage",
    "ServerMessage",
    "CLIENT_TYPES",
    "SERVER_TYPES",
]

PROTOCOL_VERSION = 7

#: Rendering algorithms (Funkhouser & Séquin's R), cheapest first; an index into this is an ``algorithm``.
ALGORITHMS = ("flat", "lit", "textured")
Algorithm = Annotated[int, Field(ge=0, lt=len(ALGORITHMS))]
AlgorithmName = Literal[ALGORITHMS]

#: Coordinates beyond this are refused: they would lose all precision in float32.
MAX_COORD = 1.0e7
#: A delta never names more representations than this in one list.
MAX_LIST = 1 << 20
#: Levels a governor ladder's chain of steps reaches from the selected level, either way.
LADDER_DEPTH = 4
#: Vertices a ladder counts at most (a selection, or a frame the governor draws).
MAX_LADDER_VERTICES = 1.0e12

#: Where the sun is when a scene does not say (``Welcome.sun``): the unit direction towards it, world space
#: (+z up; x east and y north in geographic scenes) — from the south-south-west (azimuth 200°), 45° high.
DEFAULT_SUN = (-0.241845, -0.664463, 0.707107)

Coord = Annotated[float, Field(ge=-MAX_COORD, le=MAX_COORD)]
Vec3 = Annotated[list[Coord], Field(min_length=3, max_length=3)]
Name = Annotated[str, Field(min_length=1, max_length=128, pattern=r"^[A-Za-z0-9_.\-]+$")]
Id = Annotated[int, Field(ge=0, lt=1 << 31)]
Count = Annotated[int, Field(ge=0, le=1 << 32)]
#: A time on the client's clock (the session's time base); server estimates of it may precede 0.
Time = Annotated[float, Field(ge=-1.0e9, le=1.0e9)]
#: A client's own stamp: a tenth of that range, so what the server schedules from it (a stamp plus a lead of
#: seconds) stays a valid ``Time`` — three years of session is plenty.
ClientTime = Annotated[float, Field(ge=0.0, le=1.0e8)]
Level = Annotated[float, Field(ge=0.0, le=255.0)]


class _Message(BaseModel):
    model_config = ConfigDict(strict=True, extra="forbid", allow_inf_nan=False, frozen=True)


def _norm(v: list[float]) -> float:
    return math.sqrt(sum(x * x for x in v))


class Pose(_Message):
    """A camera pose: eye position, view direction and up vector (need not be unit)."""

    eye: Vec3
    forward: Vec3
    up: Vec3

    @model_validator(mode="after")
    def _directions(self) -> "Pose":
        f, u = self.forward, self.up
        nf, nu = _norm(f), _norm(u)
        if nf < 1e-9:
            raise ValueError("forward must be a non-zero vector")
        if nu < 1e-9:
            raise ValueError("up must be a non-zero vector")
        cross = [f[1] * u[2] - f[2] * u[1], f[2] * u[0] - f[0] * u[2], f[0] * u[1] - f[1] * u[0]]
        if _norm(cross) < 1e-6 * nf * nu:
            raise ValueError("up must not be parallel to forward")
        return self


class TourKey(Pose):
    """One key of a camera tour: the pose at time ``t`` seconds after the tour starts."""

    t: Annotated[float, Field(ge=0.0, le=1.0e6)]


# --------------------------------------------------------------------------- client → server

#: The compressed held bitset (``proto.manifest.pack_held``) a hello may carry.
MAX_HELD_BYTES = 48 * 1024


class Resume(_Message):
    """Continue session ``session`` (on any replica): the ``token`` its welcome gave proves it is ours."""

    session: Annotated[str, Field(min_length=1, max_length=128, pattern=r"^[A-Za-z0-9_\-]+$")]
    token: Annotated[str, Field(min_length=16, max_length=128, pattern=r"^[A-Za-z0-9_\-]+$")]
    #: The last delta the client applied: the server numbers its deltas on after it, since the state it
    #: resumes from may have been saved before its last deltas were sent. None: the saved numbering stands.
    seq: Count | None = None


#: Keys a tour plan carries at most (a 10-minute tour keyed ten times a second).
MAX_PLAN_KEYS = 10_000


class Navigation(_Message):
    """How the client's camera can move: the degrees of freedom its interface gives (Zach 2002, 4.3).

    ``walk`` keeps the eye ``eye_height`` m above the walkable ground (the welcome's ``walkable`` grid, when
    asked for); ``fly`` is free flight; ``tour`` moves only along tour plans. The camera never leaves
    ``bounds`` (min corner, max corner) when given. The speed and turn caps stay ``Hello.max_speed`` /
    ``max_turn``.
    """

    mode: Literal["walk", "fly", "tour"] = "walk"
    eye_height: Annotated[float, Field(gt=0.0, le=100.0)] = 1.7
    bounds: Annotated[list[Vec3], Field(min_length=2, max_length=2)] | None = None

    @model_validator(mode="after")
    def _ordered(self) -> "Navigation":
        if self.bounds is not None and any(lo > hi for lo, hi in zip(*self.bounds)):
            raise ValueError("bounds must be [min corner, max corner]")
        return self


class TourPlan(_Message):
    """The camera path the client will follow: exact future poses for the path prediction.

    ``keys`` carry client times (``t`` on the session's clock, ascending); between keys the camera moves
    as ``proto.tour.Tour`` interpolates. An empty plan says the visitor drives from ``t`` on (predict from
    the samples again). A new plan replaces the last one from its first key's time.
    """

    type: Literal["tour_plan"] = "tour_plan"
    t: ClientTime
    keys: Annotated[list[TourKey], Field(max_length=MAX_PLAN_KEYS)] = []
    #: The tour's name and the stop it is at or heading to (shown on the fleet page), when it has them.
    tour: Annotated[str, Field(max_length=128)] = ""

    @model_validator(mode="after")
    def _ascending(self) -> "TourPlan":
        ts = [k.t for k in self.keys]
        if any(b < a for a, b in zip(ts, ts[1:])):
            raise ValueError("tour plan keys must be in ascending t")
        return self


#: What a kiosk is doing: playing its attract loop, driven by a visitor, counting down to the attract loop,
#: outside its open hours (dimmed), or redialling a lost server (still drawing what it holds).
KIOSK_STATES = ("attract", "visitor", "countdown", "closed", "reconnecting")


class Heartbeat(_Message):
    """A kiosk's report of its health, every ``interval`` seconds: the renderer's, not just the process's."""

    type: Literal["heartbeat"] = "heartbeat"
    kiosk: Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.\-]+$")]
    t: ClientTime
    interval: Annotated[float, Field(ge=0.5, le=600.0)] = 5.0
    state: Literal[KIOSK_STATES] = "attract"
    #: Frames drawn since the kiosk started (advancing frames are what "alive" means).
    frames: Count
    fps: Annotated[float, Field(ge=0.0, le=10_000.0)] = 0.0
    #: 95th percentile of the frame times since the last heartbeat, seconds.
    frame_p95: Annotated[float, Field(ge=0.0, le=60.0)] = 0.0
    #: The last few frame times (s), oldest first, for the fleet page's sparkline.
    recent: Annotated[list[Annotated[float, Field(ge=0.0, le=60.0)]], Field(max_length=120)] = []
    rss: Annotated[int, Field(ge=0, le=1 << 42)] = 0
    #: GPU memory in use (bytes) where the driver tells it; None where it does not.
    gpu_memory: Annotated[int, Field(ge=0, le=1 << 42)] | None = None
    cache_bytes: Annotated[int, Field(ge=0, le=1 << 42)] = 0
    reconnects: Count = 0
    tour: Annotated[str, Field(max_length=128)] = ""
    stop: Annotated[int, Field(ge=-1, le=1 << 16)] = -1


class Hello(_Message):
    """Opens a session on a scene."""

    type: Literal["hello"] = "hello"
    protocol: int
    scene: Name
    viewport: Annotated[list[Annotated[int, Field(ge=16, le=16384)]], Field(min_length=2, max_length=2)]
    fov_y: Annotated[float, Field(gt=5.0, lt=170.0)] = 60.0
    target_frame_time: Annotated[float, Field(ge=0.001, le=2.0)] = 0.05
    solver: Name = "greedy"
    client: Annotated[str, Field(max_length=128)] = ""
    #: Predict the camera path and select for the future interval the delta takes effect in (Zach 2002, 3.3).
    predict: bool = True
    #: Change levels by geomorphing on a schedule (Zach 2002, 3.4) rather than switching at once.
    morph: bool = True
    #: Navigation limits θ (m/s) and ω (degrees/s) the conservative camera assumes; None: the maxima observed.
    max_speed: Annotated[float, Field(gt=0.0, le=1.0e4)] | None = None
    max_turn: Annotated[float, Field(gt=0.0, le=3600.0)] | None = None
    #: Bytes of representation payload (``len(geometry)`` of each ``RepresentationAdd``) the client keeps;
    #: None: the server's default. The server's mirror never exceeds it; the client refuses what would.
    cache_bytes: Annotated[int, Field(ge=1 << 16, le=1 << 40)] | None = None
    #: Rendering algorithms the client offers (``ALGORITHMS``); the selection picks one per representation.
    algorithms: Annotated[list[AlgorithmName], Field(min_length=1, max_length=len(ALGORITHMS))] = ["flat"]
    #: Resume an earlier session: its cost model, camera history and pipeline carry on (protocol 4).
    resume: Resume | None = None
    #: What the client already holds: ``proto.manifest.pack_held`` of its representation ids (a zlib'd bitset).
    #: The server's mirror starts from it, so nothing held is sent again — on a resume or a fresh session.
    held: Annotated[bytes, Field(max_length=MAX_HELD_BYTES)] | None = None
    #: The client corrects the server's selection every frame along the delta's ladder (a frame governor);
    #: the server then budgets the mean frame rather than the tail, as far as the governor can reach.
    governor: bool = False
    #: The client's own measure of its renderer's seconds per vertex (``client.calibrate``): the cost model's
    #: first guess, until the frame reports have measured the machine; None: the server's default guess.
    c_vertex: Annotated[float, Field(ge=1.0e-12, le=1.0e-3)] | None = None
    #: The interface's degrees of freedom: the server predicts within them (protocol 7); None: unconstrained.
    navigation: Navigation | None = None
    #: The path the camera follows from the start, as a ``TourPlan`` would carry it (protocol 7).
    plan: TourPlan | None = None
    #: Send the scene's walkable grid in the welcome (``proto.walkable``), for walking with collision.
    walkable: bool = False
    #: The scene's tour to follow, by name (a store's named tours: walk, flyover, orbit, ...): the welcome
    #: carries its keys; None: the scene's default tour.
    tour: Name | None = None

    @model_validator(mode="after")
    def _distinct(self) -> "Hello":
        if len(set(self.algorithms)) != len(self.algorithms):
            raise ValueError("algorithms must not repeat")
        return self


class Pong(_Message):
    """The answer to a ``ping``, sent on receipt: the server's stamp back, and the client's clock then."""

    type: Literal["pong"] = "pong"
    id: Count
    sent: float
    t: ClientTime


class Ack(_Message):
    """A delta has arrived (client time ``t``) and was applied; what the client holds now.

    ``rejected`` lists the delta's representations the client refused (a bad
    payload, or one that would overflow its cache budget). ``held`` and
    ``digest`` (``proto.manifest.digest``) describe every representation the
    client holds after applying it, so the server can check its mirror.
    """

    type: Literal["ack"] = "ack"
    seq: Count
    t: ClientTime
    rejected: Annotated[list[Id], Field(max_length=MAX_LIST)] = []
    held: Annotated[int, Field(ge=-1, le=MAX_LIST)] = -1
    digest: Annotated[int, Field(ge=0, lt=1 << 64)] = 0
    held_bytes: Annotated[int, Field(ge=0, le=1 << 42)] = 0


class AlgorithmTerms(_Message):
    """A frame's work per rendering algorithm (index into ``ALGORITHMS``): the F&S cost model's inputs."""

    triangles: Annotated[list[Count], Field(max_length=len(ALGORITHMS))] = []
    vertices: Annotated[list[Count], Field(max_length=len(ALGORITHMS))] = []
    pixels: Annotated[list[Count], Field(max_length=len(ALGORITHMS))] = []
    draws: Annotated[list[Count], Field(max_length=len(ALGORITHMS))] = []

    @model_validator(mode="after")
    def _columns(self) -> "AlgorithmTerms":
        n = len(self.triangles)
        if not (len(self.vertices) == len(self.pixels) == len(self.draws) == n):
            raise ValueError("per-algorithm columns must have equal lengths")
        return self


class FrameReport(_Message):
    """What one frame drew and how long it took (fenced wall time, seconds)."""

    type: Literal["frame_report"] = "frame_report"
    frame: Count
    t: ClientTime
    time: Annotated[float, Field(gt=0.0, le=60.0)]
    triangles: Count
    vertices: Count
    draws: Count
    selection: Annotated[int, Field(ge=-1, lt=1 << 31)] = -1
    #: Covered pixels (samples passed the depth test), 0 when not measured
    pixels: Count = 0
    #: Point splats drawn (vegetation)
    splats: Count = 0
    #: GPU time of the frame from a timer query, None where the driver's values are not trustworthy
    gpu_time: Annotated[float, Field(ge=0.0, le=60.0)] | None = None
    #: Client CPU seconds spent preparing and submitting the frame (outside the GPU's work)
    cpu_time: Annotated[float, Field(ge=0.0, le=60.0)] = 0.0
    #: The same work split by rendering algorithm (None: all of it flat)
    terms: AlgorithmTerms | None = None
    #: What the frame governor drew: objects drawn coarser and finer than the selection, and the vertices of
    #: the drawn selection as the ladder counts them (``Delta.ladder_base`` and its steps; 0: no governor)
    governor_down: Count = 0
    governor_up: Count = 0
    governor_cost: Annotated[float, Field(ge=0.0, le=MAX_LADDER_VERTICES)] = 0.0
    #: The governor drew every step up its ladder offers and predicted the frame still under its aim: time asked
    #: for is left unspent for want of finer levels (the server then sends more of them ahead)
    governor_spare: bool = False


class Camera(Pose):
    """Where the client's camera is at client time ``t``; ``report``: the last frame's, sent with it.

    A client that draws sends one message a frame instead of two: each message costs a server its websocket
    and event-loop work whatever it carries, and with many sessions that work is a third of a core's time.
    The server takes the report first (its frame came before this pose), as if it had come alone.
    """

    type: Literal["camera"] = "camera"
    t: ClientTime
    report: FrameReport | None = None


# --------------------------------------------------------------------------- server → client


class Welcome(_Message):
    """Accepts a session: where the scene is, where to start, how often selections come."""

    type: Literal["welcome"] = "welcome"
    session: Annotated[str, Field(min_length=1, max_length=128)]
    protocol: int
    scene: Name
    bounds: Annotated[list[Vec3], Field(min_length=2, max_length=2)]
    start: Pose
    tau: Annotated[float, Field(gt=0.0, le=60.0)]
    solver: Name
    tour: Annotated[list[TourKey], Field(max_length=100_000)] = []
    predict: bool = True
    morph: bool = True
    #: Present with ``session`` in a later hello's ``resume`` to continue this session after a lost connection.
    token: Annotated[str, Field(max_length=128)] = ""
    #: True when the hello's ``resume`` was honoured (the state was found and the token matched).
    resumed: bool = False
    #: Representations of the hello's ``held`` the server took as held (its mirror's count).
    held: Annotated[int, Field(ge=0, le=MAX_LIST)] = 0
    #: The scene's walkable grid (``proto.walkable.encode``), when the hello asked and the scene has one.
    walkable: Annotated[bytes, Field(max_length=1 << 24)] | None = None
    #: The direction towards the scene's sun (world space, need not be unit), which lights every rendering
    #: algorithm; None: the scene names none (``DEFAULT_SUN``).
    sun: Vec3 | None = None

    @model_validator(mode="after")
    def _sun(self) -> "Welcome":
        if self.sun is not None and _norm(self.sun) < 1e-9:
            raise ValueError("sun must be a non-zero vector")
        return self


class Ping(_Message):
    """Asks for a ``pong`` at once, to measure the round trip and the client clock's offset (server time ``sent``)."""

    type: Literal["ping"] = "ping"
    id: Count
    sent: float


class RepresentationAdd(_Message):
    """A representation the client lacks, with its geometry payload (``proto.geometry``)."""

    rep: Id
    object: Id
    level: Annotated[int, Field(ge=0, le=255)]
    geometry: Annotated[bytes, Field(max_length=1 << 28)]
    #: ``proto.morph`` map of this level's vertices onto the previous level's, when one exists
    morph: Annotated[bytes, Field(max_length=1 << 26)] | None = None
    #: "mesh": ``geometry`` is ``proto.geometry``; "trees": a tree group's ``proto.points`` instance list
    kind: Literal["mesh", "trees"] = "mesh"


class ModelAdd(_Message):
    """A tree model the client lacks: prefix-ordered splats (``proto.points``), shared by tree groups."""

    model: Annotated[int, Field(ge=0, lt=1 << 16)]
    points: Annotated[bytes, Field(max_length=1 << 28)]


class Morphs(_Message):
    """Level transitions, as columns: ``rep``'s object ramps from ``level_from`` to ``level_to`` over [t0, t1).

    ``rep`` is the representation at ``level_to`` (for vegetation, the tree
    group's; its levels are resolutions in [0, 1]). A ramp across several levels
    is the chain of adjacent morphs Zach prescribes, each taking its share of
    the time. ``level_from == level_to`` holds a level over the span.
    """

    rep: Annotated[list[Id], Field(max_length=MAX_LIST)] = []
    level_from: Annotated[list[Level], Field(max_length=MAX_LIST)] = []
    level_to: Annotated[list[Level], Field(max_length=MAX_LIST)] = []
    t0: Annotated[list[Time], Field(max_length=MAX_LIST)] = []
    t1: Annotated[list[Time], Field(max_length=MAX_LIST)] = []

    @model_validator(mode="after")
    def _columns(self) -> "Morphs":
        n = len(self.rep)
        if not (len(self.level_from) == len(self.level_to) == len(self.t0) == len(self.t1) == n):
            raise ValueError("morph columns must have equal lengths")
        if any(b < a for a, b in zip(self.t0, self.t1)):
            raise ValueError("a morph's t1 must not precede its t0")
        return self

    def __len__(self) -> int:
        return len(self.rep)


class Delta(_Message):
    """Representations to add and drop, the selection to draw from ``t0`` (for [t0, t1)), and its morph schedule.

    From ``start`` on this delta's schedule governs: until ``t0`` the client
    keeps drawing the previous selection, except where ``morphs`` (down-morphs,
    ``t0`` entries before ``t0``) say otherwise; from ``t0`` it draws ``selection``,
    with the up-morphs ``morphs`` lists. A ``reset`` delta (the first, or after a
    teleport) replaces what is drawn at once. Times are on the client's clock.
    """

    type: Literal["delta"] = "delta"
    seq: Count
    t0: Time
    t1: Time
    start: Time | None = None
    reset: bool = False
    add: Annotated[list[RepresentationAdd], Field(max_length=MAX_LIST)] = []
    drop: Annotated[list[Id], Field(max_length=MAX_LIST)] = []
    selection: Annotated[list[Id], Field(max_length=MAX_LIST)] = []
    #: Rendering algorithm of each selected representation (aligned with ``selection``; empty: all flat)
    algorithm: Annotated[list[Algorithm], Field(max_length=MAX_LIST)] = []
    #: Tree models to keep (sent once per session, never dropped)
    models: Annotated[list[ModelAdd], Field(max_length=1 << 16)] = []
    budget: Annotated[float, Field(ge=0.0)] = 0.0
    predicted_cost: Annotated[float, Field(ge=0.0)] = 0.0
    cost_coeff: Annotated[float, Field(ge=0.0)] = 0.0
    #: The server's wall time (s) to select and build this delta (F&S's "compute" column)
    compute: Annotated[float, Field(ge=0.0, le=3600.0)] = 0.0
    morphs: Morphs = Morphs()
    #: Tree groups drawn from t0 (their representation) and their resolution x ∈ [0, 1]
    vegetation: Annotated[list[Id], Field(max_length=MAX_LIST)] = []
    resolution: Annotated[list[Annotated[float, Field(ge=0.0, le=1.0)]], Field(max_length=MAX_LIST)] = []
    ramps: Morphs = Morphs()
    #: The frame governor's ladder (``server.select.ladder``), lowest value first: a unit step of the chain of
    #: the selected ``ladder_rep`` that reaches level ``ladder_to`` (d = |ladder_to − ladder_rep| ≤ LADDER_DEPTH
    #: levels away, from the level one nearer) removes (down) or adds (up) ``ladder_cost`` vertices for a
    #: benefit change of ``ladder_value`` per vertex; ``ladder_base`` is the selection's vertices. The client
    #: measures what a vertex costs it.
    ladder_rep: Annotated[list[Id], Field(max_length=MAX_LIST)] = []
    ladder_to: Annotated[list[Id], Field(max_length=MAX_LIST)] = []
    ladder_cost: Annotated[list[Annotated[float, Field(gt=0.0, le=MAX_LADDER_VERTICES)]], Field(max_length=MAX_LIST)] = []
    ladder_value: Annotated[list[Annotated[float, Field(ge=0.0, le=1.0e12)]], Field(max_length=MAX_LIST)] = []
    ladder_base: Annotated[float, Field(ge=0.0, le=MAX_LADDER_VERTICES)] = 0.0

    @model_validator(mode="after")
    def _interval(self) -> "Delta":
        if self.t1 < self.t0:
            raise ValueError("t1 must not precede t0")
        if self.start is not None and self.start > self.t0:
            raise ValueError("start must not follow t0")
        if self.algorithm and len(self.algorithm) != len(self.selection):
            raise ValueError("algorithm must be empty or aligned with selection")
        if len(self.vegetation) != len(self.resolution):
            raise ValueError("vegetation and resolution must have equal lengths")
        if any(x > 1.0 for x in self.ramps.level_from) or any(x > 1.0 for x in self.ramps.level_to):
            raise ValueError("vegetation ramps are resolutions in [0, 1]")
        if any(a != int(a) for a in self.morphs.level_from) or any(b != int(b) for b in self.morphs.level_to):
            raise ValueError("mesh morphs go between whole levels")
        n = len(self.ladder_rep)
        if not (len(self.ladder_to) == len(self.ladder_cost) == len(self.ladder_value) == n):
            raise ValueError("ladder columns must have equal lengths")
        if any(not 1 <= abs(b - a) <= LADDER_DEPTH for a, b in zip(self.ladder_rep, self.ladder_to)):
            raise ValueError(f"a ladder step reaches 1 to {LADDER_DEPTH} levels from its selected representation")
        if n and not set(self.ladder_rep) <= set(self.selection):
            raise ValueError("a ladder step must start from a selected representation")
        if any(b < a for a, b in zip(self.ladder_value, self.ladder_value[1:])):
            raise ValueError("the ladder must be ordered by value, lowest first")
        return self


class Error(_Message):
    """A refused message: a stable ``code`` (see ``proto.errors.ERROR_CODES``) and a sentence."""

    type: Literal["error"] = "error"
    code: Annotated[str, Field(min_length=1, max_length=64)]
    message: Annotated[str, Field(max_length=4096)]


ClientMessage = Union[Hello, Camera, FrameReport, Pong, Ack, TourPlan, Heartbeat]
ServerMessage = Union[Welcome, Delta, Error, Ping]

CLIENT_TYPES: dict[str, type[_Message]] = {
    "hello": Hello, "camera": Camera, "frame_report": FrameReport, "pong": Pong, "ack": Ack,
    "tour_plan": TourPlan, "heartbeat": Heartbeat,
}
SERVER_TYPES: dict[str, type[_Message]] = {"welcome": Welcome, "delta": Delta, "error": Error, "ping": Ping}
