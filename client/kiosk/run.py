"""``walkstream kiosk``: the kiosk's runner — window, session, frame loop, screenshots, and the hooks.

The same client as ``walkstream client`` (``client.frame_loop.run_frames`` with its governor, the redialling
``client.connection.Link``), with the camera in the hands of ``client.kiosk.director.Director``. What
keeps a kiosk up all day without staff:

- the server or the network gone: the loop keeps drawing what it holds, the overlay shows a small
  "reconnecting…", and the link redials for as long as the kiosk runs (``PATIENCE``), resuming the
  session with nothing re-sent; before the first welcome, and after a session the server ended, the
  kiosk draws its sky with the same mark and keeps dialling — never a black frame, never a dialog;
- the run's records do not grow with the day (``Director.drawn`` trims them).

``KioskHooks`` are the call sites of the parts that keep it running unattended — open hours, the systemd
watchdog, rotated logs, failing over to the next server URL. Here they do nothing (always open, no
watchdog, logging as configured by the caller, the first URL that answers); the unattended parts
subclass it and ``walkstream kiosk`` passes theirs.
"""

from __future__ import annotations

import logging
import math
import queue
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from proto.messages import ALGORITHMS, PROTOCOL_VERSION, Hello

from ..calibrate import renderer_c_vertex
from ..connection import ClientError, Link, open_patiently, with_client
from ..frame_loop import FrameLoop, quiet_collector, run_frames
from ..governor import Governor
from ..records import ClientRun, FrameRecord
from ..renderer import Renderer
from ..splats import SplatLayer
from .config import KioskConfig
from .director import Director
from .overlay import OverlayState

__all__ = ["run_kiosk", "kiosk_renderer", "KioskHooks", "KioskRun", "Shot", "PATIENCE", "CLIENT_NAME"]

log = logging.getLogger("walkstream.kiosk")

CLIENT_NAME = "walkstream-kiosk/0.1"
#: How long a lost link is redialled (s): as long as a kiosk runs.
PATIENCE = 365 * 86400.0
#: A link silent this long (s) is taken for lost (the server pings every second).
SILENCE = 5.0
#: Seconds between dialling rounds while no server answers (each round tries every URL).
DIAL_EVERY = 1.0
#: Frames are paced like a 60 Hz display.
MAX_FPS = 60.0


class KioskHooks:
    """Where the unattended-operation parts plug in; every method is a no-op default.

    Called from the runner's thread (the frame loop's), never concurrently. ``wall`` is ``time.time()``.
    """

    def started(self, config: KioskConfig) -> None:
        """Once, before the window opens: set up logging (``kiosk.log_file``, rotation) and the watchdog."""

    def urls(self, config: KioskConfig) -> list[str]:
        """The server URLs to dial, in order, for a new session."""
        return list(config.kiosk.servers)

    def make_link(self, url: str, hello: Hello, start: float, *, timeout: float, patience: float,
                  silence: float | None, config: KioskConfig) -> Link:
        """The link that redials a lost connection: the place for failing over to the next URL."""
        return Link(url, hello, start, timeout=timeout, patience=patience, silence=silence)

    def frame(self, frames: int, wall: float) -> None:
        """Every frame drawn (``frames`` so far): notify the watchdog while frames advance."""

    def closed(self, wall: float) -> str | None:
        """About once a second: None while open, else what ``schedule.closed`` says ("dim" or "black")."""
        return None

    def exit_status(self, wall: float) -> int | None:
        """About once a second: an exit status to end the kiosk with now (e.g. 75 at ``schedule.restart_at``)."""
        return None

    def stopped(self, status: int) -> None:
        """Once, after the window closed: tell the watchdog the kiosk is stopping."""


@dataclass(frozen=True)
class Shot:
    """A screenshot: where it went, at what client time, and what the kiosk was doing."""

    path: Path
    t: float
    state: str
    caption: str
    stop: int


@dataclass
class KioskRun:
    """What a kiosk run did."""

    frames: int = 0
    sessions: int = 0
    reconnects: int = 0
    states: list[tuple[float, str]] = field(default_factory=list)
    shots: list[Shot] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    status: int = 0
    close_reasons: list[str] = field(default_factory=list)
    #: Client seconds from the start to the first drawn frame (window, dial, first delta), None before it.
    first_frame: float | None = None

    def summary(self) -> dict:
        return {"frames": self.frames, "sessions": self.sessions, "reconnects": self.reconnects,
                "states": [s for _, s in self.states], "screenshots": len(self.shots),
                "errors": self.errors[-5:], "status": self.status, "close_reasons": self.close_reasons,
                "first_frame_s": None if self.first_frame is None else round(self.first_frame, 3)}


def _hello(config: KioskConfig, size: tuple[int, int], renderer: Renderer) -> Hello:
    """The kiosk's hello: its navigation, and caps that cover the visitor and every tour alike."""
    nav, tours = config.navigation, config.playlist
    return Hello(
        protocol=PROTOCOL_VERSION, scene=config.kiosk.scene, viewport=list(size), fov_y=60.0,
        target_frame_time=config.kiosk.target_ms / 1e3, client=CLIENT_NAME, algorithms=list(ALGORITHMS),
        cache_bytes=max(config.kiosk.cache_mb << 20, 1 << 16), governor=True, c_vertex=renderer_c_vertex(renderer),
        max_speed=max([nav.max_speed] + [t.speed for t in tours]),
        max_turn=max([nav.max_turn] + [t.turn for t in tours]),
        navigation=config.navigation_message(), walkable=nav.mode == "walk",
    )


def run_kiosk(
    config: KioskConfig,
    *,
    headless: bool = False,
    duration: float = math.inf,
    screenshot_every: float | None = None,
    screenshot_dir: Path | None = None,
    hooks: KioskHooks | None = None,
    on_frame: Callable[[FrameRecord, Director], None] | None = None,
    timeout: float = 10.0,
) -> KioskRun:
    """Run the kiosk for ``duration`` s (or until its window closes or a hook ends it).

    headless : render over EGL with no window (tests, the soak); else a window, fullscreen per the config
    screenshot_every, screenshot_dir : write the shown frame (overlay included) as PNGs this often
    on_frame : called after every frame, with the director (tests drive input through it)
    Raises ``client.window.WindowError`` if the window cannot open, ``client.renderer.RendererError`` if no
    GL context can be made.
    """
    hooks = hooks or KioskHooks()
    hooks.started(config)
    k = config.kiosk
    view = None
    if not headless:
        from ..window import Window

        view = Window(k.viewport[0], k.viewport[1], title=f"walkstream kiosk {k.id}", fullscreen=k.fullscreen,
                      public=True)
    result = KioskRun()
    director: Director | None = None
    renderer: Renderer | None = None
    try:
        size = (view.width, view.height) if view is not None else (k.viewport[0], k.viewport[1])
        renderer = kiosk_renderer(size, view, k.sky)
        start = time.monotonic()  # the client clock: every t is seconds since here
        end = start + duration

        def clock() -> float:
            return time.monotonic() - start

        director = Director(config, clock=clock, size=size)
        director.attach(renderer)
        if view is not None:
            view.controller = director
        hello = _hello(config, size, renderer)
        shots = _Shots(screenshot_every, screenshot_dir, view, result)
        checked = [0.0]

        def frame_done(record: FrameRecord) -> None:
            result.frames += 1
            if result.first_frame is None:
                result.first_frame = record.t
            wall = time.time()
            hooks.frame(result.frames, wall)
            if wall - checked[0] >= 1.0:
                checked[0] = wall
                director.closed = hooks.closed(wall)
                status = hooks.exit_status(wall)
                if status is not None:
                    result.status, director.done = int(status), True
            shots.take(record.t, renderer, director)
            if on_frame is not None:
                on_frame(record, director)

        client_id = uuid.uuid4().hex
        while not director.done and time.monotonic() < end and not (view is not None and view.should_close):
            opened = _dial(hooks.urls(config), client_id, hello, timeout, end, renderer, director, view, clock, shots)
            if opened is None:
                break
            ws, welcome, nbytes, url = opened
            result.sessions += 1
            log.info("session %s on %s (resumed: %s)", welcome.session, url, welcome.resumed)
            link = hooks.make_link(url, hello, start, timeout=timeout, patience=PATIENCE, silence=SILENCE,
                                   config=config)
            run = ClientRun(welcome=welcome, client_id=client_id)
            inbox: queue.Queue = queue.Queue()
            link.attach(ws, welcome, nbytes, inbox)
            loop = FrameLoop(run, renderer, inbox, ws, cache_bytes=hello.cache_bytes, link=link, start=start)
            loop.governor = Governor(hello.target_frame_time)
            loop.splats = SplatLayer(renderer.ctx)
            try:
                with quiet_collector():
                    run_frames(loop, welcome, start, max(0.0, end - time.monotonic()), 1.0 / MAX_FPS, frame_done,
                               window=view, director=director)
            finally:
                link.close()
                loop.splats.release()
            result.reconnects += len(run.reconnects)
            result.errors += [f"{e.code}: {e.message}" for e in run.errors][-20:]
            if loop.closed:  # the session ended (an administrator, or no resume): start afresh, cache and all
                result.close_reasons.append(run.close_reason)
                log.warning("session ended: %s; dialling a new one", run.close_reason)
                director.release()
                renderer.release()
                renderer = kiosk_renderer(size, view, k.sky)
                director.attach(renderer)
        result.states = list(director.states)
        return result
    finally:
        hooks.stopped(result.status)
        if director is not None:
            director.release()
        if renderer is not None:
            renderer.release()
        if view is not None:
            view.release()


class _Shots:
    """Screenshots every ``every`` s of client time into ``folder`` (of the window's content when there is one)."""

    def __init__(self, every: float | None, folder: Path | None, view, result: KioskRun) -> None:
        self.every, self.folder, self.view, self.result = every, folder, view, result
        self.next = 0.0
        if every is not None and folder is not None:
            Path(folder).mkdir(parents=True, exist_ok=True)

    def take(self, t: float, renderer: Renderer, director: Director) -> None:
        if self.every is None or self.folder is None or t < self.next:
            return
        self.next = (math.floor(t / self.every) + 1) * self.every  # on a grid: slow frames do not stretch it
        path = Path(self.folder) / f"kiosk-{len(self.result.shots):05d}.png"
        if self.view is not None:  # what the window shows: the frame blitted to its back buffer
            self.view.blit(renderer)
            self.view.screenshot(path)
        else:
            renderer.save_png(path)
        self.result.shots.append(Shot(path, t, director.state, director.caption, director.stop))


def _dial(urls: list[str], client_id: str, hello: Hello, timeout: float, end: float, renderer: Renderer,
          director: Director, view, clock: Callable[[], float], shots: _Shots):
    """Dial ``urls`` in turn until one welcomes the kiosk: (ws, welcome, nbytes, url), or None at ``end`` or
    when the window closes. Between rounds the kiosk shows its sky with the reconnecting mark."""
    while time.monotonic() < end and not (view is not None and view.should_close) and not director.done:
        for url in urls:
            try:
                won = open_patiently(with_client(url, client_id), hello, timeout, timeout)  # one dial, its full timeout
                return won.ws, won.welcome, won.nbytes, url
            except ClientError as exc:
                log.warning("cannot open a session on %s: %s", url, exc)
        wait_until = min(end, time.monotonic() + DIAL_EVERY)
        while True:
            _placeholder(renderer, director, view)
            shots.take(clock(), renderer, director)
            if time.monotonic() >= wait_until or (view is not None and view.should_close):
                break
            time.sleep(min(0.1, max(0.0, wait_until - time.monotonic())))  # pacing the placeholder, not a sync
    return None


def kiosk_renderer(size: tuple[int, int], view, sky: bool) -> Renderer:
    """The kiosk's renderer: in the window's context, or offscreen (headless); the sky behind the scene as the
    walkstream client draws it, unless the config turns it off."""
    renderer = Renderer(*size, ctx=view.ctx) if view is not None else Renderer(*size, backend="egl")
    if sky:
        renderer.enable_sky()
    return renderer


def _placeholder(renderer: Renderer, director: Director, view) -> None:
    """A frame with nothing resident: the sky, and the reconnecting mark."""
    renderer.draw(np.zeros(0, np.int64), np.zeros(3), np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0]),
                  0.1, 10.0)
    image, changed = director.overlay.image(OverlayState(language=director.language, reconnecting=True,
                                                         buttons=False))
    director.attach(renderer)
    director.compositor.draw(image, changed)
    if view is not None:
        view.present(renderer)
        view.poll()
