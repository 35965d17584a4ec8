"""The benchmarks' and evaluations' commands: ``walkstream demo``, ``loadtest``, ``eval`` and ``bench ...``.

The root ``walkstream`` app (``walkstream/cli.py``) registers them beside the server's and the
client's commands. Each imports what it needs when it runs, so ``--help`` is instant.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from bench.methods import METHODS
from server.cli import SOLVER_HELP, check_solver, progress_bar

bench_app = typer.Typer(no_args_is_help=True, help="Benchmarks: each prints its figures; --json for machines.")


@bench_app.command("build")
def bench_build(
    scenes: list[str] = typer.Option(["auditorium", "denhaag", "sthelens", "megacity"], "--scene",
                                     help="named scenes to build (repeat the option)"),
    size: Optional[int] = typer.Option(None, help="scale every scene to this size (buildings/trees)"),
    workers: Optional[int] = typer.Option(None, help="worker processes (default: one per CPU)"),
    keep: Optional[Path] = typer.Option(None, help="keep the stores in this folder (default: a temporary one)"),
    as_json: bool = typer.Option(False, "--json", help="end with one JSON line of figures"),
) -> None:
    """Build scenes and report triangles built per second, store size and index load time."""
    from bench.build import run_build_bench

    bar, tick = progress_bar("bench build", quiet=as_json)
    with bar:
        result = run_build_bench(scenes, size=size, workers=workers, keep=keep, progress=tick)
    for line in result["lines"]:  # to stderr under --json, so stdout stays one JSON line
        typer.echo(line, err=as_json)
    if as_json:
        print(json.dumps({k: v for k, v in result.items() if k != "lines"}))


@bench_app.command("select")
def bench_select(
    sizes: str = typer.Option("1000,10000,100000,1000000", help="objects per generated instance, comma-separated"),
    levels: int = typer.Option(4, help="levels of detail per object (×4 faces per level)"),
    repeats: int = typer.Option(7, help="timed runs per figure (the median is reported), after one warm-up"),
    seed: int = typer.Option(0, help="random seed of the generated instances"),
    exact_max: int = typer.Option(1000, help="largest size solved exactly by the MIP (HiGHS)"),
    reference_max: int = typer.Option(100_000, help="largest size timed with the plain-Python reference greedy"),
    as_json: bool = typer.Option(False, "--json", help="end with one JSON line of figures"),
) -> None:
    """Time the greedy from scratch and the incremental solver's coherent step; check optimality and goals."""
    from bench.select import run

    try:
        parsed = [int(s.replace("_", "")) for s in sizes.split(",") if s.strip()]
    except ValueError:
        raise typer.BadParameter(f"expected comma-separated integers, got {sizes!r}", param_hint="--sizes") from None
    if not parsed or min(parsed) < 1:
        raise typer.BadParameter("sizes must be positive integers", param_hint="--sizes")
    if levels < 1 or repeats < 1:
        raise typer.BadParameter("must be at least 1", param_hint="--levels/--repeats")
    bar, tick = progress_bar("bench select", quiet=as_json)
    with bar:
        result = run(parsed, levels=levels, repeats=repeats, seed=seed, progress=tick, exact_max=exact_max,
                     reference_max=reference_max)
    for line in result["lines"]:  # to stderr under --json, so the JSON stays the last line of stdout
        typer.echo(line, err=as_json)
    if as_json:
        print(json.dumps({k: v for k, v in result.items() if k != "lines"}))


@bench_app.command("predict")
def bench_predict(
    stores: Optional[list[Path]] = typer.Option(None, "--store", help="scene stores whose tours to predict "
                                                "(default: the demo and Den Haag stores, built if missing)"),
    rate: float = typer.Option(20.0, help="camera samples per second, as a client sends them"),
    jitter: float = typer.Option(0.0, help="Gaussian noise on each sampled eye, metres (0.5° on the direction)"),
    pairs: int = typer.Option(40, help="level pairs rendered to compare vertex correspondences (0: skip)"),
    city: Optional[Path] = typer.Option(None, help="the city store the correspondences are rendered on "
                                        "(default: Den Haag, built if missing)"),
    size: Optional[int] = typer.Option(None, help="scale of the default Den Haag store (trees; default: full)"),
    seed: int = typer.Option(0, help="random seed (jitter, pair sampling)"),
    kiosk: bool = typer.Option(True, help="compare tour-aware with linear prediction on a kiosk tour"),
    kiosk_store: Optional[Path] = typer.Option(None, help="the store the kiosk tour walks (default: the "
                                               "auditorium, built if missing)"),
    kiosk_seconds: float = typer.Option(6.0, help="seconds of the kiosk tour the image error is measured over "
                                        "(two real client runs; 0: skip the image error)"),
    kiosk_viewport: str = typer.Option("320x180", help="viewport of the kiosk image-error runs, WxH"),
    as_json: bool = typer.Option(False, "--json", help="end with one JSON line of figures"),
) -> None:
    """Prediction error against horizon on the scenes' tours (against holding the last pose),
    nearest-vertex against collapse-map geomorph correspondences rendered by the real client, and on a
    kiosk tour the prediction and image error of tour-aware against linear prediction."""
    from bench.correspondence import measure
    from bench.stores import build_demo, cached_auditorium, cached_denhaag, demo_store
    from bench.predict import run, tours_from_stores

    if rate <= 0 or jitter < 0 or pairs < 0:
        raise typer.BadParameter("rate must be positive, jitter and pairs non-negative")
    if kiosk_seconds < 0 or (0 < kiosk_seconds <= 2.0):
        raise typer.BadParameter("must be 0 (skip) or more than the 2 s warm-up", param_hint="--kiosk-seconds")
    try:
        viewport = tuple(int(v) for v in kiosk_viewport.lower().split("x"))
        if len(viewport) != 2 or min(viewport) < 16:
            raise ValueError
    except ValueError:
        raise typer.BadParameter(f"expected WxH of at least 16x16, got {kiosk_viewport!r}",
                                 param_hint="--kiosk-viewport") from None
    if kiosk_store is not None and not kiosk_store.exists():
        raise typer.BadParameter(f"no such store: {kiosk_store}", param_hint="--kiosk-store")
    for path in stores or []:
        if not path.exists():
            raise typer.BadParameter(f"no such store: {path}", param_hint="--store")
    if city is not None and not city.exists():
        raise typer.BadParameter(f"no such store: {city}", param_hint="--city")
    if city is None and (pairs or not stores):
        city = cached_denhaag(size=size, seed=0, quiet=as_json)
    if not stores:
        demo = demo_store(576, 0)
        if not demo.exists():
            build_demo(demo, 576, 0, quiet=as_json)
        stores = [demo, city]
    bar, tick = progress_bar("bench predict", quiet=as_json)
    with bar:
        prediction = run(tours_from_stores(stores), rate=rate, jitter=jitter, seed=seed, progress=tick)
        morph = measure(city, pairs=pairs, seed=seed, progress=tick) if pairs else None
        walk = None
        if kiosk:
            from bench.kiosk import image_kiosk, kiosk_tour, predict_kiosk
            from server.scene.store import SceneStore

            kiosk_store = kiosk_store or cached_auditorium(as_json)
            with SceneStore.open(kiosk_store) as store:
                grid = store.walkable()
            keys = kiosk_tour(grid, seed=seed)
            walk = {"predict": predict_kiosk(keys, grid, rate=rate, progress=tick)}
            if kiosk_seconds:
                walk["image"] = image_kiosk(kiosk_store, keys, duration=kiosk_seconds, viewport=viewport,
                                            progress=tick)
    lines = ["Prediction error against horizon (linear prediction vs holding the last pose):", *prediction["lines"]]
    if morph is not None:
        lines += ["", f"Geomorph correspondences on {city.name} (half-way morph vs the blend of its end states):",
                  *morph["lines"]]
    for part in (walk or {}).values():
        lines += ["", *part["lines"]]
    for line in lines:  # to stderr under --json, so the JSON stays the last line of stdout
        typer.echo(line, err=as_json)
    if as_json:
        out = {"prediction": {k: v for k, v in prediction.items() if k != "lines"}}
        if morph is not None:
            out["correspondence"] = {k: v for k, v in morph.items() if k != "lines"}
        if walk is not None:
            out["kiosk"] = {name: {k: v for k, v in part.items() if k != "lines"} for name, part in walk.items()}
        print(json.dumps(out))



@bench_app.command("render")
def bench_render(
    store: Optional[Path] = typer.Option(None, help="the store whose tour measures the cost model "
                                         "(default: the auditorium, built if missing)"),
    duration: float = typer.Option(20.0, help="seconds of the tour the cost model is measured over"),
    quick: bool = typer.Option(False, help="fewer sizes and repeats, and no 10k-representation row"),
    no_tour: bool = typer.Option(False, "--no-tour", help="skip the cost-model measurement (no server)"),
    as_json: bool = typer.Option(False, "--json", help="end with one JSON line of figures"),
) -> None:
    """Frame time against triangles, client CPU per frame against drawn representations, and the online
    cost model's held-out error over the auditorium tour (each against a reference measured in the same run)."""
    from bench.render import run as run_render
    from bench.stores import cached_auditorium

    if duration <= 2.5:
        raise typer.BadParameter("the tour needs more than the 2 s warm-up", param_hint="--duration")
    if store is not None and not store.exists():
        raise typer.BadParameter(f"no such store: {store}", param_hint="--store")
    if store is None and not no_tour:
        store = cached_auditorium(as_json)
    bar, tick = progress_bar("bench render", quiet=as_json)
    with bar:
        result = run_render(None if no_tour else store, duration=duration, quick=quick, progress=tick)
    for line in result["lines"]:
        typer.echo(line, err=as_json)
    if as_json:
        print(json.dumps({k: v for k, v in result.items() if k != "lines"}))


@bench_app.command("benefit")
def bench_benefit(
    stores: Optional[list[Path]] = typer.Option(None, "--store", help="scene stores to measure "
                                                 "(default: the auditorium and the cached Den Haag store)"),
    objects: int = typer.Option(8, min=1, help="objects per scene, each drawn at every level from 15 views"),
    as_json: bool = typer.Option(False, "--json", help="end with one JSON line of figures"),
) -> None:
    """How well each accuracy model (F&S, Zach, screen-space error) ranks and predicts the image error
    (FLIP against the finest level) the real renderer draws; picks the simplest within 10 % of the best."""
    from bench.benefit import run as run_benefit

    stores = _city_stores(stores, as_json, auditorium_first=True)
    bar, tick = progress_bar("bench benefit", quiet=as_json)
    with bar:
        result = run_benefit(list(stores), objects=objects, progress=tick)
    for line in result["lines"]:
        typer.echo(line, err=as_json)
    if as_json:
        print(json.dumps({k: v for k, v in result.items() if k != "lines"}))


def _city_stores(stores: Optional[list[Path]], quiet: bool, *, auditorium_first: bool) -> list[Path]:
    """The ``--store`` s given, each checked to exist, else the cached auditorium and Den Haag stores."""
    if not stores:
        from bench.stores import cached_auditorium, cached_denhaag

        pair = [cached_auditorium(quiet), cached_denhaag(quiet=quiet)]
        return pair if auditorium_first else pair[::-1]
    for p in stores:
        if not p.exists():
            raise typer.BadParameter(f"no such store: {p}", param_hint="--store")
    return list(stores)


@bench_app.command("encoding")
def bench_encoding(
    stores: Optional[list[Path]] = typer.Option(None, "--store", help="scene stores to measure "
                                                 "(default: the cached Den Haag store and the auditorium)"),
    keys: int = typer.Option(30, help="tour keys a session is driven over for the on-the-wire figure"),
    as_json: bool = typer.Option(False, "--json", help="end with one JSON line of figures"),
) -> None:
    """Payload and on-the-wire bytes against raw float32 (goal ≤ 40 %), with zstd of the raw arrays as the
    reference measured in the same run."""
    from bench.encoding import run as run_encoding

    stores = _city_stores(stores, as_json, auditorium_first=False)
    bar, tick = progress_bar("bench encoding", quiet=as_json)
    with bar:
        result = run_encoding(list(stores), progress=tick, keys=keys)
    for line in result["lines"]:
        typer.echo(line, err=as_json)
    if as_json:
        print(json.dumps({k: v for k, v in result.items() if k != "lines"}))


@bench_app.command("hostile")
def bench_hostile(
    store: Optional[Path] = typer.Option(None, "--store", help="scene store (default: the cached demo scene)"),
    seconds: float = typer.Option(16.0, min=2.0, help="seconds of the good client's run per attack (16: about 32 "
                                  "deltas at τ = 0.5 s, so one delta more or less at the run's edges is 3 %)"),
    attack: Optional[list[str]] = typer.Option(None, "--attack", help="run only these attacks (repeatable)"),
    as_json: bool = typer.Option(False, "--json", help="end with one JSON line of figures"),
) -> None:
    """A real replica, one good client and in turn each attack; the good client's deltas against its run
    without attack, on time, frame p95, the server's CPU and RSS, and whether a new client still connects."""
    from bench.hostile import ATTACKS, format_table, run
    from bench.stores import build_demo, demo_store

    for a in attack or []:
        if a not in ATTACKS:
            raise typer.BadParameter(f"unknown attack {a!r}; choose from {', '.join(ATTACKS)}", param_hint="--attack")
    if store is None:
        store = demo_store(24, 0)
        if not store.exists():
            build_demo(store, 24, 0, quiet=as_json)
    elif not store.exists():
        raise typer.BadParameter(f"no such store: {store}", param_hint="--store")
    result = run(store, seconds=seconds, attacks=attack or None, say=lambda s: typer.echo(s, err=True))
    for line in format_table(result):
        typer.echo(line, err=as_json)
    if as_json:
        print(json.dumps(result))
    if not result["passed"]:
        raise typer.Exit(1)


@bench_app.command("soak")
def bench_soak(
    duration: float = typer.Option(3600.0, min=60.0, help="seconds of soak (the README's figures: one hour; CI: 120)"),
    store: Optional[Path] = typer.Option(None, "--store", help="scene store (default: the cached demo scene)"),
    cut_every: Optional[float] = typer.Option(None, help="seconds between network cuts (default: 300, or a third of "
                                              "a run shorter than 15 minutes)"),
    cut_for: Optional[float] = typer.Option(None, help="seconds each cut lasts (default: 60, or a quarter of "
                                            "--cut-every when that is scaled)"),
    sample_every: float = typer.Option(10.0, min=1.0, help="seconds between samples of the kiosk"),
    seed: int = typer.Option(0, help="seed of the synthetic visitors"),
    out: Path = typer.Option(Path("soak"), help="folder for the kiosk's config, log, status and the chart"),
    as_json: bool = typer.Option(False, "--json", help="end with one JSON line: passed, each pass line, the chart"),
) -> None:
    """A headless kiosk on its attract loop with synthetic visitors, through network cuts and a server restart:
    RSS, threads, sockets, frames and deltas checked against the pass lines; a chart of the run."""
    from bench.soak import SoakPlan, run
    from bench.stores import build_demo, demo_store

    try:
        plan = SoakPlan.scaled(duration, sample_every)
        if cut_every is not None or cut_for is not None:
            every = cut_every if cut_every is not None else plan.cut_every
            plan = SoakPlan(duration=duration, cut_every=every,
                            cut_for=cut_for if cut_for is not None else min(plan.cut_for, every / 4.0),
                            sample_every=sample_every)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--duration/--cut-every/--cut-for") from None
    if store is None:
        store = demo_store(24, 0)
        if not store.exists():
            build_demo(store, 24, 0, quiet=as_json)
    elif not store.exists():
        raise typer.BadParameter(f"no such store: {store}", param_hint="--store")
    bar, tick = progress_bar("bench soak", quiet=as_json)
    with bar:
        result = run(store, plan, out, seed=seed, progress=tick)
    for name, line in result["lines"].items():
        mark = "PASS" if line["ok"] else "FAIL"
        typer.echo(f"{mark}  {name:<26} {line['figure']!s:>8}  (limit {line['limit']})", err=as_json)
    typer.echo(f"chart: {result['chart']}", err=as_json)
    if as_json:
        print(json.dumps({k: v for k, v in result.items() if k not in ("samples",)}))
    if not result["passed"]:
        raise typer.Exit(1)


def parse_hold(text: str):
    """``--hold`` as a ``client.hold.Hold``; a bad line is a one-line usage error naming it."""
    from client.hold import Hold

    try:
        return Hold.parse(text)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--hold") from None


def demo(
    duration: float = typer.Option(10.0, help="seconds of tour to run"),
    target_ms: float = typer.Option(50.0, help="target frame time in milliseconds"),
    width: int = typer.Option(640),
    height: int = typer.Option(360),
    store: Optional[Path] = typer.Option(None, help="scene store (default: the demo scene, built if missing)"),
    objects: int = typer.Option(576, help="demo scene size when it has to be built"),
    seed: int = typer.Option(0),
    out: Path = typer.Option(Path("walkstream-out"), help="folder for the chart"),
    as_json: bool = typer.Option(False, "--json", help="end with one JSON line of figures"),
    solver: str = typer.Option("greedy", help=SOLVER_HELP),
    governor: bool = typer.Option(True, "--governor/--no-governor",
                                  help="the client corrects each frame along the delta's ladder"),
    hold: str = typer.Option("p95:1.3", help="the line the governor holds, pNN:BOUND (NN % of frames within "
                             "BOUND × target): by default the demo's own line, 95 % within 1.3 ×; p99:1.1 is "
                             "the client's default"),
) -> None:
    """Build the demo scene if needed, serve it on loopback and run the headless client over its tour."""
    from rich.console import Console

    from bench.demo import per_second, run_demo
    from bench.stores import build_demo, demo_store
    from server.scene.store import SceneStore

    console = Console(stderr=as_json, soft_wrap=True)
    target = target_ms / 1e3
    if not 5 <= target_ms <= 1000:
        raise typer.BadParameter("must lie in [5, 1000]", param_hint="--target-ms")
    check_solver(solver)
    line = parse_hold(hold)
    path = store or demo_store(objects, seed)
    if not path.exists():
        if store is not None:
            raise typer.BadParameter(f"no such store: {path}", param_hint="--store")
        build_demo(path, objects, seed, quiet=False)
    with SceneStore.open(path) as s:
        scene = s.index.name

    on_frame = per_second(lambda text: console.print(text), target_ms)

    held = f", holding {line}" if governor else ""
    console.print(f"[bold]walkstream demo[/bold]: scene {scene!r} from {path}, {solver}, {duration:.0f} s at "
                  f"{target_ms:.0f} ms{held}")
    run, summary, chart = run_demo(
        path, scene=scene, duration=duration, target=target, viewport=(width, height), out=out, on_frame=on_frame,
        solver=solver, governor=governor, hold=line,
    )
    if summary.mean_ok and summary.p95_ok:
        verdict = "holds"
    elif summary.p95_ok and summary.mean_ms < target_ms:
        verdict = "under-used (frames faster than asked: the selection saw no benefit in more detail, or the cost model overestimates)"
    else:
        verdict = "MISSED"
    console.print(
        f"after {summary.warmup_s:.0f} s: {summary.frames} frames, mean {summary.mean_ms:.1f} ms, "
        f"p95 {summary.p95_ms:.1f} ms, max {summary.max_ms:.1f} ms against {target_ms:.0f} ms — budget {verdict}; "
        f"c_vertex {summary.cost_coeff * 1e9:.1f} ns; chart {chart}"
    )
    if as_json:
        print(json.dumps({**summary.as_dict(), "chart": str(chart), "scene": scene, "solver": run.welcome.solver,
                          "hold": str(line) if governor else None}))


EVAL_METHODS = ",".join(METHODS)


def _eval_tour(store: Path, name: str | None) -> str | None:
    """The tour ``walkstream eval`` runs over: ``name`` if the store has it (else a one-line error naming the
    tours it has), or ``bench.evaluate.eval_tour``'s choice."""
    from bench.evaluate import eval_tour
    from server.scene.store import SceneStore
    from server.scene.tour import named_tours

    with SceneStore.open(store) as s:
        if name is None:
            return eval_tour(s.index)
        tours = named_tours(s.index)
        if name not in tours:
            raise typer.BadParameter(f"the scene {s.index.name!r} has no tour {name!r}; its tours: "
                                     f"{', '.join(sorted(tours)) or 'none'}", param_hint="--tour")
    return name


def eval_(
    scene: str = typer.Argument(..., metavar="SCENE", help="a named scene (auditorium, denhaag, sthelens, demo, "
                                "megacity), a scene store (.db), or a CityJSON/glTF/OBJ/PLY/DEM/CityGML file "
                                "(built once with generated tours)"),
    out: Optional[Path] = typer.Option(None, help="report folder (default: walkstream-out/eval-SCENE)"),
    tour: Optional[str] = typer.Option(None, "--tour", help="the scene's tour to run over (walk, flyover, orbit, "
                                       "...: `walkstream inspect` lists them; default: the scene's own tour where "
                                       "it came with one, else its walk where it has one, else its default)"),
    target_ms: float = typer.Option(50.0, help="the target frame time of Table 1 and Figure 7 (ms)"),
    budgets: Optional[str] = typer.Option(None, help="target frame times to run, comma-separated ms "
                                          "(default: ½, 1 and 2 × the target)"),
    methods: str = typer.Option(EVAL_METHODS, help="methods to run, comma-separated"),
    duration: Optional[float] = typer.Option(None, help="seconds of tour per run (default: the whole tour, "
                                             "at most 90 s)"),
    width: int = typer.Option(640),
    height: int = typer.Option(360),
    tau: float = typer.Option(0.5, help="seconds between selections (τ) on the evaluation's server"),
    seed: int = typer.Option(0, help="scene seed (named scenes) and the quality sampling's seed"),
    every: int = typer.Option(10, help="measure image quality on every EVERY-th frame (and the frame before)"),
    samples: int = typer.Option(24, help="at most this many quality samples a run, spread over it (0: no cap)"),
    quality: bool = typer.Option(True, "--quality/--no-quality", help="measure FLIP, PSNR, SSIM and popping"),
    scenarios: bool = typer.Option(True, "--scenarios/--no-scenarios", help="run the failure scenarios"),
    scenario_method: str = typer.Option("predictive", help="the method the failure scenarios run"),
    scenario: Optional[list[str]] = typer.Option(None, "--scenario", help="run only these scenarios (repeat it; "
                                                 "spin, turn, oscillation, drift, below_coarsest, network)"),
    repeats: int = typer.Option(3, help="runs of each method and budget, interleaved (A B C A B C …); Table 1 "
                                "shows the median run and the spread"),
    governor: bool = typer.Option(True, "--governor/--no-governor", help="run each budget-dependent method "
                                  "also with the client's frame governor"),
    algorithm: str = typer.Option("lit", help="the rendering algorithm every method draws with (flat, lit, "
                                  "textured): the same rule for all"),
    pin: bool = typer.Option(True, "--pin/--no-pin", help="server and client on different cores (≥ 2 cores)"),
    as_json: bool = typer.Option(False, "--json", help="end with one JSON line: Table 1, the checks, the "
                                 "scenarios and the report's path"),
) -> None:
    """Every method over the scene's tour with the real server and client: Table 1, Figure 7, image error
    against frame time, false-colour views at A and C, and the scenarios where methods fail — as a report
    folder with an index.html."""
    from rich.console import Console

    from bench import evaluate as ev
    from bench.report.checks import checks
    from bench.report.folder import summary_lines, write_report
    from bench.report.table import table1
    from bench.stores import DEFAULT_CACHE, resolve_scene

    console = Console(stderr=as_json, soft_wrap=True)
    if not 5 <= target_ms <= 1000:
        raise typer.BadParameter("must lie in [5, 1000]", param_hint="--target-ms")
    try:
        budget_list = None if budgets is None else [float(b) for b in budgets.split(",") if b.strip()]
    except ValueError:
        raise typer.BadParameter(f"not a comma-separated list of numbers: {budgets!r}", param_hint="--budgets")
    if budget_list is not None and (not budget_list or any(not 1 <= b <= 2000 for b in budget_list)):
        raise typer.BadParameter("each budget must lie in [1, 2000] ms", param_hint="--budgets")
    names = [m.strip() for m in methods.split(",") if m.strip()]
    unknown = [m for m in names if m not in METHODS]
    if unknown or not names:
        raise typer.BadParameter(f"unknown method(s) {', '.join(unknown) or '(none given)'}; known: "
                                 f"{', '.join(METHODS)}", param_hint="--methods")
    if scenario_method not in METHODS:
        raise typer.BadParameter(f"unknown method {scenario_method!r}", param_hint="--scenario-method")
    if duration is not None and duration <= 3.0:
        raise typer.BadParameter("a run needs more than the 2 s warm-up", param_hint="--duration")
    if every < 1:
        raise typer.BadParameter("must be ≥ 1", param_hint="--every")
    if not 1 <= repeats <= 20:
        raise typer.BadParameter(f"must lie in [1, 20], got {repeats}", param_hint="--repeats")
    from proto.messages import ALGORITHMS

    if algorithm not in ALGORITHMS:
        raise typer.BadParameter(f"unknown algorithm {algorithm!r}; known: {', '.join(ALGORITHMS)}",
                                 param_hint="--algorithm")
    if samples < 0:
        raise typer.BadParameter("must be ≥ 0", param_hint="--samples")
    if scenario:
        from bench.scenarios.run import SCENARIOS

        bad = [n for n in scenario if n not in SCENARIOS]
        if bad:
            raise typer.BadParameter(f"unknown scenario(s) {', '.join(bad)}; known: {', '.join(SCENARIOS)}",
                                     param_hint="--scenario")
    bar, tick = progress_bar("eval", quiet=False)
    with bar:
        try:
            store, name = resolve_scene(scene, seed=seed, cache_dir=DEFAULT_CACHE, progress=tick)
        except (ValueError, FileNotFoundError) as exc:
            raise typer.BadParameter(str(exc), param_hint="SCENE")
        tour = _eval_tour(store, tour)
        folder = out or Path("walkstream-out") / f"eval-{name}"
        folder.mkdir(parents=True, exist_ok=True)
        results = ev.evaluate(store, scene=name, methods=names, target_ms=target_ms, budgets_ms=budget_list,
                              duration=duration, viewport=(width, height), tau=tau, seed=seed, quality=quality,
                              every=every, samples=samples or None, out=folder, progress=tick, repeats=repeats,
                              governor=governor, algorithms=(algorithm,), pin=pin, tour=tour)
        if scenarios:
            from bench.scenarios.run import run_scenarios

            results["scenarios"] = run_scenarios(store, name, target_ms=target_ms, method=scenario_method,
                                                 names=scenario or None, viewport=(width, height), tau=tau,
                                                 seed=seed, progress=tick, tour=tour)
    index = write_report(results, folder)
    for line in summary_lines(results):
        console.print(line, markup=False, highlight=False)
    for s in results.get("scenarios") or []:
        console.print(s["line"], markup=False, highlight=False)
    console.print(f"report: {index}")
    if as_json:
        print(json.dumps({
            "scene": name, "store": str(store), "report": str(index), "tour": tour, "target_ms": target_ms,
            "budgets_ms": results.get("budgets_ms"), "table1": table1(results),
            "checks": checks(results),
            "runs": [{"method": r["method"], "target_ms": r["target_ms"], "governor": r.get("governor", False),
                      "repeat": r.get("repeat", 0), **r["summary"]} for r in results["runs"]],
            "scenarios": [{k: v for k, v in s.items()} for s in results.get("scenarios") or []],
            "skipped": results.get("skipped", {}),
        }))
