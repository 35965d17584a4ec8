"""One selection of a session, from its cameras to the delta that carries it (Zach 2002, 3.4).

The cameras of the interval (``timing``) and the cost model's budget go to
the solver (``selection.select``), under the selection time limit of the
session's injected stopwatch. The choice then passes the byte gate (``gate``:
what the link carries in time), the morph scheduler times its transitions, the
client-cache mirror (``mirror``) says what must be added and may be dropped, and
the adds are read from the store in the gate's value order. The delta carries
all of that, with the selection's compute time as the stopwatch measured it.

What carries from one selection to the next lives here: the solver's memory,
the morph schedulers, what each object drew last, and the session's estimates
of covered pixels per box pixel and of morph-map bytes per geometry byte.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from proto.messages import ALGORITHMS, MAX_LADDER_VERTICES, Delta, FrameReport, ModelAdd, Morphs, RepresentationAdd

from ..clock import Delivery
from ..select.cost import FrameCostModel
from ..select.benefit import resolved_accuracy
from ..select.ladder import Ladder, build_ladder, held_chain, prefetch
from ..select.morph import MorphScheduler, mark
from ..select.selection import DEFAULT_FACTORS, Interval, Memory, select
from ..select.snapshot import dump_fields, load_fields
from ..select.solvers.candidates import NO_LIMIT, TimeLimit
from .gate import through_gate
from .mirror import CacheMirror
from .payloads import Payloads
from .table import SceneTable

__all__ = ["Pipeline", "MEAN_FLOOR"]

#: With the governor, the least median measured ÷ predicted ratio the budget is divided by (it then exceeds
#: the target by up to 1 / MEAN_FLOOR in model seconds, for a model found to price frames that much too high).
MEAN_FLOOR = 0.67
#: The weight of each observed frame report in ``Pipeline.spare``: it follows a change within about a second
#: of reports (they are observed at ``SessionConfig.observe_hz``).
SPARE_WEIGHT = 0.1


class Pipeline:
    """A session's selections: the state one carries to the next, and ``select`` that builds a delta."""

    #: The fields a snapshot holds (among the session's fields), by their snapshot names.
    STATE = {"_pixel_scale": "pixel_scale"}
    #: ... and those that may come and go with the streaming code (a snapshot without them still loads).
    OPTIONAL = {"deferred": "deferred", "fallbacks": "fallbacks", "ladder_shed": "shed", "ahead_spare": "spare"}

    def __init__(self, config) -> None:
        self.config = config
        self.table: SceneTable | None = None
        self.store = None
        self.scene = None  # the solvers' views of the scene (``SceneTable.scene``)
        self.algorithms: tuple = (0,)
        self.memory = Memory()
        self.morph = MorphScheduler(config.tau, morph=False)
        self.ramp = MorphScheduler(config.tau, morph=False)
        self.maps = False  # send collapse maps with the adds (the client morphs or governs)
        self.prev_rep = np.zeros(0, np.int64)  # the rep each object drew last delta, −1 none
        self.drawn = np.zeros(0, np.int64)
        self.pixel_scale = 1.0  # covered pixels per pixel of box screen area, measured
        self.pixels_predicted: dict[int, float] = {}  # seq → box pixels its selection was priced with
        self.morph_share = 0.1  # morph-map bytes per geometry byte sent, learned from the adds
        self.last_stats: dict = {}
        self.last_gate: dict = {}
        self.last_tail = 1.0  # the budget's tail ratio at the last selection
        self.ladder_to = np.zeros(0, np.int64)  # where the last delta's ladder steps go (kept resident)
        self.shed = 0.0  # the share of its selection the last ladder's steps down could save
        self.spare = 0.0  # the recent share of frames whose governor took every step up with time to spare
        self.deferred = 0  # choices that waited for bytes
        self.fallbacks = 0  # ... and were drawn coarser meanwhile

    def to_state(self) -> dict:
        """{"fields": …, "optional": …}: the selection's figures a snapshot holds (among the session's fields)."""
        return {"fields": dump_fields(self, self.STATE), "optional": dump_fields(self, self.OPTIONAL, optional=True)}

    def from_state(self, fields, optional) -> None:
        """Take in ``to_state``'s data; ValueError (pipeline unchanged) if it does not fit."""
        saved = {attr: getattr(self, attr) for attr in (*self.STATE.values(), *self.OPTIONAL.values())}
        try:
            load_fields(self, fields, self.STATE, "session")
            load_fields(self, optional, self.OPTIONAL, "session", optional=True)
        except ValueError:
            self.__dict__.update(saved)
            raise

    def start(self, table: SceneTable, store, hello) -> None:
        """Set up for the scene and the options a hello named."""
        self.table, self.store = table, store
        self.scene = table.scene(self.config.importance)
        self.algorithms = tuple(ALGORITHMS.index(a) for a in hello.algorithms)
        self.memory = Memory()
        self.morph = MorphScheduler(self.config.tau, morph=hello.morph)
        self.ramp = MorphScheduler(self.config.tau, morph=hello.morph)
        # The governor ramps between adjacent levels by their collapse maps, so it needs them as much as the
        # morph schedule does.
        self.maps = bool(hello.morph or hello.governor)
        self.prev_rep = np.full(table.n_objects, -1, np.int64)
        self.drawn = np.zeros(0, np.int64)
        self.ladder_to = np.zeros(0, np.int64)
        self.spare = 0.0

    # ------------------------------------------------------------------ feedback

    def observe_pixels(self, report: FrameReport) -> None:
        """Fold a frame's covered pixels into the fill estimate: boxes overstate what a mesh covers (and
        depth-tested overdraw understates nothing), so the ratio is learnt."""
        predicted = self.pixels_predicted.get(report.selection, 0.0)
        if report.pixels > 0 and predicted > 0:
            ratio = float(np.clip(report.pixels / predicted, 0.02, 4.0))
            self.pixel_scale += 0.1 * (ratio - self.pixel_scale)

    def observe_governor(self, report: FrameReport) -> None:
        """Fold in whether a governed frame ran out of steps up with time to spare (``spare``, an average)."""
        if report.governor_cost > 0:  # 0: the frame was not governed
            self.spare += SPARE_WEIGHT * (float(report.governor_spare) - self.spare)

    # ------------------------------------------------------------------ one selection

    def select(self, seq: int, now: float, hello, view, margin: float, t0: float, start: float, switch: float,
               reset: bool, cost: FrameCostModel, mirror: CacheMirror, delivery: Delivery,
               stopwatch: Callable[[], float] | None, culled=None) -> tuple[Delta, int, float]:
        """Delta ``seq`` for the cameras ``view`` (widened by ``margin`` degrees) over the interval from ``t0``,
        its schedule running from ``start`` to ``switch``; returns (delta, payload bytes, compute seconds).
        ``culled``: the culling and projection a batch of sessions did for it (``selection.cull_many``)."""
        config, table = self.config, self.table
        tau = config.tau
        # The fitted model's fixed per-frame cost (clear, finish) is spent whatever is drawn. And the frame at
        # the budget quantile, not the mean one, meets the target: the model's recent held-out measured ÷
        # predicted ratio at that quantile shrinks what the selection may spend.
        tail = cost.tail_ratio(config.budget_quantile) if config.budget_quantile > 0 else 1.0
        if hello.governor:
            # The client's governor holds each frame to the target by stepping down its ladder: the mean frame
            # is budgeted, as far as the governor can reach. Its steps down save a share ``shed`` of the
            # selection (the last ladder's), so the tail frame still fits when (1 − shed) × the selection at
            # the tail ratio does; a scene whose objects have few coarser levels is budgeted as without it.
            # The median ratio may fall below 1 (to MEAN_FLOOR): a model that prices the frames it is shown too
            # high would otherwise leave the time asked for unspent, and the governor holds what it misjudges.
            mean = cost.tail_ratio(0.5, floor=MEAN_FLOOR)
            tail = min(max(mean, tail * (1.0 - self.shed)), tail)
        self.last_tail = tail
        budget = max(hello.target_frame_time / tail - cost.overhead, 0.25 * hello.target_frame_time)
        # The only clock the selection sees: an anytime solver stops at select_limit with its best so far.
        began = 0.0 if stopwatch is None else stopwatch()
        limit = NO_LIMIT if stopwatch is None else TimeLimit(stopwatch, began + config.select_limit)
        choice = select(self.scene, view, cost, budget, hello.solver, margin,
                        memory=self.memory, t=t0, limit=limit, factors=config.factors,
                        algorithms=self.algorithms, pixel_scale=self.pixel_scale, culled=culled)
        self.last_stats = dict(choice.stats)
        self.pixels_predicted[seq] = choice.pixels
        if len(self.pixels_predicted) > 64:
            self.pixels_predicted.pop(min(self.pixels_predicted))
        reps, algorithm, rank = self._gate(choice.reps, choice.algorithm, view, now, mirror, delivery)
        ahead = self._ahead(reps, view, mirror) if hello.governor else np.zeros(0, np.int64)
        level = table.rep_level[reps]
        key = reps - level
        kind, _ = mark(table.rep_parent, self.drawn, reps)
        tr = self.morph.schedule(key, level.astype(np.float64), start, switch, reset=reset, kind=kind)
        self.drawn = reps
        self.prev_rep[:] = -1
        self.prev_rep[table.rep_object[reps]] = reps
        vegetation, resolution, ramps = [], [], Morphs()
        drawn_groups = groups = np.zeros(0, np.int64)
        if choice.x is not None and choice.x_reps is not None:
            rt = self.ramp.schedule(choice.x_reps, choice.x, start, switch, reset=reset)
            vegetation, resolution = choice.x_reps.tolist(), np.clip(choice.x, 0.0, 1.0).tolist()
            ramps = Morphs.model_construct(rep=rt.key.tolist(), level_from=np.clip(rt.level_from, 0, 1).tolist(),
                           level_to=np.clip(rt.level_to, 0, 1).tolist(), t0=rt.t0.tolist(), t1=rt.t1.tolist())
            # Tree groups drawn now, and those a ramp still draws from the window on, must be resident too.
            drawn_groups = np.asarray(choice.x_reps, np.int64)[np.asarray(choice.x) > 0]
            groups = np.union1d(drawn_groups, rt.needed_key[rt.needed_hi > 0]).astype(np.int64)
        # The ladder's chains down stay resident: the levels that hold the frame when the plan is too heavy.
        below = np.zeros(0, np.int64)
        if hello.governor:
            arrays = self._arrays(mirror)
            below = np.concatenate([below] + [to for _, to in held_chain(
                reps, -1, rep_object=arrays["rep_object"], resident=arrays["resident"], eligible=arrays["eligible"])])
        # The previous ladder governs until this delta's switch, and its steps ramp back after: kept too.
        new, drop = mirror.plan(np.concatenate([reps, drawn_groups]),
                                np.concatenate([groups, ahead, below, self.ladder_to]), seq,
                                ranges=(tr.needed_key, tr.needed_lo, tr.needed_hi))
        ladder = self._ladder(reps, view, mirror) if hello.governor else Ladder.empty()
        self.ladder_to = ladder.to
        self.shed = ladder.shed
        if new.size and rank is not None:
            # Best benefit per byte first (a chain's intermediates with their target, coarse before fine).
            order = rank[table.rep_object[new]]
            new = new[np.lexsort((table.rep_level[new], order))]
        add, models, nbytes = self._adds(new, mirror)
        morphs = Morphs.model_construct(
            rep=(tr.key + tr.level_to.astype(np.int64)).tolist(), level_from=tr.level_from.tolist(),
            level_to=tr.level_to.tolist(), t0=tr.t0.tolist(), t1=tr.t1.tolist(),
        )
        took = 0.0 if stopwatch is None else stopwatch() - began
        self.last_stats.update(tr.stats)
        # Built, not validated: every value is the server's own, and validating its long lists costs more than
        # encoding them. The client validates what it decodes; the tests check a delta built here against a
        # validated copy, byte for byte.
        delta = Delta.model_construct(
            seq=int(seq),
            t0=float(switch),
            t1=float(switch + tau),
            start=float(start),
            reset=bool(reset),
            add=add,
            drop=drop.tolist(),
            models=models,
            selection=reps.tolist(),
            algorithm=[] if algorithm is None else algorithm.tolist(),
            budget=float(budget),
            predicted_cost=float(choice.cost),
            cost_coeff=float(cost.c_vertex),
            compute=min(max(took, 0.0), 3600.0),
            morphs=morphs,
            vegetation=vegetation,
            resolution=resolution,
            ramps=ramps,
            ladder_rep=ladder.rep.tolist(),
            ladder_to=ladder.to.tolist(),
            ladder_cost=np.minimum(ladder.cost, MAX_LADDER_VERTICES).astype(np.float64).tolist(),
            ladder_value=ladder.value.astype(np.float64).tolist(),
            ladder_base=float(min(ladder.base, MAX_LADDER_VERTICES)),
        )
        return delta, nbytes, took

    def _arrays(self, mirror: CacheMirror) -> dict:
        table = self.table
        return dict(rep_object=table.rep_object, rep_faces=table.rep_faces, object_lo=table.object_lo,
                    object_hi=table.object_hi, resident=mirror.resident, eligible=~table.rep_trees)

    def _ahead(self, reps: np.ndarray, view, mirror: CacheMirror) -> np.ndarray:
        """Neighbouring levels of the selection sent ahead for the governor's steps, with the bytes the gate left
        (at most ``ahead_share`` of what the selection's adds take, plus ``ahead_floor``; up to 1 + ``ahead_gain``
        times that while the governor reports time to spare with every step up taken)."""
        gate, config = self.last_gate, self.config
        used = float(gate.get("bytes", 0))
        left = max(float(gate.get("budget", gate.get("link", 0.0))) - used, 0.0)
        left = min(left, (config.ahead_share * used + config.ahead_floor) * (1.0 + config.ahead_gain * self.spare))
        cam = view.views[0] if isinstance(view, Interval) else view
        return prefetch(reps, cam, rep_bytes=self.table.rep_bytes, left=left, rep_error=self._ladder_errors(),
                        **self._arrays(mirror))

    def _ladder_errors(self) -> np.ndarray | None:
        """The levels' geometric errors where the session prices accuracy by them (screen-space error), else None:
        the ladder values steps as the selection values levels."""
        flat = self.scene.flat
        factors = resolved_accuracy(self.config.factors or DEFAULT_FACTORS, errors=flat.rep_error is not None)
        return flat.rep_error if factors.accuracy == "sse" else None

    def _ladder(self, reps: np.ndarray, view, mirror: CacheMirror) -> Ladder:
        """The governor's ladder for the gated selection, over what the client holds after this delta."""
        cam = view.views[0] if isinstance(view, Interval) else view
        arrays = self._arrays(mirror)
        mesh = arrays["eligible"][reps]
        return build_ladder(reps[mesh], cam, rep_vertices=self.scene.flat.rep_vertices,
                            rep_error=self._ladder_errors(), **arrays)

    def _gate(self, reps: np.ndarray, algorithm, view, now: float, mirror: CacheMirror, delivery: Delivery):
        """The selection as the link allows it (``gate.through_gate``), with the send order per object: bytes
        this delta's new representations may take are bandwidth × τ × link_share, less what is in flight."""
        config = self.config
        link = delivery.bandwidth * config.tau * config.link_share
        in_flight = delivery.in_flight(now, max_age=max(4 * config.tau, 1.0))
        left = max(link - in_flight, 0.0)
        budget = left / (1.0 + self.morph_share)  # the gate counts geometry; morph maps ride along
        cam = view.views[0] if isinstance(view, Interval) else view
        gated = through_gate(reps, algorithm, cam, self.table, mirror.resident, self.prev_rep, budget, in_flight)
        self.last_gate = {"link": left, "bandwidth": delivery.bandwidth, **gated.stats}
        self.deferred += gated.deferred
        self.fallbacks += gated.fallbacks
        return gated.reps, gated.algorithm, gated.rank

    def _adds(self, new: np.ndarray, mirror: CacheMirror) -> tuple[list[RepresentationAdd], list[ModelAdd], int]:
        """The adds for ``new`` (meshes with their morph maps, tree groups' instance lists), the store's tree
        models with the session's first tree group, and the payload bytes of both — as the scene's shared
        cache holds them (``payloads``: read and packed once for every session)."""
        payloads = Payloads.of(self.store)
        add = payloads.adds(new.tolist(), self.maps) if new.size else []
        models: list[ModelAdd] = []
        if new.size and self.table.rep_trees[new].any() and not mirror.models_sent:
            mirror.models_sent = True  # the groups' instances name these: sent once, kept
            models = payloads.models()
        # The stored sizes (the store records each payload's length), summed over arrays: a delta may carry
        # hundreds of adds.
        geometry = int(self.table.rep_bytes[new].sum()) if new.size else 0
        maps = int(payloads.morph_bytes[new].sum()) if new.size and self.maps else 0
        nbytes = geometry + maps + sum(len(m.points) for m in models)
        if geometry:  # what morph maps add to the geometry they come with, as this session sees it
            self.morph_share += 0.3 * (maps / geometry - self.morph_share)
        return add, models, nbytes

