"""What a client run records: one ``FrameRecord`` (and, traced, one ``FrameTrace``) per frame, the run's ``ClientRun``.

Plain frozen records, no GL and no sockets: the benchmarks and the tests read
runs through these, and the frame loop (``client.frame_loop``) writes them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from proto.errors import ProtocolError
from proto.messages import Error, Welcome

__all__ = ["FrameRecord", "FrameTrace", "Reconnect", "ClientRun"]


@dataclass(frozen=True)
class FrameRecord:
    """One frame as the client saw it; ``seq`` is the delta whose selection was drawn (-1: none).

    ``cost_coeff``, ``budget`` and ``predicted_cost`` come from the last applied
    delta (0 before any); ``upload_time`` is the decode + upload time (s) spent
    since the previous frame, outside the fence.
    """

    frame: int
    t: float
    time: float
    triangles: int
    vertices: int
    draws: int
    seq: int
    cost_coeff: float
    budget: float
    predicted_cost: float
    upload_time: float = 0.0
    morphs: int = 0
    pixels: int = 0
    splats: int = 0
    gpu_time: float | None = None
    cpu_time: float = 0.0
    prepare_time: float = 0.0
    terms: dict | None = None  # per rendering algorithm: triangles, vertices, pixels, draws (lists)
    bytes: int = 0  # bytes of the deltas applied since the previous frame (as received: framed, maybe compressed)
    compute: float = 0.0  # the server's selection time of the latest delta applied (s)
    governor_down: int = 0  # objects the frame governor drew coarser than the selection
    governor_up: int = 0  # ... and finer
    governor_cost: float = 0.0  # vertices of what it drew, as the ladder counts them (0: no governor)
    governor_predicted: float = 0.0  # the time it predicted for the frame (s; 0: no prediction yet)
    governor_bound: bool = False  # it held back a step that did not fit its aim, or had no ladder (False: all drawn)
    governor_aim: float = 0.0  # the share of the target it steered the frame to (``Governor.steer``; 0: no governor)
    governor_quantile: float = 0.0  # the quantile of measured ÷ predicted that aim came from (``Ledger.quantile``)


@dataclass(frozen=True)
class FrameTrace:
    """What one frame drew, enough to draw it again: per object its key (level-0 rep id), continuous
    level, rep and morph weight (all schedule rows, drawn or not), the camera, and — aligned with the
    reps actually drawn (``rep[drawn]``) — their rendering algorithm; the tree groups and resolutions."""

    t: float
    key: "np.ndarray"
    level: "np.ndarray"
    rep: "np.ndarray"
    weight: "np.ndarray"
    eye: "np.ndarray | None" = None
    forward: "np.ndarray | None" = None
    up: "np.ndarray | None" = None
    drawn: "np.ndarray | None" = None  # (n,) bool: the rows the cache held, hence drawn
    algorithm: "np.ndarray | None" = None  # (drawn,) index into proto.messages.ALGORITHMS, or None (all flat)
    vegetation: "np.ndarray | None" = None  # (g,) tree-group reps drawn
    resolution: "np.ndarray | None" = None  # (g,) their resolution x in (0, 1]


@dataclass(frozen=True)
class Reconnect:
    """One lost connection and its recovery (times on the client clock, s).

    resumed : the server continued the old session (False: a fresh session that adopted the held manifest)
    held : representations the hello's held manifest named; welcome_held : how many the server took as held
    attempts : dials it took (over every URL); url : the server that welcomed the redial
    """

    lost_at: float
    resumed_at: float
    resumed: bool
    held: int
    welcome_held: int
    session: str = ""
    attempts: int = 1
    reason: str = ""
    url: str = ""


@dataclass
class ClientRun:
    """What one run produced.

    errors : ``Error`` frames from the server, plus server frames this client could not decode
    rejected : geometry payloads the client refused (their reps were never resident)
    skipped : per frame, scheduled representations left undrawn because they were not resident (summed)
    late : schedules that arrived after their window opened (rebased so nothing jumped)
    unmorphed : morphing draws made at full detail for want of morph targets
    trace : with ``trace=True``, every frame's drawn levels and weights
    refused_full : representations refused because they would have taken the cache over its budget
    peak_cache_bytes : the most payload bytes the cache held after any delta
    close_reason : why the connection ended early, ``None`` if the client ended it
    client_id : the run's stable id, sent as ``client=<id>`` in the URL's query (a load balancer hashes it)
    reconnects : every lost connection the run recovered from, in order
    resent : representations a delta added that the cache already held then (0 when resumes work)
    adds_after_reconnect : representations added by deltas after the first reconnect
    bytes_per_connection : bytes received over each connection, in order (their sum is ``bytes_received``)
    deltas_per_connection : deltas received over each connection, in order
    attempts : hellos it took to open the session (more than one when the server was ``busy``)
    url : the server that welcomed the first connection (with the client id in its query)
    governor : with the frame governor, its predictors' held-out errors and the one in force
        (``FramePredictor.report``); None without
    """

    welcome: Welcome
    frames: list[FrameRecord] = field(default_factory=list)
    errors: list[Error] = field(default_factory=list)
    deltas_received: int = 0
    bytes_received: int = 0
    rejected: list[ProtocolError] = field(default_factory=list)
    skipped: int = 0
    close_reason: str | None = None
    late: int = 0
    unmorphed: int = 0
    pings: int = 0
    trace: list[FrameTrace] = field(default_factory=list)
    refused_full: int = 0
    peak_cache_bytes: int = 0
    client_id: str = ""
    reconnects: list[Reconnect] = field(default_factory=list)
    resent: int = 0
    adds_after_reconnect: int = 0
    bytes_per_connection: list[int] = field(default_factory=list)
    deltas_per_connection: list[int] = field(default_factory=list)
    attempts: int = 1
    governor: dict | None = None
    url: str = ""
