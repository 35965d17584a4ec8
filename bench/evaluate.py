"""``walkstream eval``: every LOD method over a scene's tour, side by side (F&S 1993 Table 1).

One real server (``walkstream serve`` in a child process) serves the scene; the
real headless client drives one fresh session per run over the scene's tour, in
a fixed order: each method at the target frame time and — where the method
looks at the budget at all — at every other budget; a budget-dependent method runs
both without and with the client's frame governor (``hello.governor``). Every run
is repeated ``repeats`` times, interleaved (A B C A B C …), so that a slow stretch
of the machine hits every method alike; server and client run on different cores
and a calibration workload is timed every second beside each run
(``bench.machine``; on the server's core, not the client's). All runs offer the client one rendering algorithm
(``ALGORITHMS``, "lit" by default), so every method draws with the same shading
rule and differs only in the levels it picks. Each run keeps every
frame's measured time, the server's selection time, triangles, drawn
representations and bytes, and a trace of what it drew; afterwards the traces
are replayed untimed (``bench.replay``) against the full-detail frame at the
same camera for image error and popping (``bench.quality``), and the
false-colour level images at viewpoints A and C are drawn. The result is the
dict the README's "Evaluation" section describes (``bench.report`` writes it out).

The methods and what a session does with them are ``bench.methods.METHODS``.

Frames are paced at 60 fps (``MAX_FPS``): a frame's measured time is its fenced draw
either way, and an unpaced client on cheap frames outruns the server's per-session
message rate limit (see ``MAX_FPS``).
"""

from __future__ import annotations

import math
import os
import pickle
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np

from bench.jsonable import jsonable
from bench.methods import METHODS, Method

__all__ = [
    "RunSpec", "ALGORITHMS", "REPEATS", "MAX_FPS", "MAX_DURATION_S", "WARMUP_S", "scene_has_continuous", "plan", "skipped_methods",
    "tour_of", "eval_tour", "run_one", "summarize_frames", "evaluate", "print_table", "table_rows",
]

Progress = Callable[[str, int, int], None]

#: A frame over this multiple of the target broke it (F&S's 1.10).
OVER_RATIO = 1.10
#: Frames in the first seconds are the loop converging (cost model, first deltas); summaries start after.
WARMUP_S = 2.0
#: A tour longer than this is cut here by default: seven methods × three budgets must end within the hour.
MAX_DURATION_S = 90.0
#: Frames are paced at 60 fps, as a display would. Pacing never changes a measured frame time (the fenced
#: draw, ``FrameStats.time``), only idles the client after frames faster than 17 ms, which the budgets here
#: (≥ 25 ms) rarely allow; paced and unpaced runs cost the server the same CPU and selection time. But an
#: unpaced client sends a pose and a report per frame, and on cheap frames (a sparse view, a small viewport)
#: passes the server's 200 messages/s per session: the server drops them (``rate_limited`` errors) and
#: closes a session that keeps it up — the run would measure the rate limiter. 60 fps is 120 messages/s.
MAX_FPS: float | None = 60.0
#: The rendering algorithm every method of a Table 1 run draws with (the same rule for all: the baselines
#: would otherwise take the richest shader, Optimization the one it prices best).
ALGORITHMS: tuple[str, ...] = ("lit",)
#: Runs of each (method, budget, governor), interleaved.
REPEATS = 3


def _noop(stage: str, done: int, total: int) -> None:
    pass


@dataclass(frozen=True)
class RunSpec:
    """One run of the evaluation: a method at a target frame time (ms), with or without the client's
    frame governor, and which of its repeats it is."""

    method: Method
    target_ms: float
    governor: bool = False
    repeat: int = 0


# ---------------------------------------------------------------- planning


def scene_has_continuous(store_path: str | Path) -> bool:
    """True if the store holds tree groups (the continuous objects of the mixed solver)."""
    from server.scene.index import TREES
    from server.scene.store import SceneStore

    with SceneStore.open(store_path) as s:
        return bool(np.any(s.index.object_kind == TREES))


def _methods(methods: Iterable[str | Method] | None) -> list[Method]:
    if methods is None:
        return list(METHODS.values())
    out = []
    for m in methods:
        if isinstance(m, Method):
            out.append(m)
        elif m in METHODS:
            out.append(METHODS[m])
        else:
            raise ValueError(f"unknown method {m!r}; known: {', '.join(METHODS)}")
    if not out:
        raise ValueError("no methods to evaluate")
    names = [m.name for m in out]
    if len(set(names)) != len(names):
        raise ValueError(f"a method is named twice: {names}")
    return out


def _budgets(target_ms: float, budgets_ms: Iterable[float] | None) -> list[float]:
    """The budgets, sorted, the target among them; default 0.5×, 1×, 2× the target."""
    if not (math.isfinite(target_ms) and target_ms > 0):
        raise ValueError(f"the target frame time must be a positive number of ms, got {target_ms!r}")
    given = [0.5 * target_ms, target_ms, 2.0 * target_ms] if budgets_ms is None else [float(b) for b in budgets_ms]
    bad = [b for b in given if not (math.isfinite(b) and b > 0)]
    if bad:
        raise ValueError(f"budgets must be positive numbers of ms, got {bad}")
    return sorted(set(given) | {float(target_ms)})


def skipped_methods(methods: Iterable[str | Method] | None, continuous: bool) -> dict[str, str]:
    """Methods the scene cannot run, with why (``mixed`` without tree groups)."""
    return {m.name: "no continuous objects" for m in _methods(methods) if m.continuous_only and not continuous}


def plan(methods: Iterable[str | Method] | None, target_ms: float, budgets_ms: Iterable[float] | None,
         *, continuous: bool = True, repeats: int = 1, governor: bool = True) -> list[RunSpec]:
    """The runs, in a fixed order: method by method (in the order given), budgets ascending, a
    budget-dependent method without then (``governor``) with the governor; all that ``repeats`` times,
    interleaved (every run once, then every run again, …).

    A budget-independent method (none, static) runs once, at ``target_ms``; a continuous-only one (mixed)
    is dropped when ``continuous`` is False (``skipped_methods`` says so).
    """
    budgets = _budgets(target_ms, budgets_ms)
    specs = []
    for m in _methods(methods):
        if m.continuous_only and not continuous:
            continue
        for b in (budgets if m.budget_dependent else [float(target_ms)]):
            for g in ((False, True) if m.budget_dependent and governor else (False,)):
                specs.append(RunSpec(m, b, g))
    if repeats < 1:
        raise ValueError(f"repeats must be at least 1, got {repeats!r}")
    return [RunSpec(sp.method, sp.target_ms, sp.governor, r) for r in range(repeats) for sp in specs]


def eval_tour(index) -> str | None:
    """The tour an evaluation runs over by default: the scene's own where it came with one (the auditorium's
    A → B → C, the demo's flight), else its ``walk`` where it has one — a walkthrough evaluated from an orbit
    measures the wrong thing — else its default tour (None: it has none)."""
    from server.scene.tour import default_tour_name, named_tours

    tours = named_tours(index)
    default = default_tour_name(index)
    if default in tours and tours[default]["kind"] == "scene":
        return default
    return "walk" if "walk" in tours else default


def tour_of(store: str | Path, name: str | None = None) -> tuple[list[dict], dict[str, float], float]:
    """The keys of the store's tour ``name`` (None: its default tour), its named viewpoints (tour times, e.g.
    F&S's A, B, C: the default tour's) and its length (s); KeyError naming the tours there are for a name the
    store lacks."""
    from server.scene.store import SceneStore
    from server.scene.tour import default_tour_name, tour_for

    with SceneStore.open(store) as s:
        keys = [dict(k) for k in tour_for(s.index, name)[0]]
        default = name is None or name == default_tour_name(s.index)
        viewpoints = {str(k): float(v) for k, v in (s.index.meta.get("viewpoints") or {}).items()} if default else {}
    length = max((float(k["t"]) for k in keys), default=0.0)
    return keys, viewpoints, length


def derive_viewpoints(store: str | Path, duration: float, warmup: float, *, viewport=(640, 360), fov_y: float = 60.0,
                      missing: Sequence[str] = ("A", "C"), keys: Sequence[dict] | None = None
                      ) -> dict[str, tuple[float, str]]:
    """Stand-ins for F&S's viewpoints on a scene that names none: {label: (tour time, why)}.

    A (many large, complex objects): the tour time with the most objects in view; C (sudden complexity):
    the time whose next second adds the most objects to the view. Sampled every 0.5 s between the warm-up
    and the run's end, along ``keys`` (default: the store's tour).
    """
    if not missing:
        return {}
    from bench.scenarios.paths import visible_counts
    from proto.tour import Tour
    from server.scene.store import SceneStore

    with SceneStore.open(store) as s:
        index = s.index
        keys = list(index.tour) if keys is None else list(keys)
        if not keys:
            return {}
        tour = Tour(keys)
        ts = np.arange(warmup + 0.5, max(duration - 0.5, warmup + 0.5) + 1e-9, 0.5)
        counts = visible_counts(index, tour.pose_at(ts), fov_y, tuple(viewport))
    out: dict[str, tuple[float, str]] = {}
    if "A" in missing and counts.size:
        i = int(np.argmax(counts))
        out["A"] = (float(ts[i]), f"most objects in view ({int(counts[i])})")
    if "C" in missing and counts.size > 2:
        rise = counts[2:] - counts[:-2]
        i = int(np.argmax(rise))
        out["C"] = (float(ts[i + 2]), f"steepest rise in objects in view (+{int(rise[i])} in 1 s)")
    return out


# ---------------------------------------------------------------- one run




def _frames_dict(frames) -> dict[str, list]:
    """``ClientRun.frames`` as the schema's column lists (plain Python numbers)."""
    return {
        "t": [float(f.t) for f in frames],
        "time_ms": [float(f.time) * 1e3 for f in frames],
        "compute_ms": [float(f.compute) * 1e3 for f in frames],
        "triangles": [int(f.triangles) for f in frames],
        "reps": [int(f.draws) for f in frames],
        "bytes": [int(f.bytes) for f in frames],
        "morphs": [int(f.morphs) for f in frames],
        "predicted_ms": [float(f.predicted_cost) * 1e3 for f in frames],
        "seq": [int(f.seq) for f in frames],
        # The governor's own view of each frame (0 and False without one): whether a stretch under the target
        # was held by its aim (bound) or had nothing finer left to draw.
        "governor_predicted_ms": [float(f.governor_predicted) * 1e3 for f in frames],
        "governor_bound": [bool(f.governor_bound) for f in frames],
        # What set the aim: the share of the target steered to, and the quantile of the measured scatter behind it.
        "governor_aim": [round(float(f.governor_aim), 4) for f in frames],
        "governor_quantile": [round(float(f.governor_quantile), 4) for f in frames],
    }


def _stat(values: np.ndarray, fn) -> float | None:
    return float(fn(values)) if values.size else None


def summarize_frames(frames: Mapping[str, Sequence], warmup: float = WARMUP_S,
                     target_ms: float | None = None) -> dict[str, Any]:
    """Table 1's figures over the frames after ``warmup`` s that draw a selection (``seq`` ≥ 0).

    Frame time: mean, max, std (population, as F&S's σ), p95 and p99 (linear interpolation), and with
    ``target_ms`` the share of frames over 1.10 × target in per cent (``over_pct``: F&S's max is one frame
    of thousands, which on a shared machine is its noise; this says how often the target broke). Compute: the
    server's selection time, each selection counted once (at the first frame that draws it) — a selection
    runs every τ, not every frame, so averaging it over frames would weight it by the frames it lasted.
    Triangles and drawn representations: means per frame; bytes: the deltas applied after the warm-up.
    Figures of an empty set are None.
    """
    t = np.asarray(frames["t"], np.float64)
    seq = np.asarray(frames.get("seq", np.zeros(t.size)), np.int64)
    keep = (t >= warmup) & (seq >= 0)
    ms = np.asarray(frames["time_ms"], np.float64)[keep]
    new = np.ones(t.size, bool)
    new[1:] = seq[1:] != seq[:-1]
    compute = np.asarray(frames["compute_ms"], np.float64)[keep & new]
    return {
        "frames": int(keep.sum()),
        "selections": int(compute.size),
        "compute_mean_ms": _stat(compute, np.mean),
        "compute_max_ms": _stat(compute, np.max),
        "frame_mean_ms": _stat(ms, np.mean),
        "frame_max_ms": _stat(ms, np.max),
        "frame_std_ms": _stat(ms, np.std),
        "frame_p95_ms": _stat(ms, lambda v: np.percentile(v, 95)),
        "frame_p99_ms": _stat(ms, lambda v: np.percentile(v, 99)),
        "over_pct": None if target_ms is None else _stat(ms, lambda v: 100.0 * np.mean(v > OVER_RATIO * target_ms)),
        "triangles_mean": _stat(np.asarray(frames["triangles"], np.float64)[keep], np.mean),
        "reps_mean": _stat(np.asarray(frames["reps"], np.float64)[keep], np.mean),
        "bytes_total": int(np.asarray(frames["bytes"], np.int64)[t >= warmup].sum()),
    }


_QUALITY_KEYS = ("flip_mean", "psnr_mean", "ssim_mean", "popping_mean")


def run_one(
    server_url: str,
    scene: str,
    spec: RunSpec,
    *,
    duration: float,
    viewport: tuple[int, int] = (640, 360),
    fov_y: float = 60.0,
    tour: Sequence[dict] | None = None,
    on_frame: Callable | None = None,
    warmup: float = WARMUP_S,
    max_fps: float | None = MAX_FPS,
    algorithms: Sequence[str] = ALGORITHMS,
    calibrate: bool = True,
    calibration_cores: Sequence[int] | None = None,
    plan: bool = False,
    tour_name: str | None = None,
) -> tuple[dict, list]:
    """One fresh session of ``spec`` over the tour (the server's — its ``tour_name`` one, or its default —
    or ``tour``); returns (run dict, traces).

    The run dict has the schema's method, target_ms, solver, predict, morph, frames (every frame, the
    warm-up included, plus ``seq``: the selection drawn, −1 before the first), an empty quality and a
    summary (``summarize_frames`` plus errors, late, deltas and bytes_received; image figures None until
    measured), governor and repeat, and (``calibrate``) the calibration workload's times beside the run
    ({"t", "ms"}, ``bench.machine.Calibration``). ``traces`` are the client's ``FrameTrace`` per frame, aligned with the frames.
    """
    import contextlib

    from bench.machine import Calibration
    from client.app import run_client

    if not duration > 0:
        raise ValueError(f"duration must be positive, got {duration!r}")
    m = spec.method
    with (Calibration(cores=calibration_cores) if calibrate else contextlib.nullcontext()) as calib:
        run = run_client(
            server_url, scene, duration=duration, viewport=tuple(viewport), fov_y=fov_y,
            target_frame_time=spec.target_ms / 1e3, solver=m.solver, predict=m.predict, morph=m.morph, trace=True,
            tour=tour, on_frame=on_frame, max_fps=max_fps, algorithms=tuple(algorithms), governor=spec.governor,
            plan=plan, tour_name=tour_name,
        )
    frames = _frames_dict(run.frames)
    summary = summarize_frames(frames, warmup, spec.target_ms)
    summary.update({k: None for k in _QUALITY_KEYS})
    summary.update(errors=len(run.errors), late=int(run.late), deltas=int(run.deltas_received),
                   bytes_received=int(run.bytes_received), unmorphed=int(run.unmorphed))
    calibration = calib.samples() if calib is not None else {"t": [], "ms": []}
    summary["calibration_median_ms"] = float(np.median(calibration["ms"])) if calibration["ms"] else None
    result = {
        "method": m.name, "target_ms": float(spec.target_ms), "solver": m.solver, "predict": m.predict,
        "morph": m.morph, "governor": bool(spec.governor), "repeat": int(spec.repeat),
        "budget_dependent": bool(m.budget_dependent), "frames": frames, "calibration": calibration,
        "quality": {k: [] for k in ("t", "frame", "flip", "psnr", "ssim", "popping")},
        "summary": summary,
        "error_codes": sorted({e.code for e in run.errors}),
    }
    return result, list(run.trace)


# ---------------------------------------------------------------- the evaluation


def _nearest(traces: list, at_t: float):
    if not traces:
        return None
    t = np.array([tr.t for tr in traces])
    return traces[int(np.argmin(np.abs(t - at_t)))]


def evaluate(
    store: str | Path,
    *,
    scene: str | None = None,
    methods: Iterable[str | Method] | None = None,
    target_ms: float = 50.0,
    budgets_ms: Iterable[float] | None = None,
    duration: float | None = None,
    viewport: tuple[int, int] = (640, 360),
    fov_y: float = 60.0,
    tau: float = 0.5,
    seed: int = 0,
    warmup: float = WARMUP_S,
    quality: bool = True,
    every: int = 10,
    out: str | Path | None = None,
    progress: Progress | None = None,
    max_fps: float | None = MAX_FPS,
    samples: int | None = 24,
    workers: int | None = None,
    repeats: int = REPEATS,
    governor: bool = True,
    algorithms: Sequence[str] = ALGORITHMS,
    pin: bool = True,
    tour: str | None = None,
) -> dict:
    """Run every method over ``store``'s tour on one real server; the schema's results dict.

    ``tour`` names the store's tour the runs follow (default: ``eval_tour``'s choice); ValueError naming the
    tours there are if the store has none of that name.

    ``duration`` defaults to the tour's length, at most ``MAX_DURATION_S``; ``budgets_ms`` to 0.5×, 1× and
    2× ``target_ms`` (the target is always among them). ``progress(stage, done, total)`` follows the stages
    "runs" and "quality". With ``quality`` the traces are replayed afterwards (one ``bench.replay.Replayer``)
    for image error and popping, every ``every``-th frame after the warm-up but at most ``samples`` frames a
    run (spread over it; None: no cap), in ``workers`` processes (default: one per CPU), and with ``out`` the false-colour
    level images at viewpoints A and C of the runs at ``target_ms`` go to ``out/images``. Each run's traces
    wait on disk (a temporary folder), not in memory, and are dropped once measured. The run order is
    fixed; ``seed`` is recorded and handed to the quality sampling where it takes one. ``repeats``,
    ``governor`` and ``algorithms`` as ``plan`` and the module docstring say; ``pin`` puts server and
    client on different cores (``bench.machine.split_cores``) and restores this process's cores after.
    """
    from bench.demo import ServerProcess
    from server.scene.store import SceneStore

    store = Path(store)
    tick = progress or _noop
    if not 0.05 <= tau <= 10:
        raise ValueError(f"τ must lie in [0.05, 10] s, got {tau!r}")
    if every < 1:
        raise ValueError(f"every must be at least 1, got {every!r}")
    if warmup < 0:
        raise ValueError(f"warmup must be non-negative, got {warmup!r}")
    with SceneStore.open(store) as s:
        scene = scene or s.index.name
        tour = eval_tour(s.index) if tour is None else tour
    chosen = _methods(methods)
    continuous = scene_has_continuous(store)
    budgets = _budgets(target_ms, budgets_ms)
    specs = plan(chosen, target_ms, budgets, continuous=continuous, repeats=repeats, governor=governor)
    try:
        keys, viewpoints, length = tour_of(store, tour)
    except KeyError as exc:
        raise ValueError(exc.args[0]) from None
    if duration is None:
        if length <= 0:
            raise ValueError(f"{store}: the store has no tour to run over; give a duration")
        duration = min(length, MAX_DURATION_S)
    if not duration > warmup:
        raise ValueError(f"the duration ({duration} s) must exceed the warm-up ({warmup} s)")
    results: dict[str, Any] = {
        "scene": scene, "store": str(store.resolve()), "target_ms": float(target_ms), "budgets_ms": budgets,
        "viewport": [int(v) for v in viewport], "fov_y": float(fov_y), "tau_s": float(tau), "seed": int(seed),
        "tour": tour, "duration_s": float(duration), "warmup_s": float(warmup), "every": int(every), "samples": samples,
        "viewpoints": {k: v for k, v in viewpoints.items() if v <= duration},
        "methods": [m.name for m in chosen if not (m.continuous_only and not continuous)],
        "skipped": skipped_methods(chosen, continuous),
        "max_fps": max_fps, "repeats": int(repeats), "governor": bool(governor),
        "algorithms": [str(a) for a in algorithms], "cores": {},
        "runs": [], "images": {},
    }
    derived = derive_viewpoints(store, duration, warmup, viewport=viewport, fov_y=fov_y,
                                missing=[k for k in ("A", "C") if k not in results["viewpoints"]], keys=keys)
    if derived:
        results["viewpoints"].update({k: t for k, (t, _) in derived.items()})
        results["viewpoints_derived"] = {k: why for k, (_, why) in derived.items()}
    at_views = {k: v for k, v in results["viewpoints"].items() if k in ("A", "C")}
    with tempfile.TemporaryDirectory(prefix="walkstream-eval-") as spill:
        spilled: list[Path] = []
        near: dict[str, dict[str, Any]] = {k: {} for k in at_views}  # viewpoint → method → its nearest trace
        mine = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
        with ServerProcess([store], extra=["--tau", str(tau)]) as server:
            from bench.machine import split_cores

            results["cores"] = split_cores(server.proc.pid) if pin else {}
            tick("runs", 0, len(specs))
            try:
                for i, spec in enumerate(specs):
                    run, traces = run_one(server.url, scene, spec, duration=duration, viewport=viewport,
                                          fov_y=fov_y, warmup=warmup, max_fps=max_fps, algorithms=algorithms,
                                          calibration_cores=results["cores"].get("server"), tour_name=tour)
                    results["runs"].append(run)
                    _spill(results, spec, traces, i, spill, spilled, near, at_views, quality, target_ms)
                    del traces
                    tick("runs", i + 1, len(specs))
            finally:
                if mine is not None and results["cores"]:
                    os.sched_setaffinity(0, mine)
        if quality:
            _measure_quality(results, spilled, near, store, viewport, fov_y, every, warmup, seed,
                             None if out is None else Path(out), tick, samples=samples, workers=workers)
    return jsonable(results)


def _spill(results, spec, traces, i, spill, spilled, near, at_views, quality, target_ms) -> None:
    """Keep a run's traces on disk for the quality pass, and the first repeat's nearest traces to A and C
    (the governor's runs aside: the level images show each method's plan)."""
    if not quality:
        return
    if spec.target_ms == float(target_ms) and spec.repeat == 0 and not spec.governor:
        for k, t in at_views.items():
            near[k][spec.method.name] = _nearest(traces, t)
    path = Path(spill) / f"run{i:03d}.pickle"
    with open(path, "wb") as f:
        pickle.dump(traces, f, protocol=pickle.HIGHEST_PROTOCOL)
    spilled.append(path)


def _measure_quality(results: dict, spilled: list[Path], near: dict, store: Path, viewport, fov_y: float,
                     every: int, warmup: float, seed: int, out: Path | None, tick: Progress,
                     samples: int | None = None, workers: int | None = None) -> None:
    """Replay each run's traces for image error, a run per worker process; then the false-colour images.

    The runs are over by now, so the replay may use every core: each worker is a fresh (spawned) process
    with its own EGL context and ``Replayer`` — GL state does not survive a fork.
    """
    import concurrent.futures as cf
    import multiprocessing as mp

    from bench import quality as q
    from bench.replay import Replayer

    runs = results["runs"]
    tick("quality", 0, len(runs))
    workers = max(1, min(workers or os.cpu_count() or 1, len(runs)))
    jobs = [(str(store), tuple(viewport), fov_y, str(path), every, warmup, samples, seed) for path in spilled]
    measured: list[dict | None] = [None] * len(runs)
    with cf.ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn")) as pool:
        futures = {pool.submit(_quality_job, *job): i for i, job in enumerate(jobs)}
        for done, fut in enumerate(cf.as_completed(futures), start=1):
            measured[futures[fut]] = fut.result()
            tick("quality", done, len(runs))
    for run, m in zip(runs, measured):
        run["quality"] = jsonable({k: list(m.get(k, [])) for k in ("t", "frame", "flip", "psnr", "ssim", "popping")})
        run["summary"].update(jsonable(q.summary(m)))
    if out is not None and near:
        images = out / "images"
        images.mkdir(parents=True, exist_ok=True)
        with Replayer(store, viewport=tuple(viewport), fov_y=fov_y) as replayer:
            for label, by_method in near.items():
                traced = {m: [tr] for m, tr in by_method.items() if tr is not None}
                if not traced:
                    continue
                files = q.false_colour_images(replayer, traced, results["viewpoints"][label], images, label)
                results["images"][label] = {m: f"images/{Path(p).name}" for m, p in files.items()}


def _quality_job(store: str, viewport: tuple, fov_y: float, spilled: str, every: int, warmup: float,
                 samples: int | None, seed: int) -> dict:
    """One run's image error (in a worker process): load its spilled traces, replay, measure, delete them."""
    from bench import quality as q
    from bench.replay import Replayer

    with open(spilled, "rb") as f:
        traces = pickle.load(f)
    Path(spilled).unlink()
    with Replayer(store, viewport=viewport, fov_y=fov_y) as replayer:
        return q.measure(replayer, traces, every=every, warmup=warmup, samples=samples, seed=seed)



# ---------------------------------------------------------------- printing


def table_rows(results: Mapping[str, Any], target_ms: float | None = None) -> list[dict]:
    """One row per method at ``target_ms`` (default the headline target), in ``METHODS`` order, a method's
    run with the governor after it ("+gov"); each the median of its repeats by mean frame time (as
    ``bench.report.results.run_at`` picks it)."""
    target = float(results["target_ms"] if target_ms is None else target_ms)
    order = {name: i for i, name in enumerate(METHODS)}
    groups: dict[tuple[str, bool], list] = {}
    for r in results["runs"]:
        free = not r.get("budget_dependent", METHODS.get(r["method"], METHODS["none"]).budget_dependent)
        if free or float(r["target_ms"]) == target:
            groups.setdefault((r["method"], bool(r.get("governor", False))), []).append(r)
    rows = []
    for (method, governor), runs in sorted(groups.items(), key=lambda kv: (order.get(kv[0][0], len(order)), kv[0][1])):
        runs = sorted(runs, key=lambda r: (r["summary"].get("frame_mean_ms") is None,
                                           r["summary"].get("frame_mean_ms") or 0.0))
        median = runs[(len(runs) - 1) // 2]
        rows.append({"method": f"{method}+gov" if governor else method, "target_ms": target, **median["summary"]})
    return rows


def _fmt(v, digits: int = 1) -> str:
    if v is None:
        return "–"
    if isinstance(v, float) and not math.isfinite(v):
        return "∞" if v > 0 else "–"
    if isinstance(v, int):
        return f"{v:,d}"
    return f"{v:,.{digits}f}"


def print_table(results: Mapping[str, Any], console=None) -> None:
    """F&S Table 1 at the target as a rich table (ms), with p95, triangles and the image figures."""
    from rich.console import Console
    from rich.table import Table

    console = console or Console(stderr=True)
    target = float(results["target_ms"])
    table = Table(title=f"{results['scene']}: methods at {target:g} ms ({results['duration_s']:g} s tour, "
                        f"after {results['warmup_s']:g} s warm-up)")
    cols = [("method", "left"), ("compute mean", "right"), ("compute max", "right"), ("frame mean", "right"),
            ("frame max", "right"), ("frame std", "right"), ("frame p95", "right"), ("triangles", "right"),
            ("FLIP", "right"), ("PSNR", "right"), ("SSIM", "right"), ("popping", "right"), ("frames", "right")]
    for name, just in cols:
        table.add_column(name, justify=just)
    for r in table_rows(results):
        table.add_row(
            r["method"], _fmt(r["compute_mean_ms"], 2), _fmt(r["compute_max_ms"], 2), _fmt(r["frame_mean_ms"]),
            _fmt(r["frame_max_ms"]), _fmt(r["frame_std_ms"]), _fmt(r["frame_p95_ms"]),
            _fmt(None if r["triangles_mean"] is None else int(round(r["triangles_mean"]))),
            _fmt(r.get("flip_mean"), 3), _fmt(r.get("psnr_mean"), 1), _fmt(r.get("ssim_mean"), 3),
            _fmt(r.get("popping_mean"), 2), _fmt(r["frames"]),
        )
    console.print(table)
    for name, why in (results.get("skipped") or {}).items():
        console.print(f"skipped {name}: {why}")
