"""The client's entry point: connect, follow the tour, apply deltas, draw, measure, report.

``run_client`` opens the session and hands it to the frame loop. One thread
owns the GL context and the websocket's sending side (``client.frame_loop``);
a background thread only receives and decodes frames onto a queue, answering
pings at once, and another redials a lost connection while the frame loop
keeps drawing what is resident (``client.connection``). What a run produced
comes back as a ``client.records.ClientRun``.

Per frame, in order: pose for ``t`` → ``Camera`` → apply queued deltas → the
schedule's representations and morph weights for ``t`` → draw them (fenced) →
``FrameReport`` → ``FrameRecord``. Decoding and uploading happen between
frames, always outside the timed fence.

A redial resumes the session by its token with the cache's held manifest, so
the server sends nothing the cache already holds. The run's client id goes in
the URL's query (``client=<id>``) so a load balancer hashing on it keeps the
client on one replica.
"""

from __future__ import annotations

import queue
import time
import uuid
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from proto.messages import ALGORITHMS, DEFAULT_SUN, PROTOCOL_VERSION, Error, Hello, TourKey, TourPlan
from proto.tour import Tour

from .connection import Arrived, Item, Link, Redialled, as_urls, open_patiently, with_client
from .frame_loop import FrameLoop, quiet_collector, run_frames
from .calibrate import renderer_c_vertex
from .governor import Governor
from .hold import STRICT, Hold
from .navigation import Navigator
from .records import ClientRun, FrameRecord
from .renderer import COLOURS, Renderer
from .splats import SplatLayer

__all__ = ["run_client"]

CLIENT_NAME = "walkstream-client/0.1"


#: Keys a hello's plan carries at most: a hello must fit one client frame (``proto.codec.MAX_CLIENT_FRAME``).
HELLO_PLAN_KEYS = 400


def tour_plan(keys: Sequence[dict], duration: float) -> TourPlan:
    """The plan of a run that follows looping tour ``keys`` from client time 0 (tour time = client time):
    the loops unrolled over ``duration`` s and a second more, at most ``HELLO_PLAN_KEYS`` keys (a longer run
    is predicted from its samples after them)."""
    tour = Tour(keys)
    loop = tour.duration
    out: list[TourKey] = []
    k = 0
    while True:  # at each loop's end both its last key and the next loop's first stand at one time, as Tour wraps
        out += [TourKey(t=float(tour.t[i] + k * loop), eye=tour.eye[i].tolist(), forward=tour.forward[i].tolist(),
                        up=tour.up[i].tolist()) for i in range(len(tour.t))]
        if loop <= 0 or len(out) >= HELLO_PLAN_KEYS or tour.t[0] + (k + 1) * loop > duration + 1.0:
            end = int(np.searchsorted([key.t for key in out], duration + 1.0)) + 1  # one key past the run
            return TourPlan(t=0.0, keys=out[:min(end, HELLO_PLAN_KEYS)], tour="run")
        k += 1


def run_client(
    url: str | Sequence[str],
    scene: str,
    *,
    duration: float,
    viewport: Sequence[int] = (640, 360),
    fov_y: float = 60.0,
    target_frame_time: float = 0.05,
    solver: str = "greedy",
    on_frame: Callable[[FrameRecord], None] | None = None,
    screenshot: Path | None = None,
    max_fps: float | None = 60.0,
    timeout: float = 10.0,
    backend: str | None = "egl",
    predict: bool = True,
    morph: bool = True,
    trace: bool = False,
    window: bool = False,
    navigate: str = "tour",
    false_colour: bool = False,
    colours: str = "data",
    sky: bool = True,
    algorithms: Sequence[str] = ALGORITHMS,
    cache_bytes: int | None = None,
    reconnect_timeout: float = 10.0,
    silence_timeout: float | None = 10.0,
    tour: "Sequence[dict] | None" = None,
    governor: bool = True,
    hold: Hold = STRICT,
    calibrate: bool = True,
    plan: bool = False,
    record_tour: Path | None = None,
    tour_name: str | None = None,
) -> ClientRun:
    """Run one session for ``duration`` seconds of frames and return what happened.

    ``url`` is the server's websocket, or several servers' (tried in turn, on the
    first connect and on every redial; ``client.connection``).
    ``max_fps`` paces frames like a display's refresh would (None: as fast as
    possible); ``timeout`` bounds connecting and waiting for the welcome.
    ``predict`` and ``morph`` ask the server for path prediction and geomorphing;
    ``trace`` records every frame's drawn levels and weights in ``ClientRun.trace``.
    ``window`` shows the frames in a window (``client.window``; ends early when
    it is closed) and ``navigate`` ("tour", "fly", "walk") says who moves the
    camera there: the scene's tour, or the user (``client.navigation.Navigator``,
    whose limits go out in the ``Hello``). ``false_colour`` sets ``Renderer.false_colour``, ``colours``
    ``Renderer.colours`` ("data": the scene's colours, "objects": a tint per object); ``sky`` paints the
    sky behind the scene (``client.sky``). Every algorithm is lit by the scene's sun (``Welcome.sun``).
    ``algorithms`` are the rendering algorithms offered to the selection (``proto.messages.ALGORITHMS``);
    ``cache_bytes`` is the client cache's budget (payload bytes), kept by both ends.
    A lost connection is redialled for up to ``reconnect_timeout`` s (0: never; ``math.inf``: for ever; the run
    then ends with a ``connection_lost`` error), resuming the session by its token with
    the cache's held manifest, while frames go on from what is resident; a link
    silent for ``silence_timeout`` s (None: no limit) counts as lost. A ``busy`` server
    is retried as long on the first connect too.
    ``tour`` (keys ``{t, eye, forward, up}``, as ``proto.messages.TourKey``) replaces the
    tour the server's welcome carries: evaluations drive the camera along paths of their own.
    ``governor`` (on by default) asks for the delta's ladder and corrects the selection every
    frame to hold ``target_frame_time`` (``client.governor``); off, the server's plan is drawn as it is.
    ``hold`` is the line it holds (``client.hold.Hold``; by default at most 1 % of frames over 1.1 × target).
    ``calibrate`` measures the renderer's seconds per vertex before the hello (``client.calibrate``), the
    server's first guess for its cost model. ``plan`` (with a ``tour``) tells the server the path in the
    hello (``Hello.plan``): it then predicts the camera along the tour instead of extrapolating.
    ``record_tour`` (with ``window`` and a navigator): M or Space marks the current pose as a tour stop, and the
    stops are written there when the run ends (``client.kiosk.record``; nothing is written if none was marked).
    ``tour_name`` asks the server for the scene's tour of that name (``Hello.tour``: walk, flyover, orbit, ...)
    in place of its default one; a name the scene lacks is refused (``ClientError`` naming the tours it has).
    Raises ``client.connection.ClientError`` if the session cannot be opened, ``client.window.WindowError``
    if the window cannot.
    """
    if colours not in COLOURS:
        raise ValueError(f"colours must be one of {', '.join(COLOURS)}, got {colours!r}")
    if navigate not in ("tour", "fly", "walk"):
        raise ValueError(f"navigate must be tour, fly or walk, got {navigate!r}")
    if navigate != "tour" and not window:
        raise ValueError("interactive navigation (fly, walk) needs window=True")
    if tour is not None and navigate != "tour":
        raise ValueError("a tour and interactive navigation exclude each other")
    if record_tour is not None and navigate == "tour":
        raise ValueError("recording a tour needs interactive navigation (fly or walk) in a window")
    urls = as_urls(url)  # raises ValueError now on an empty list
    if tour is not None:
        tour = list(tour)
        Tour(tour)  # raises ValueError now, before connecting, on a malformed tour
    if plan and tour is None:
        raise ValueError("plan needs a tour: the path the hello announces")
    width, height = (int(v) for v in viewport)
    view = None
    if window:
        from .window import Window

        view = Window(width, height)
        try:
            renderer = Renderer(width, height, fov_y=fov_y, ctx=view.ctx)
        except BaseException:
            view.release()
            raise
    else:
        renderer = Renderer(width, height, fov_y=fov_y, backend=backend)
    if false_colour:
        setattr(renderer, "false_colour", True)
    renderer.colours = colours
    if sky:
        renderer.enable_sky()
    navigator = Navigator(mode=navigate) if navigate != "tour" else None
    limits = {} if navigator is None else {"max_speed": navigator.max_speed, "max_turn": navigator.max_turn}
    if view is not None:
        view.controller = navigator
    recorder = None
    if record_tour is not None and view is not None and navigator is not None:
        from .kiosk.record import StopRecorder

        recorder = StopRecorder()
        view.marker = lambda: recorder.mark(navigator.pose)
    start = time.monotonic()  # the client clock: every t is seconds since here
    client_id = uuid.uuid4().hex
    urls = tuple(with_client(u, client_id) for u in urls)
    loop: FrameLoop | None = None
    try:
        hello = Hello(
            protocol=PROTOCOL_VERSION, scene=scene, viewport=[width, height], fov_y=fov_y,
            target_frame_time=target_frame_time, solver=solver, client=CLIENT_NAME, predict=predict, morph=morph,
            algorithms=list(algorithms), cache_bytes=cache_bytes, governor=governor,
            c_vertex=renderer_c_vertex(renderer) if calibrate else None, **limits,
            plan=tour_plan(tour, duration) if plan else None, tour=tour_name,
        )
        opened = open_patiently(urls, hello, timeout, max(0.0, reconnect_timeout))
        link = Link(urls, hello, start, timeout=timeout, patience=reconnect_timeout, silence=silence_timeout)
        run = ClientRun(welcome=opened.welcome, client_id=client_id, attempts=opened.attempts, url=opened.url)
        sun = np.asarray(opened.welcome.sun if opened.welcome.sun is not None else DEFAULT_SUN, np.float64)
        renderer.sun = sun / np.linalg.norm(sun)
        inbox: queue.Queue[Item] = queue.Queue()
        link.attach(opened.ws, opened.welcome, opened.nbytes, inbox, url=opened.url)
        welcome = opened.welcome
        loop = FrameLoop(run, renderer, inbox, opened.ws, cache_bytes=cache_bytes, link=link, start=start)
        if governor:
            loop.governor = Governor(target_frame_time, hold=hold)
        try:
            loop.splats = SplatLayer(renderer.ctx)
            loop.splats.sun = renderer.sun
            with quiet_collector():
                run_frames(loop, welcome, start, duration, 1.0 / max_fps if max_fps else 0.0, on_frame, trace,
                        window=view, navigator=navigator, tour_keys=tour)
            if screenshot is not None:
                renderer.save_png(screenshot)
        finally:
            link.close()
        while True:  # late arrivals: count them, record errors, apply nothing
            try:
                item = inbox.get_nowait()
            except queue.Empty:
                break
            if isinstance(item, Arrived):
                run.deltas_received += 1
            elif isinstance(item, Error) and item.code != "closed":
                run.errors.append(item)
            elif isinstance(item, Redialled):  # won just as the run ended
                item.ws.close_socket()
        if link.ws is not None:  # the last connection was still up when the run ended
            loop.count_connection(link.counter)
        run.bytes_received = sum(run.bytes_per_connection)
        run.rejected = list(loop.cache.rejected)
        run.unmorphed = renderer.unmorphed
        if loop.governor is not None:
            run.governor = loop.governor.report()
        return run
    finally:
        if recorder is not None and recorder.stops:
            recorder.write(record_tour)
        if loop is not None and loop.splats is not None:
            loop.splats.release()
        renderer.release()
        if view is not None:
            view.release()
