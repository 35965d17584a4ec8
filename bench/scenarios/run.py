"""The six scenarios and how they run: one server for a ``run_scenarios`` call, a fresh session per
run along the scenario's path, the figures measured and the verdict given (``SCENARIOS``).
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from bench.jsonable import jsonable
from bench.methods import METHODS
from bench.scenarios.measures import (
    coverage, frame_times, level_jumps, recovery_time, reset_times, rounded, window_stats,
)
from bench.scenarios.paths import (
    WALK_SPEED, Anchor, anchor_of, forward_of, max_speed, oscillation_path, spin_path, straight_path, tour_segment,
    turn_path, visible_counts,
)
from bench.scenarios.verdicts import (
    below_coarsest_verdict, drift_verdict, network_verdict, oscillation_verdict, spin_verdict, turn_verdict,
)

__all__ = [
    "SCENARIOS", "Context", "WARMUP_S", "MAX_FPS", "run_scenarios", "tour_index", "print_results", "coarsest_frame_ms", "spin",
    "turn", "oscillation", "drift", "below_coarsest", "network",
]


#: Solvers that never leave a visible object unrepresented: over budget they keep the coarsest cut.
_CUT_SOLVERS = frozenset({"hierarchical"})

#: Seconds the session takes to settle (first deltas, cost model) before any scenario's event.
WARMUP_S = 2.0
#: Client frames are paced like a 60 Hz display: cheap frames must not starve the server of the CPU.
MAX_FPS = 60.0

Tick = Callable[[str, int, int], None]


@dataclass
class Context:
    """What every scenario needs: the store and scene, the method, the target, one server.

    ``url`` starts the server on first use (``bench.demo.ServerProcess``, ``--tau``); ``close`` ends it.
    """

    store: Path
    scene: str
    target_ms: float = 50.0
    method: str = "predictive"
    #: The client corrects every frame along the delta's ladder (``client.governor``), as a client runs by
    #: default. The oscillation scenario runs without it: it judges the server's morph schedule by the
    #: schedule's own morph rate, and the governor's ramps (up to two levels per ``client.governor.RAMP``)
    #: are faster than that by design.
    governor: bool = True
    viewport: tuple[int, int] = (640, 360)
    tau: float = 0.5
    seed: int = 0
    scale: float = 1.0
    fov_y: float = 60.0
    index: Any = None
    anchor: Anchor | None = None
    _server: Any = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"unknown method {self.method!r}; known: {', '.join(METHODS)}")
        if self.target_ms <= 0 or self.tau <= 0 or self.scale <= 0:
            raise ValueError("target_ms, tau and duration_scale must be positive")
        self.store = Path(self.store)
        if self.index is None:
            from server.scene.store import SceneStore

            with SceneStore.open(self.store) as s:
                self.index = s.index
        if self.anchor is None:
            self.anchor = anchor_of(self.index, viewport=self.viewport, fov_y=self.fov_y)

    @property
    def target(self) -> float:
        return self.target_ms / 1e3

    @property
    def server(self):
        if self._server is None:
            from bench.demo import ServerProcess

            self._server = ServerProcess([self.store], extra=["--tau", str(self.tau)])
        return self._server

    @property
    def url(self) -> str:
        return self.server.url

    def close(self) -> None:
        if self._server is not None:
            self._server.close()
            self._server = None

    def seconds(self, s: float, floor: float = 0.5) -> float:
        """A phase's length scaled by ``duration_scale``, never below ``floor``."""
        return max(floor, s * self.scale)

    def run(self, keys: list[dict], duration: float, *, method: str | None = None, target_ms: float | None = None,
            url: str | None = None, trace: bool = True, on_frame: Callable | None = None,
            governor: bool | None = None):
        """One session along ``keys`` for ``duration`` s of frames (``client.app.run_client``, traced); the
        governor as ``self.governor`` unless ``governor`` says otherwise."""
        from client.app import run_client

        m = METHODS[method or self.method]
        solver, predict, morph = m.solver, m.predict, m.morph
        return run_client(url or self.url, self.scene, duration=duration, viewport=self.viewport, fov_y=self.fov_y,
                          target_frame_time=(target_ms or self.target_ms) / 1e3, solver=solver, predict=predict,
                          morph=morph, trace=trace, tour=keys, max_fps=MAX_FPS, timeout=30.0, on_frame=on_frame,
                          governor=self.governor if governor is None else governor)


def _result(name: str, passed: bool, text: str, figures: dict) -> dict:
    return {"name": name, "title": SCENARIOS[name][0], "passed": bool(passed),
            "line": f"{'PASS' if passed else 'FAIL'} {name:<14} — {text}", "figures": jsonable(figures)}


def _run_figures(run) -> dict:
    return {"frames": len(run.frames), "errors": len(run.errors), "late": int(run.late),
            "deltas": int(run.deltas_received), "bytes": int(run.bytes_received),
            "disconnected": run.close_reason is not None}


# ------------------------------------------------------------------------------------------------ scenarios


def spin(ctx: Context) -> dict:
    """Sudden complexity (F&S's spin at C): hold a sparse view (looking up, 60°) from the anchor, then a full
    turn in 1 s down into the dense view, which is then held 2 s. The same path is run with ``static`` as a
    reference (it ignores the budget, so its ratio shows what the spin costs unmanaged).

    Pass: p95 frame time over the spin and the second after it ≤ 1.25 × target. The window holds ~40 frames
    at a 50 ms target (the spin alone, ~20: its p95 would be its second-worst frame). The steady frame sits
    at the target (the budget is set for the 95th percentile), so the margin is 25 % for the frames the
    selection made for the sparse view still on screen when the dense one appears.
    """
    a = ctx.anchor
    hold, spin_s, after = ctx.seconds(4.0, floor=WARMUP_S + 0.5), 1.0, ctx.seconds(2.0, floor=1.0)
    keys = spin_path(a, hold=hold, spin=spin_s, after=after)
    duration = hold + spin_s + after
    t0, t1 = hold, hold + spin_s
    run = ctx.run(keys, duration)
    ref = ctx.run(keys, duration, method="static", governor=False)  # unmanaged: no governor either
    from proto.tour import Tour

    tour = Tour(keys)
    sparse, dense = visible_counts(ctx.index, tour.pose_at(np.array([hold / 2, t1 + 0.5])), ctx.fov_y, ctx.viewport)
    fig = {
        "anchor": a.source, "spin_s": [t0, t1],
        "before": window_stats(run.frames, WARMUP_S, t0),
        "during": window_stats(run.frames, t0, t1),
        "after": window_stats(run.frames, t1, t1 + 1.0),
        "spin": window_stats(run.frames, t0, t1 + 1.0),
        "reference": {"method": "static", **window_stats(ref.frames, t0, t1 + 1.0)},
        "objects_in_view": {"sparse": int(sparse), "dense": int(dense)},
        **_run_figures(run),
    }
    ok, text = spin_verdict(fig, ctx.target_ms)
    return _result("spin", ok and fig["errors"] == 0, text, fig)


def turn(ctx: Context) -> dict:
    """An abrupt turn (a prediction miss): walk along the dense view for 4 s at the tour's speed, turn 150° in
    0.15 s (1000°/s, beyond any speed the predictor fitted; a single camera step over 60° at that rate also
    counts as a teleport, which resets the selection) and walk on for 3 s.

    Figures: per frame, the share of the flat objects in the frustum that something drawn represents
    (``coverage``); its median over the 2 s before the turn is the baseline. Recovery is the time from the
    turn's end until coverage is back within 0.05 of the baseline for good; holes are frames whose schedule
    names representations not yet resident; the first delta drawn after the turn; p95 in the 2 s after.

    Pass: recovery ≤ 2τ + 0.3 s (a selection for the new view needs one τ to be made and one to take effect,
    plus a round trip and an upload) and p95 ≤ 1.25 × target in the 2 s after.
    """
    a = ctx.anchor
    walk, turn_s, after = ctx.seconds(4.0, floor=WARMUP_S + 0.5), 0.15, ctx.seconds(3.0, floor=2.0)
    keys = turn_path(a, walk=walk, turn_s=turn_s, after=after)
    run = ctx.run(keys, walk + turn_s + after)
    t_end = walk + turn_s
    t = np.array([tr.t for tr in run.trace])
    cov = coverage(ctx.index, run.trace, fov_y=ctx.fov_y, viewport=ctx.viewport)
    before = (t >= walk - 2.0) & (t < walk) & np.isfinite(cov)
    baseline = float(np.median(cov[before])) if before.any() else 1.0
    win = (t >= walk) & (t < t_end + 2.0)
    rec = recovery_time(t[win], cov[win], t_end, baseline)
    holes = np.array([int((~np.asarray(tr.drawn, bool)).sum()) if tr.drawn is not None else 0 for tr in run.trace])
    seq_at = next((f.seq for f in reversed(run.frames) if f.t < t_end), -1)
    first = next((f.t for f in run.frames if f.t >= t_end and f.seq != seq_at), math.inf)
    fig = {
        "anchor": a.source, "turn_s": [walk, t_end], "baseline_coverage": rounded(baseline, 3),
        "min_coverage": rounded(np.nanmin(cov[win]), 3) if win.any() else math.nan,
        "recovery_s": rounded(rec, 3) if math.isfinite(rec) else math.inf,
        "hole_frames": int((holes[win] > 0).sum()), "holes": int(holes[win].sum()),
        "first_delta_s": rounded(first - t_end, 3) if math.isfinite(first) else math.inf,
        "before": window_stats(run.frames, WARMUP_S, walk),
        "after": window_stats(run.frames, t_end, t_end + 2.0),
        "skipped": int(run.skipped), **_run_figures(run),
    }
    ok, text = turn_verdict(fig, ctx.target_ms, ctx.tau)
    return _result("turn", ok and fig["errors"] == 0, text, fig)


def oscillation(ctx: Context) -> dict:
    """Forward and back (morph conflicts): 2 m forward and back along the dense view (scaled by the tour's
    speed over a walker's 1.4 m/s in larger scenes, within ``max_speed()``), a full cycle every 2τ, for
    8 s. Each prediction points the wrong way half the time, so up-morphs get overridden by down-morphs.

    Pass: between consecutive frames no object drawn in both steps its continuous level by more than 0.5
    — or, after a slow frame, by more than the steepest morph could in that time, (K − 1)·dt/τ for an object
    of K levels (``level_jumps``; a morph steps ≤ 0.4 for 4 levels at 50 ms frames, a pop ≥ 1) — and no
    schedule arrived late (``ClientRun.late``). Resets are excused: with prediction on, a frame over 0.5 s
    resets the session (``reset_times``), whose next delta replaces the picture at once by design; the
    pairs in the 2τ after one are counted apart. Unmorphed switches are counted, not judged.
    """
    a = ctx.anchor
    period = 2 * ctx.tau
    # Peak speed 2·amplitude/period, kept within max_speed() like every path.
    amplitude = min(2.0 * max(1.0, a.speed / WALK_SPEED), max_speed() * period / 2)
    duration = ctx.seconds(8.0, floor=2.0)
    keys = oscillation_path(a, amplitude=amplitude, period=period, duration=duration)
    run = ctx.run(keys, duration, governor=False)  # the schedule's morphs alone (``Context.governor``)
    fig = {
        "anchor": a.source, "amplitude_m": rounded(amplitude), "period_s": period,
        "levels": level_jumps(run.trace, span=_span(ctx.index), tau=ctx.tau,
                              resets=reset_times(run.trace) if METHODS[ctx.method].predict else ()),
        "unmorphed": int(run.unmorphed),
        "morph_frames": int(sum(1 for f in run.frames if f.morphs > 0)),
        "frame": window_stats(run.frames, min(WARMUP_S, duration / 2)),
        **_run_figures(run),
    }
    ok, text = oscillation_verdict(fig)
    return _result("oscillation", ok and fig["errors"] == 0, text, fig)


class _CpuLoad:
    """``count`` busy-loop processes (``python -c "while True: pass"``), started by ``start`` and ended by
    ``stop`` — each by its own handle, always, even when the run fails."""

    def __init__(self, count: int) -> None:
        self.count = count
        self.procs: list[subprocess.Popen] = []

    def start(self) -> None:
        for _ in range(self.count):
            self.procs.append(subprocess.Popen([sys.executable, "-c", "while True: pass"],
                                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))

    def stop(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                p.kill()
        for p in self.procs:
            p.wait()
        self.procs.clear()

    def __enter__(self) -> "_CpuLoad":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def drift(ctx: Context) -> dict:
    """Cost drift: a slow straight walk (a quarter of the tour's speed) along the dense view for 16 s; from 1/3
    to 2/3 of it ``os.cpu_count()`` busy-loop processes compete with the renderer's (llvmpipe's) threads, the
    client and the server. The frame time comes back only if the fitted cost model follows the drift and the
    selection coarsens.

    Figures: mean frame time before the load, in its first second, from 3 s after its start to its end
    (settled), and after it; the cost model's coefficient (``FrameRecord.cost_coeff``, median) and the
    triangles drawn before and settled.

    Pass: settled mean ≤ 1.15 × target — the steady mean sits at the target, so 15 % for a model that has
    followed the load most of the way (the load itself varies as the scheduler shares the cores) — with
    something still drawn (settled triangles > 0). Whether the picture comes back after the load is in the
    figures (``triangles_after``), not judged. A solver that never leaves a visible object out (hierarchical,
    predictive) coarsens no further than its coarsest cut; after the run that cut is drawn under the same load
    (``coarsest_loaded_ms``, as ``below_coarsest`` draws it) and the verdict judges such a solver at that floor
    when it drew there (``drift_verdict``).
    """
    a = ctx.anchor
    duration = ctx.seconds(16.0, floor=9.0)
    keys = straight_path(a, duration=duration, speed=0.25 * a.speed)
    load_t0, load_t1 = duration / 3, 2 * duration / 3
    load = _CpuLoad(os.cpu_count() or 1)
    started = stopped = math.nan

    def on_frame(rec) -> None:
        nonlocal started, stopped
        if not load.procs and math.isnan(started) and rec.t >= load_t0:
            load.start()
            started = rec.t
        elif load.procs and rec.t >= load_t1:
            load.stop()
            stopped = rec.t

    with load:  # stops the load however the run ends
        run = ctx.run(keys, duration, trace=False, on_frame=on_frame)
    cut = METHODS[ctx.method].solver in _CUT_SOLVERS
    floor_ms = math.nan
    if cut:  # the cheapest picture such a solver can coarsen to, drawn under the same load
        with _CpuLoad(load.count) as busy:
            busy.start()
            floor_ms = coarsest_frame_ms(ctx.store, ctx.index, a, cut=True, viewport=ctx.viewport, fov_y=ctx.fov_y)
    if math.isnan(started):
        started = load_t0
    if math.isnan(stopped):
        stopped = load_t1

    def median_of(attr: str, t0: float, t1: float) -> float:
        v = [getattr(f, attr) for f in run.frames if t0 <= f.t < t1 and f.seq >= 0]
        return float(np.median(v)) if v else math.nan

    settle = started + 3.0
    held = [f for f in run.frames if settle <= f.t < stopped and f.seq >= 0 and f.budget > 0]
    fig = {
        "anchor": a.source, "load_s": [rounded(started), rounded(stopped)], "processes": load.count,
        "before": window_stats(run.frames, WARMUP_S, started),
        "first_second": window_stats(run.frames, started, started + 1.0),
        "settled": window_stats(run.frames, settle, stopped),
        "after": window_stats(run.frames, stopped + 1.0),
        "cost_coeff_before": median_of("cost_coeff", WARMUP_S, started),
        "cost_coeff_settled": median_of("cost_coeff", settle, stopped),
        "triangles_before": rounded(median_of("triangles", WARMUP_S, started), 0),
        "triangles_settled": rounded(median_of("triangles", settle, stopped), 0),
        "triangles_after": rounded(median_of("triangles", stopped + 1.0, math.inf), 0),
        # A cut solver that cannot fit the budget under the load sends its coarsest cut, priced over it.
        "over_budget_settled": rounded(float(np.mean([f.predicted_cost > f.budget * (1 + 1e-9) for f in held]))
                                       if held else math.nan, 3),
        "cut_solver": cut, "coarsest_loaded_ms": rounded(floor_ms, 1),
        **_run_figures(run),
    }
    ok, text = drift_verdict(fig, ctx.target_ms)
    return _result("drift", ok and fig["errors"] == 0, text, fig)


def _span(index) -> np.ndarray:
    """(m,) K − 1 (an object's levels less one) by representation id: the most levels one ramp crosses."""
    return (np.asarray(index.rep_count, np.float64) - 1.0)[np.asarray(index.rep_object, np.int64)]


def _coarsest_reps(index, cut: bool) -> np.ndarray:
    """Level-0 representations of the cheapest complete picture: the hierarchies' roots for a cut solver,
    the flat objects (leaf meshes, finest terrain patches) for a flat one. Tree groups are left out."""
    from server.scene.index import TREES

    objects = (index.object_parent < 0) & (index.object_kind != TREES) if cut else index.flat
    return np.asarray(index.rep_first[np.nonzero(objects)[0]], np.int64)


def coarsest_frame_ms(store: Path, index, anchor: Anchor, *, cut: bool, viewport: tuple[int, int],
                      fov_y: float = 60.0, frames: int = 15) -> float:
    """Median fenced time (ms) of drawing every object at its coarsest level from the anchor, drawn the way the
    client draws a frame (``client.frame_loop``: the splat layer attached, weights, levels and algorithms given —
    flat, as the hierarchical solver draws), so the run's frames compare with it like for like."""
    from client.renderer import Renderer
    from client.splats import SplatLayer
    from proto.camera import NEAR, far_plane
    from proto.geometry import decode_geometry
    from server.scene.store import SceneStore

    reps = _coarsest_reps(index, cut)
    renderer = Renderer(int(viewport[0]), int(viewport[1]), fov_y=fov_y, backend="egl")
    splats = None
    try:
        splats = SplatLayer(renderer.ctx)
        with SceneStore.open(store) as s:
            for rep, blob in zip(reps.tolist(), s.geometries(reps.tolist())):
                renderer.upload(rep, decode_geometry(blob), object_id=int(index.rep_object[rep]))
        eye, fwd = anchor.eye, np.array(forward_of(anchor.yaw, anchor.pitch))
        up, far = np.array([0.0, 0.0, 1.0]), far_plane(anchor.eye, index.bounds)
        ones, zeros = np.ones(reps.size), np.zeros(reps.size)
        times = [renderer.draw(reps, eye, fwd, up, NEAR, far, weights=ones, levels=zeros,
                               algorithms=zeros.astype(np.int64), layers=(splats,)).time
                 for _ in range(frames + 2)][2:]
    finally:
        if splats is not None:
            splats.release()
        renderer.release()
    return float(np.median(times)) * 1e3


def below_coarsest(ctx: Context) -> dict:
    """A budget below the coarsest level: the target is 1 ms (the smallest ``hello`` accepts), while drawing
    every object at its coarsest level from the anchor — measured with the client's renderer before the run,
    the median of 15 frames — costs more (the figures show by how much). The camera walks slowly along the
    dense view for 6 s.

    The coarsest frame is the hierarchies' roots at level 0 for a solver that cuts hierarchies (the cheapest
    picture it can draw), the flat objects at level 0 for the others.

    Pass (``below_coarsest_verdict``): the session keeps running (frames drawn, no errors, not disconnected),
    and a flat solver keeps every delta's predicted cost within its budget — it drops objects rather than
    exceed it — with a median frame time (after the warm-up) below the coarsest frame's; a solver that
    never leaves a visible object unrepresented (hierarchical, predictive) cannot: it keeps the coarsest
    cut (plus what its cost model prices free) and must draw it at no more than 1.25 × the coarsest frame's
    time. On the frames whose last three deltas were all over budget, the figures give the share of drawn
    objects above their coarsest level and the frames with a split hierarchy node.
    """
    a = ctx.anchor
    solver = METHODS[ctx.method].solver
    cut = solver in _CUT_SOLVERS
    target_ms = 1.0
    coarsest = coarsest_frame_ms(ctx.store, ctx.index, a, cut=cut, viewport=ctx.viewport, fov_y=ctx.fov_y)
    duration = ctx.seconds(6.0, floor=2.5)
    run = ctx.run(straight_path(a, duration=duration, speed=0.25 * a.speed), duration, target_ms=target_ms)
    drawn = [f for f in run.frames if f.seq >= 0]
    by_delta = {f.seq: (f.budget, f.predicted_cost) for f in drawn}
    over_set = {q for q, (b, p) in by_delta.items() if p > b * (1 + 1e-9) + 1e-12}
    checked: list = []  # frames drawing only over-budget deltas
    raised, splits = [], 0
    roots = np.asarray(ctx.index.object_parent) < 0
    rep_object = np.asarray(ctx.index.rep_object, np.int64)
    for f, tr in zip(run.frames, run.trace):
        # Drawn from the latest delta or the one before, morphing from the one before that: all over budget.
        if not {f.seq, f.seq - 1, f.seq - 2} <= over_set:
            continue
        d = np.asarray(tr.drawn, bool) if tr.drawn is not None else np.ones(tr.key.shape, bool)
        if not d.any():
            continue
        checked.append(f)
        raised.append(float(np.mean(np.asarray(tr.level)[d] > 1e-9)))
        splits += int(not roots[rep_object[np.asarray(tr.key, np.int64)[d]]].all())
    # A cut solver is judged on the frames of its over-budget deltas (before them it may still be spending a
    # budget the first, unfitted cost model thought it had); a flat solver on every frame after the warm-up.
    judged = checked if cut and over_set else [f for f in drawn if f.t >= min(WARMUP_S, duration / 2)]
    ms = frame_times(judged)
    fig = {
        "anchor": a.source, "target_ms": target_ms, "target_source": "protocol minimum (hello.target_frame_time)",
        "coarsest_ms": rounded(coarsest), "below": bool(coarsest > target_ms),
        "coarsest_of": "hierarchy roots" if cut else "flat objects",
        "cut_solver": cut, "over_budget_frames": len(checked),
        "judged": "over-budget frames" if cut and over_set else "frames after the warm-up",
        "raised_share": rounded(np.mean(raised), 3) if raised else 0.0, "split_frames": splits,
        "over_budget_deltas": len(over_set), "deltas_drawn": len(by_delta),
        "budget_ms": rounded(np.median([b for b, _ in by_delta.values()]) * 1e3, 3) if by_delta else math.nan,
        "predicted_ms": rounded(np.median([p for _, p in by_delta.values()]) * 1e3, 3) if by_delta else math.nan,
        "mean_ms": rounded(ms.mean()) if ms.size else math.nan,
        "median_ms": rounded(np.median(ms)) if ms.size else math.nan,
        "triangles_mean": rounded(np.mean([f.triangles for f in judged]), 0) if judged else 0.0,
        "max_triangles": int(max((f.triangles for f in judged), default=0)),
        "p95_triangles": rounded(np.percentile([f.triangles for f in judged], 95), 0) if judged else 0.0,
        "coarsest_triangles": int(ctx.index.rep_faces[_coarsest_reps(ctx.index, cut)].sum()),
        **_run_figures(run),
    }
    ok, text = below_coarsest_verdict(fig)
    return _result("below_coarsest", ok, text, fig)


def network(ctx: Context) -> dict:
    """A bad network: 40 ± 10 ms each way and 1 % of relayed chunks lost (each costs a 200 ms retransmission
    and holds back what follows; ``bench.netem.DelayProxy`` between client and server), over 12 s of the
    scene's own tour around the anchor.

    Pass: p95 frame time (after the warm-up) ≤ 1.10 × target and no errors. A slow link delays deltas,
    not frames: the client draws what it holds, and the server starts each selection early enough for the
    measured round trip, so the frame time should barely notice — 10 % margin for frames drawing a late
    delta's uploads.
    """
    from bench.netem import DelayProxy

    a = ctx.anchor
    duration = ctx.seconds(12.0, floor=3.0)
    start = max(0.0, a.t - duration / 2)
    keys = tour_segment(ctx.index, start, duration + 1.0)
    with DelayProxy("127.0.0.1", ctx.server.port, latency=0.04, jitter=0.01, loss=0.01, rto=0.2,
                    seed=ctx.seed) as proxy:
        run = ctx.run(keys, duration, url=f"ws://{proxy.address}/ws")
        lost = proxy.lost
    st = window_stats(run.frames, min(WARMUP_S, duration / 2))
    fig = {
        "tour_s": [rounded(start), rounded(start + duration)], "latency_ms": 40.0, "jitter_ms": 10.0, "loss": 0.01,
        **st, "reconnects": len(run.reconnects), "lost_chunks": int(lost), **_run_figures(run),
    }
    ok, text = network_verdict(fig, ctx.target_ms)
    return _result("network", ok, text, fig)


#: The scenarios in the order they run: name → (title, function).
SCENARIOS: dict[str, tuple[str, Callable[[Context], dict]]] = {
    "spin": ("sudden complexity: the spin at C", spin),
    "turn": ("abrupt turn: a prediction miss", turn),
    "oscillation": ("forward/backward oscillation: morph conflicts", oscillation),
    "drift": ("cost drift: CPU load injected mid-run", drift),
    "below_coarsest": ("a budget below the coarsest level", below_coarsest),
    "network": ("network latency with jitter and loss", network),
}


def tour_index(store: str | os.PathLike[str], tour: str):
    """The store's index with its tour ``tour`` in place of the default one (and its start, and no viewpoints
    unless ``tour`` is the default: they are times of the default tour); KeyError naming the tours there are."""
    from dataclasses import replace

    from server.scene.store import SceneStore
    from server.scene.tour import default_tour_name, tour_for

    with SceneStore.open(store) as s:
        keys, start = tour_for(s.index, tour)
        own = tour == default_tour_name(s.index)
        return replace(s.index, tour=keys, start=start, meta=s.index.meta if own else {**s.index.meta, "viewpoints": {}})


def run_scenarios(
    store: str | os.PathLike[str],
    scene: str,
    *,
    target_ms: float = 50.0,
    method: str = "predictive",
    names: Sequence[str] | None = None,
    viewport: tuple[int, int] = (640, 360),
    tau: float = 0.5,
    progress: Tick | None = None,
    seed: int = 0,
    duration_scale: float = 1.0,
    tour: str | None = None,
) -> list[dict]:
    """Run the named scenarios (default: all, in ``SCENARIOS`` order) with ``method`` against one server on
    ``store``; one result each (``name``, ``title``, ``passed``, ``line``, ``figures``). A scenario that
    raises is a FAIL with the error in its line, and the rest still run. ``progress("scenarios", done,
    total)`` after each; ``duration_scale`` shortens the phases (tests); ``tour`` names the store's tour the
    scenarios take their anchor and segments from (default: its default tour)."""
    names = list(SCENARIOS) if names is None else list(names)
    unknown = [n for n in names if n not in SCENARIOS]
    if unknown:
        raise ValueError(f"unknown scenario(s) {', '.join(unknown)}; known: {', '.join(SCENARIOS)}")
    ctx = Context(Path(store), scene, target_ms=float(target_ms), method=method, viewport=tuple(viewport), tau=tau,
                  seed=seed, scale=float(duration_scale), index=None if tour is None else tour_index(store, tour))
    results: list[dict] = []
    if progress is not None:
        progress("scenarios", 0, len(names))
    try:
        for i, name in enumerate(names, 1):
            began = time.monotonic()
            try:
                res = SCENARIOS[name][1](ctx)
            except Exception as exc:  # one broken scenario must not hide the others' lines
                res = _result(name, False, f"error: {type(exc).__name__}: {exc}"[:300], {"error": str(exc)})
            res["figures"]["method"] = method
            res["figures"]["target_ms"] = res["figures"].get("target_ms", float(target_ms))
            res["figures"]["seconds"] = rounded(time.monotonic() - began, 1)
            results.append(res)
            if progress is not None:
                progress("scenarios", i, len(names))
    finally:
        ctx.close()
    return results


def print_results(results: Sequence[Mapping[str, Any]], console=None) -> None:
    """Print each scenario's line (``console``: a rich Console or anything with ``print``; default stdout)."""
    for r in results:
        if console is None:
            print(r["line"])
        else:
            console.print(r["line"], markup=False, highlight=False)
