"""What a session is given: its settings, the scene stores it serves, and the states it passes through."""

from __future__ import annotations

import dataclasses
import enum
import math
from dataclasses import dataclass
from typing import Protocol

from ..select.benefit import BenefitFactors

__all__ = ["SessionConfig", "SessionState", "SceneSource", "TAIL_MIN_SHARE"]

#: Frames under this share of the target frame time (measured and predicted) are left out of the budget's tail
#: ratio and move only the cost model's fixed overhead, not its per-unit prices (``OnlineCostModel.tail_min_time``).
TAIL_MIN_SHARE = 0.25


class SceneSource(Protocol):
    """What a session needs of a scene store."""

    @property
    def index(self): ...

    def geometries(self, reps) -> list[bytes]: ...

    def walkable(self): ...

    def walkable_encoded(self) -> bytes: ...


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
    ahead_share : with the governor, the levels sent ahead for its ladder (``select.ladder.prefetch``) take at
        most this share of the bytes the selection's own adds take (plus ``ahead_floor`` bytes): every byte
        sent is a byte the client decodes and uploads between frames, so the link's headroom is not the limit
    ahead_gain : that allowance grows to (1 + ahead_gain) × as the share of recent frames whose governor drew every
        step up and still had time to spare (``FrameReport.governor_spare``) goes to 1: where the picture is
        short of finer levels, the time between frames to decode them is there too
    cost_model : "online" — F&S's coefficients fitted to the frame reports by robust recursive least
        squares, the simplest adequate model chosen (``select.cost_online``); "zach" — the running
        c_vertex average alone (Zach 2002, 4.2), for comparison
    governed_within : with the client's governor on, the online cost model uses a richer model than the
        simplest only when the simplest one's held-out error exceeds (1 + this) × the best one's (``within``;
        0.30 without the governor, and never less with it: a governed session asks more, not less). The governor corrects each frame's cost from the frames themselves, so a
        richer model's better frame predictions buy the plan little; what it costs the plan is its extra
        terms' prices, fitted on frames the governor holds at one load (its steps change vertices while the
        draws stay), and extrapolated by the solver to plans of other mixes.
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
    governed_within: float = 1.0
    link_share: float = 0.8
    ahead_share: float = 0.5
    ahead_floor: int = 64 * 1024
    ahead_gain: float = 3.0
    budget_quantile: float = 0.95
    observe_hz: float = 20.0
    bandwidth: float = 10.0e6

    def __post_init__(self) -> None:
        if not self.observe_hz > 0:
            raise ValueError(f"observe_hz must be positive, got {self.observe_hz}")
        if not (self.ahead_share >= 0 and self.ahead_floor >= 0 and 0 <= self.ahead_gain < math.inf):
            raise ValueError(f"ahead_share, ahead_floor and ahead_gain must be finite and non-negative, got "
                             f"{self.ahead_share}, {self.ahead_floor}, {self.ahead_gain}")
        if not (0 <= self.governed_within < math.inf):
            raise ValueError(f"governed_within must be finite and non-negative, got {self.governed_within}")
        if self.cost_model not in ("online", "zach"):
            raise ValueError(f"cost_model must be 'online' or 'zach', got {self.cost_model!r}")
