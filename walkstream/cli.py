"""The ``walkstream`` command line: the root app, assembled from the commands of each part.

The server's commands (``build``, ``inspect``, ``serve``) live in ``server/cli.py`` and the
benchmarks and evaluations (``demo``, ``eval``, ``bench ...``) in ``bench/cli.py``, the load commands
(``loadtest``, ``bench sessions``) in ``bench/cli_load.py``.
The ``client`` command lives here: it checks the solver against the server's registry and
prints the demo's frame-time summary, and the client package imports only ``proto``.
Each command imports what it needs when it runs, so ``--help`` is instant.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path
from typing import Literal, Optional

import typer

from bench import cli as bench_cli
from bench import cli_load
from server import cli as server_cli
from server.cli import SOLVER_HELP, check_solver

#: sysexits' EX_CONFIG: a kiosk whose config is wrong exits with it (its systemd unit does not restart on it).
EX_CONFIG = 78

app = typer.Typer(
    add_completion=False,
    pretty_exceptions_enable=False,
    no_args_is_help=True,
    help="walkstream: streamed walkthroughs that hold the frame rate you ask for.",
)


def client(
    url: str = typer.Argument("ws://127.0.0.1:8765/ws", help="the server's websocket URL"),
    scene: str = typer.Option("demo", help="scene name"),
    duration: Optional[float] = typer.Option(None, help="seconds to run (default: 10; with --window, until "
                                             "the window is closed)"),
    target_ms: float = typer.Option(50.0, help="target frame time in milliseconds"),
    width: int = typer.Option(640),
    height: int = typer.Option(360),
    screenshot: Optional[Path] = typer.Option(None, help="write the last frame to this PNG"),
    solver: str = typer.Option("greedy", help=SOLVER_HELP),
    predict: bool = typer.Option(True, help="ask the server to select for the predicted camera path"),
    morph: bool = typer.Option(True, help="ask for geomorph schedules (off: levels switch at once)"),
    window: bool = typer.Option(False, "--window", help="show the frames in a window (needs a display; "
                                "xvfb-run for a virtual one). Keys: WASD move, Q/E down/up, drag looks, "
                                "Shift faster, Tab fly/walk, F false colour, P screenshot, Esc quits"),
    navigate: Literal["tour", "fly", "walk"] = typer.Option(
        "tour", help="who moves the camera: the scene's tour, or you flying or walking (needs --window)"),
    tour: Optional[str] = typer.Option(None, "--tour", help="follow the scene's tour of this name (walk, flyover, "
                                       "orbit, ...: `walkstream inspect` lists them; default: the scene's default "
                                       "tour)"),
    colour: Literal["data", "objects", "levels"] = typer.Option(
        "data", help="what surfaces are drawn in: the scene's colours (semantic surfaces, materials), a tint "
                     "per object, or a colour per drawn level with morphs striped"),
    false_colour: bool = typer.Option(False, "--false-colour", help="the same as --colour levels"),
    governor: bool = typer.Option(True, "--governor/--no-governor",
                                  help="correct the server's selection every frame along each delta's ladder "
                                       "(the frame governor; --no-governor draws the server's plan as it is)"),
    hold: str = typer.Option("p99:1.1", help="the line the governor holds: pNN:BOUND keeps NN % of frames within "
                             "BOUND × target (p99:1.1: at most 1 % over 1.1 ×; a looser line spends more of the "
                             "time asked for where frames scatter)"),
    reconnect_timeout: float = typer.Option(10.0, min=0.0, help="seconds to keep redialling a lost connection "
                                            "(resuming the session, nothing re-sent); 0: a loss ends the run"),
    record_tour: Optional[Path] = typer.Option(None, "--record-tour", help="with --window: M or Space marks the "
                                               "current pose as a tour stop; the stops are written here (TOML, or "
                                               "JSON for a .json name) on exit, as a kiosk tour's `file` reads them"),
) -> None:
    """Run the client over the scene's tour (headless, or in a window you can navigate) and print its frame times."""
    from client.app import run_client
    from client.connection import ClientError, check_url
    from client.window import WindowError

    check_solver(solver)
    try:
        check_url(url)
    except ClientError as exc:
        server_cli.fail(str(exc))
    if navigate != "tour" and not window:
        raise typer.BadParameter("fly and walk are driven by keys and mouse: add --window", param_hint="--navigate")
    if tour is not None:
        if navigate != "tour" or record_tour is not None:
            raise typer.BadParameter("a tour moves the camera itself: drop --navigate and --record-tour",
                                     param_hint="--tour")
        if not re.fullmatch(r"[A-Za-z0-9_.\-]{1,128}", tour):
            raise typer.BadParameter(f"{tour!r}: a tour's name is letters, digits, '_', '.' or '-'", param_hint="--tour")
    if record_tour is not None:
        if not window:
            raise typer.BadParameter("stops are marked with a key in the window: add --window",
                                     param_hint="--record-tour")
        if record_tour.is_dir() or not record_tour.parent.is_dir():
            server_cli.fail(f"--record-tour {str(record_tour)!r}: give a file name in an existing folder")
        if navigate == "tour":
            navigate = "fly"  # recording is flying to the stops and marking them
    if duration is None:
        duration = float("inf") if window else 10.0
    line = bench_cli.parse_hold(hold)
    try:
        run = run_client(
            url, scene, duration=duration, viewport=(width, height), target_frame_time=target_ms / 1e3,
            screenshot=screenshot, solver=solver, predict=predict, morph=morph, window=window, navigate=navigate,
            false_colour=false_colour or colour == "levels", colours="objects" if colour == "objects" else "data",
            reconnect_timeout=reconnect_timeout, governor=governor, hold=line, record_tour=record_tour,
            tour_name=tour,
        )
    except (WindowError, ClientError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    from bench.demo import summarize

    typer.echo(json.dumps({**summarize(run, target_ms / 1e3).as_dict(), "reconnects": len(run.reconnects),
                           "resent": run.resent, "close_reason": run.close_reason, "governor": run.governor}))


def kiosk(
    config: Optional[Path] = typer.Argument(None, help="the kiosk's config file (TOML); see --example"),
    example: bool = typer.Option(False, "--example", help="print a commented example config (the auditorium "
                                 "scene) and exit"),
    headless: bool = typer.Option(False, "--headless", help="render over EGL with no window (tests, the soak)"),
    duration: Optional[float] = typer.Option(None, min=0.0, help="seconds to run (default: until stopped)"),
    screenshot_every: Optional[float] = typer.Option(None, min=0.05, help="write what is shown every S seconds "
                                                     "(needs --screenshot-dir)"),
    screenshot_dir: Optional[Path] = typer.Option(None, help="where --screenshot-every writes its PNGs"),
    status_file: Optional[Path] = typer.Option(None, help="write what the kiosk is doing (frames, deltas, state, "
                                               "camera, cache) to this JSON file twice a second"),
    synthetic_visitors: Optional[int] = typer.Option(None, help="simulate visitors (taps, walks, leaving) from "
                                                     "this random seed: the soak's load"),
) -> None:
    """Run a museum kiosk: the attract loop of its tours, a visitor's walk on touch, back after the idle countdown."""
    if example:
        from client.kiosk.example import EXAMPLE

        typer.echo(EXAMPLE, nl=False)
        return
    if config is None:
        raise typer.BadParameter("give the config file (walkstream kiosk --example prints one)",
                                 param_hint="CONFIG")
    if (screenshot_every is None) != (screenshot_dir is None):
        raise typer.BadParameter("give --screenshot-every and --screenshot-dir together",
                                 param_hint="--screenshot-every")
    import logging
    import math

    from client.kiosk.config import ConfigError, load_config
    from client.kiosk.run import run_kiosk
    from client.renderer import RendererError
    from client.window import WindowError

    try:
        cfg = load_config(config)
    except ConfigError as exc:  # EX_CONFIG: the systemd unit does not restart a kiosk whose config is wrong
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(EX_CONFIG) from None
    from client.kiosk.unattended import StatusFile, SyntheticVisitors, UnattendedHooks, chain, exit_on_unexpected

    if not logging.getLogger().handlers:
        logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    status = None if status_file is None else StatusFile(status_file, cfg.navigation.bounds or None)
    visitors = None if synthetic_visitors is None else SyntheticVisitors(synthetic_visitors)
    try:
        run = run_kiosk(cfg, headless=headless, duration=math.inf if duration is None else duration,
                        screenshot_every=screenshot_every, screenshot_dir=screenshot_dir, hooks=UnattendedHooks(),
                        on_frame=chain(status, visitors))
    except (WindowError, RendererError) as exc:
        server_cli.fail(str(exc))
    except ValueError as exc:  # a setting the config's own checks let through (a log file that cannot be opened)
        typer.echo(f"error: {config}: {exc}", err=True)
        raise typer.Exit(EX_CONFIG) from None
    except Exception as exc:  # status 1: systemd restarts the kiosk (2 and 78 are for a person to fix)
        raise typer.Exit(exit_on_unexpected(exc)) from None
    typer.echo(json.dumps(run.summary()))
    if run.status:
        raise typer.Exit(run.status)


app.command()(server_cli.build)
app.command()(server_cli.inspect)
app.command()(server_cli.serve)
app.command()(client)
app.command()(kiosk)
app.command()(bench_cli.demo)
app.command()(cli_load.loadtest)
app.command("eval")(bench_cli.eval_)
bench_cli.bench_app.command("sessions")(cli_load.bench_sessions)
app.add_typer(bench_cli.bench_app, name="bench")


def main(argv: list[str] | None = None) -> None:
    """Run the command line; an unexpected failure is one line and exit status 2 unless ``--debug`` is given."""
    args = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in args
    if debug:
        args.remove("--debug")
    try:
        app(args=args, prog_name="walkstream", standalone_mode=True)
    except SystemExit:
        raise
    except KeyboardInterrupt:
        raise SystemExit(130) from None
    except Exception as exc:
        if debug:
            raise
        typer.echo(f"error: {type(exc).__name__}: {exc} (run with --debug for the traceback)", err=True)
        raise SystemExit(2) from None


if __name__ == "__main__":
    sys.exit(main())
