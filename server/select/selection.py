"""One selection, start to end: cull, size, benefit and cost per level, solve.

The steps the session runs every τ, as one pure function over the scene's
arrays, so that a benchmark or a test can run exactly what a session runs.

A scene offers three views of its objects (``Scene``): the flat one (triangle-mesh
leaves, for the flat solvers), the hierarchical one (every mesh, HLOD and terrain
node, for Mason & Blake's solver) and the vegetation (tree groups, the continuous
part of the mixed solver). What a session's selection remembers from one run to
the next — the options drawn last time (hysteresis, frame coherence), the last
view (motion), Feedback's threshold — is a ``Memory`` it owns.

Accuracy by view (``BenefitFactors.accuracy = "auto"``, the default): a view that
holds its levels' geometric errors (every view of a scene index) uses the
screen-space error (``benefit.DEFAULT_ACCURACY``, chosen by ``bench benefit``);
without them the flat view uses F&S's, the hierarchical view Zach's with each node's #originalFaces
the full-detail faces of its subtree (``Levels.original_faces``), so that
splitting a coarse HLOD node pays while its faces are far fewer than its pixels.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from . import options, solvers
from .benefit import BenefitFactors, original_faces, resolved_accuracy
from .camera import View, cull_hierarchy, widened
from .cost import CostModel
from .solvers.candidates import NO_LIMIT, Candidates, TimeLimit

__all__ = ["Levels", "Scene", "Memory", "Choice", "Interval", "Culled", "select", "cull_many", "HIERARCHICAL",
           "MIXED", "DEFAULT_FACTORS"]

#: The benefit factors a session without its own uses (one object: "auto" accuracy resolves once on it).
DEFAULT_FACTORS = BenefitFactors()

#: Solvers that read the hierarchical view, and the one that also takes the vegetation.
HIERARCHICAL = frozenset({"hierarchical"})
MIXED = frozenset({"mixed"})


@dataclass(frozen=True)
class Levels:
    """The part of a scene index the selection reads (structure of arrays).

    object_lo, object_hi : (n, 3) float bounding boxes
    rep_first, rep_count : (n,) int — the object's representations are ids
        rep_first .. rep_first + rep_count − 1, coarsest first
    rep_faces, rep_vertices : (m,) int, over the whole scene
    object_class : (n,) int class ids (Importance), or None
    ids    : (n,) int64 scene object ids of these rows (None: 0..n−1)
    parent : (n,) int64 parent row within this view, −1 for roots (hierarchical view), or None
    rep_error : (m,) object-space geometric error of each representation (screen-space error accuracy), or None
    rep_textured : (m,) bool — the representation carries a base-colour texture (``benefit.texture_accuracy``),
        or None when none does (the benefit is then exactly the untextured one)
    """

    object_lo: np.ndarray
    object_hi: np.ndarray
    rep_first: np.ndarray
    rep_count: np.ndarray
    rep_faces: np.ndarray
    rep_vertices: np.ndarray
    object_class: np.ndarray | None = None
    ids: np.ndarray | None = None
    parent: np.ndarray | None = None
    rep_error: np.ndarray | None = None
    rep_textured: np.ndarray | None = None

    @property
    def n(self) -> int:
        return int(self.object_lo.shape[0])

    @classmethod
    def subset(cls, index, rows: np.ndarray, hierarchy: bool = False) -> "Levels":
        rows = np.asarray(rows, np.int64)
        parent = None
        if hierarchy:
            local = np.full(index.n_objects, -1, np.int64)
            local[rows] = np.arange(rows.size)
            up = index.object_parent[rows].astype(np.int64)
            parent = np.where(up >= 0, local[np.maximum(up, 0)], -1)
        return cls(
            index.object_lo[rows], index.object_hi[rows], index.rep_first[rows], index.rep_count[rows],
            index.rep_faces, index.rep_vertices, index.object_class[rows].astype(np.int64), rows, parent,
            rep_error=_errors(index), rep_textured=_textured(index),
        )

    @classmethod
    def of(cls, index) -> "Levels":
        """The flat view of a scene index: its triangle-mesh leaves (``SceneIndex.flat``)."""
        return cls.subset(index, np.nonzero(index.flat)[0])

    def original_faces(self) -> np.ndarray:
        """(n,) float64 Zach's #originalFaces per row, computed once per view (``benefit.original_faces``):
        a chain's finest level's faces; in a hierarchy, a node's subtree leaves' finest faces summed."""
        def make():
            count = self.rep_count.astype(np.int64)
            finest = np.where(count > 0, self.rep_faces[self.rep_first.astype(np.int64) + np.maximum(count, 1) - 1], 0)
            return original_faces(finest, self.parent)

        return options.cached(self, "original_faces", make)

    def depth(self) -> np.ndarray:
        """(n,) int64 each row's depth in its hierarchy (0 for roots and for a view without one), computed once."""
        def make():
            depth = np.zeros(self.n, np.int64)
            if self.parent is None:
                return depth
            up = self.parent.copy()
            alive = np.nonzero(up >= 0)[0]
            while alive.size:
                depth[alive] += 1
                up[alive] = self.parent[up[alive]]
                alive = alive[up[alive] >= 0]
            return depth

        return options.cached(self, "depth", make)


def _errors(index) -> np.ndarray | None:
    """(m,) float64 the index's geometric errors, or None when it stores none (all zero: an index built
    without measuring them would make every level look as good as full detail)."""
    err = np.asarray(getattr(index, "rep_error", np.zeros(0)), np.float64)
    return err if err.size and bool((err > 0).any()) else None


def _textured(index) -> np.ndarray | None:
    """(m,) bool the index's representations that carry a texture, or None when none does (an index of a
    store built before texels were recorded, or of a scene without textures)."""
    texels = getattr(index, "rep_texels", None)
    textured = np.asarray(texels if texels is not None else np.zeros(0)) > 0
    return textured if bool(textured.any()) else None


@dataclass(frozen=True)
class Scene:
    """The three views of a scene the solvers read, and the importance of each semantic class."""

    flat: Levels
    hierarchy: Levels | None = None
    vegetation: Levels | None = None
    importance: np.ndarray | None = None  # (C,) weight per class id
    n_objects: int = 0

    @classmethod
    def of(cls, index, importance: np.ndarray | None = None) -> "Scene":
        from server.scene.index import TREES

        trees = index.object_kind == TREES
        hierarchy = Levels.subset(index, np.nonzero(~trees)[0], hierarchy=True)
        hierarchy.original_faces(), hierarchy.depth()  # once per scene, not in the first τ
        return cls(
            flat=Levels.of(index),
            hierarchy=hierarchy,
            vegetation=Levels.subset(index, np.nonzero(trees)[0]),
            importance=importance,
            n_objects=int(index.n_objects),
        )


@dataclass
class Memory:
    """What a session's selection carries from one run to the next.

    option    : (n_objects,) int64 — option (level) drawn per scene object last time, −1 none
    view, t   : the last (widened) view and its client time, for apparent screen speed
    solver    : per-solver state passed in and updated from the result (Feedback's
                threshold, the incremental solver's value threshold)
    frame_time: the client's last measured frame time (Feedback reads it)
    """

    option: np.ndarray | None = None
    view: View | None = None
    t: float | None = None
    solver: dict = field(default_factory=dict)
    frame_time: float | None = None


@dataclass(frozen=True)
class Interval:
    """The cameras one selection is for (Zach 2002, 3.3): the predicted path sampled over the
    target interval, and the conservative camera that contains every view reachable by then.

    Benefit is the mean over ``views`` plus ``weight`` (λ, the distrust of the
    prediction) times the conservative camera's; cost is the maximum over ``views``.
    times : client time of each view (the Motion factor's clock), or None
    """

    views: tuple
    conservative: View | None = None
    weight: float = 0.1
    times: tuple | None = None

    def __post_init__(self) -> None:
        if not self.views:
            raise ValueError("an interval needs at least one sampled view")
        if not (self.weight >= 0 and np.isfinite(self.weight)):
            raise ValueError(f"the conservative weight λ must be finite and ≥ 0, got {self.weight}")


@dataclass(frozen=True)
class _Cam:
    """One camera of a selection: its (widened) view, matrices, benefit weight and client time."""

    view: View
    clip: np.ndarray
    planes: np.ndarray
    weight: float
    t: float | None
    sampled: bool  # a sample of the path (costs are its maximum), not the conservative camera


def _cameras(view, margin_deg: float, t: float | None) -> list[_Cam]:
    def cam(v, w, tt, sampled, margin):
        wide = widened(v, margin)
        return _Cam(wide, wide.matrix(), wide.planes(), w, tt, sampled)

    if isinstance(view, Interval):
        n = len(view.views)
        times = view.times or (t,) * n
        cams = [cam(v, 1.0 / n, tt, True, margin_deg) for v, tt in zip(view.views, times)]
        if view.conservative is not None and view.weight > 0:
            cams.append(cam(view.conservative, view.weight, times[0], False, 0.0))
        return cams
    return [cam(view, 1.0, t, True, margin_deg)]


@dataclass(frozen=True)
class Choice:
    """The selection: representation ids to draw (one per drawn object), predicted cost and benefit."""

    reps: np.ndarray  # (s,) int64
    cost: float
    benefit: float
    visible: int
    stats: dict
    x: np.ndarray | None = None  # vegetation resolutions (mixed solver), one per visible tree group
    x_reps: np.ndarray | None = None  # the tree groups' representations, aligned with x
    algorithm: np.ndarray | None = None  # (s,) rendering algorithm of each of reps (None: all flat)
    pixels: float = 0.0  # estimated pixels the drawn objects cover (box area over the sampled cameras)


@dataclass(frozen=True)
class Culled:
    """What a batch (``cull_many``) found for one selection: its cameras, the flat view's rows they see, and
    the rows' (size, offset, speed) under each camera (``options.project``)."""

    cams: list
    rows: np.ndarray
    projected: tuple


def cull_many(requests: list) -> list[Culled | None]:
    """Cull and project the selections of many sessions at once: one compiled pass over all their cameras per
    scene view (sessions of one scene share its index). ``requests``: per selection (scene, view, solver,
    margin_deg, memory, t) as ``select`` takes them, or None. Per request a ``Culled`` to hand to ``select``,
    or None where the batch does not apply (the hierarchical and mixed solvers cull their own views; before
    the kernels are ready). ``select`` with it chooses exactly what it chooses alone."""
    out: list[Culled | None] = [None] * len(requests)
    groups: dict[int, list[tuple[int, object, list, object]]] = {}
    for i, req in enumerate(requests):
        if req is None:
            continue
        scene, view, solver, margin_deg, memory, t = req
        if isinstance(scene, Levels) or solver in HIERARCHICAL or solver in MIXED:
            continue
        groups.setdefault(id(scene.flat), []).append((i, scene.flat, _cameras(view, margin_deg, t), memory))
    for members in groups.values():
        done = options.cull_project_many(members[0][1], [(cams, memory) for _, _, cams, memory in members])
        if done is None:
            continue
        for (i, _, cams, _), (rows, projected) in zip(members, done):
            out[i] = Culled(cams, rows, projected)
    return out


def select(
    scene: Scene | Levels,
    view: View | Interval,
    cost_model: CostModel,
    budget: float,
    solver: str = "greedy",
    margin_deg: float = 20.0,
    *,
    memory: Memory | None = None,
    t: float | None = None,
    factors: BenefitFactors | None = None,
    limit: TimeLimit = NO_LIMIT,
    algorithms: tuple = (0,),
    pixel_scale: float = 1.0,
    culled: Culled | None = None,
) -> Choice:
    """Choose representations for ``view`` within ``budget`` seconds with the solver called ``solver``.

    ``culled``: this selection's part of a batch (``cull_many``), which did the culling and projection.

    ``algorithms`` are the rendering algorithms the client offers (indices into
    ``proto.messages.ALGORITHMS``): the flat solvers choose one per drawn
    object (``Choice.algorithm``); the hierarchical solver draws the first.
    ``pixel_scale`` turns box screen area into covered pixels for a fill-rate cost term.

    ``factors`` with "auto" accuracy (the default) use Zach's accuracy on the
    hierarchical view and F&S's on the flat one; an explicit accuracy applies to both.

    ``view`` is one camera, or an ``Interval`` of predicted cameras and the
    conservative one. ``margin_deg`` widens the field of view of the (sampled)
    cameras so that objects about to come into view are already selected.
    ``memory`` (updated in place) carries hysteresis, motion and solver state
    between runs; ``t`` is the view's client time.
    """
    if isinstance(scene, Levels):
        scene = Scene(flat=scene, n_objects=int(scene.ids.max()) + 1 if scene.ids is not None and scene.n else scene.n)
    factors = DEFAULT_FACTORS if factors is None else factors  # one, not a new one validated each τ
    view_levels = scene.hierarchy if solver in HIERARCHICAL and scene.hierarchy is not None else scene.flat
    factors = resolved_accuracy(factors, hierarchical=solver in HIERARCHICAL, errors=view_levels.rep_error is not None)
    solve = solvers.get(solver)
    cams = _cameras(view, margin_deg, t) if culled is None else culled.cams
    if solver in HIERARCHICAL:
        if scene.hierarchy is None:
            raise ValueError("the hierarchical solver needs the scene's hierarchical view (Scene.of)")
        choice = _select_hierarchical(scene, cams, cost_model, budget, solve, memory, factors, limit)
        if tuple(algorithms) != (0,):
            choice = replace(choice, algorithm=np.full(choice.reps.size, int(algorithms[0]), np.int64))
    else:
        choice = _select_flat(scene, cams, cost_model, budget, solver, solve, memory, factors, limit,
                              tuple(int(a) for a in algorithms), float(pixel_scale), culled)
    if memory is not None:
        memory.view, memory.t = cams[0].view, cams[0].t
    return choice


def _remember(memory: Memory | None, scene: Scene, ids: np.ndarray, option: np.ndarray) -> None:
    if memory is None:
        return
    if memory.option is None or memory.option.shape[0] != scene.n_objects:
        memory.option = np.full(scene.n_objects, -1, np.int64)
    memory.option[:] = -1
    memory.option[ids] = option


def _select_flat(scene, cams, cost_model, budget, solver, solve, memory, factors, limit,
                 algorithms=(0,), pixel_scale=1.0, culled=None) -> Choice:
    lv = scene.flat
    rows = np.nonzero(options.cull(lv, cams))[0] if culled is None else culled.rows
    smooth, trees = None, np.zeros(0, np.int64)
    if solver in MIXED:
        smooth, trees = _smooth(scene, cams, cost_model)
    if rows.size == 0 and trees.size == 0:
        _remember(memory, scene, np.zeros(0, np.int64), np.zeros(0, np.int64))
        return Choice(np.zeros(0, np.int64), 0.0, 0.0, 0, {"stopped": "done"})
    size, rep, valid, faces, benefit, cost, previous = options.benefit_cost(
        lv, rows, scene, cams, cost_model, memory, factors, algorithms, pixel_scale,
        None if culled is None else culled.projected)
    cand = Candidates.of(benefit, cost, valid, size=size, faces=faces,
                         previous=None if previous is None else previous.astype(np.int64))
    state = dict(memory.solver) if memory is not None else {}
    if memory is not None and memory.frame_time is not None:
        state["frame_time"] = memory.frame_time
    state.setdefault("target", budget)
    kw = {"smooth": smooth} if solver in MIXED else {}
    result = solve(cand, budget, limit=limit, state=state, **kw)
    drawn = result.level >= 0
    reps = rep[drawn, result.level[drawn]]
    algorithm = None
    if algorithms != (0,):
        algorithm = np.asarray(algorithms, np.int64)[result.level[drawn] % len(algorithms)]
    if memory is not None:
        # A session keeps one solver, so its threshold (Feedback's pixels, the incremental value θ) is its own.
        threshold = result.stats.get("threshold")
        if threshold is not None and np.isfinite(threshold):
            memory.solver["threshold"] = float(threshold)
        ids = lv.ids[rows] if lv.ids is not None else rows
        _remember(memory, scene, ids[drawn], result.level[drawn])
    stats = dict(result.stats)
    cost_drawn = result.cost
    if result.x is not None:
        stats["vegetation"] = int(trees.size)
        stats["vegetation_x_mean"] = float(result.x.mean()) if result.x.size else 0.0
    return Choice(reps=reps, cost=cost_drawn, benefit=result.benefit, visible=int(rows.size + trees.size),
                  stats=stats, x=result.x, x_reps=_group_reps(scene, trees) if result.x is not None else None,
                  algorithm=algorithm, pixels=float(size[drawn].sum()))


def _group_reps(scene: Scene, rows: np.ndarray) -> np.ndarray:
    """The representation (finest level) of each given tree group row."""
    veg = scene.vegetation
    return (veg.rep_first[rows] + veg.rep_count[rows] - 1).astype(np.int64)


def _smooth(scene, cams, cost_model):
    """The continuous part of the mixed solver: visible tree groups, resolution x ∈ [0, 1] each.

    Benefit weight is the pixels a group covers (× importance, weighted over the
    cameras like a mesh's); its cost at full resolution is the cost model's price of all its points.
    """
    from .solvers.mixed_problem import Smooth

    veg = scene.vegetation
    if veg is None or veg.n == 0:
        return Smooth.empty(), np.zeros(0, np.int64)
    rows = np.nonzero(options.cull(veg, cams))[0]
    if rows.size == 0:
        return Smooth.empty(), rows
    size, _, _ = options.project(veg, rows, cams, None, [None] * len(cams))
    weight = np.zeros(rows.size)
    for cam, s in zip(cams, size):
        weight += cam.weight * s
    if scene.importance is not None and veg.object_class is not None:
        weight = weight * scene.importance[veg.object_class[rows]]
    points = veg.rep_vertices[veg.rep_first[rows] + veg.rep_count[rows] - 1]
    slope = np.maximum(cost_model.splat_cost(points), 1e-12)
    return Smooth.of(weight, slope), rows


def _select_hierarchical(scene, cams, cost_model, budget, solve, memory, factors, limit) -> Choice:
    from .solvers.hierarchical import Forest

    lv = scene.hierarchy
    visible = np.zeros(lv.n, bool)
    for cam in cams:
        visible |= cull_hierarchy(lv.parent, lv.object_lo, lv.object_hi, cam.planes)
    rows = np.nonzero(visible)[0]
    if rows.size == 0:
        _remember(memory, scene, np.zeros(0, np.int64), np.zeros(0, np.int64))
        return Choice(np.zeros(0, np.int64), 0.0, 0.0, 0, {"stopped": "done"})
    _, rep_v, valid_v, _, benefit_v, cost_v, _ = options.benefit_cost(lv, rows, scene, cams, cost_model, memory,
                                                                      factors)
    # The forest spans every node; culled ones keep their levels (for shape checks) but are never cut.
    rep, valid, _, vertices = options.option_arrays(lv, np.arange(lv.n))
    k = valid.shape[1]
    benefit = np.zeros(valid.shape)
    cost = np.where(valid, cost_model.predict(vertices), 0.0)
    kv = benefit_v.shape[1]
    benefit[rows, :kv] = benefit_v
    cost[rows, :kv] = np.where(valid_v, cost_v, 0.0)
    forest = Forest.of(lv.parent, benefit, cost, valid, visible)
    result = solve(forest, budget, limit=limit, state=dict(memory.solver) if memory is not None else {})
    node = np.nonzero(result.level >= 0)[0]
    reps = rep[node, result.level[node]] if k else np.zeros(0, np.int64)
    _remember(memory, scene, lv.ids[node], result.level[node])
    return Choice(reps=reps.astype(np.int64), cost=result.cost, benefit=result.benefit, visible=int(rows.size),
                  stats=dict(result.stats))
