"""The kiosk's camera director: who moves the camera each frame, what the overlay shows, what the server hears.

``client.frame_loop.run_frames`` asks it for the pose of every frame (``pose_at``), sends what it queues
(``outgoing``: tour plans and heartbeats) and hands it each drawn frame (``drawn``), after the timed draw,
to blend the overlay over. The window gives it the visitor's input (``key``, ``look``, ``tap``).

- Attract: the camera follows a ``client.kiosk.stops.Segment`` — the playlist loop — and each segment (and
  each later part of a long one, within the client frame limit) goes to the server as a ``TourPlan``, so it
  predicts the exact future poses instead of extrapolating.
- Visitor: any input takes the camera (``client.kiosk.walking.KioskNavigator`` from the current pose, and an
  empty ``TourPlan``: the visitor drives). The buttons fly to the next or previous stop or home (a one-stop
  segment, told to the server too) or switch the captions' language.
- Countdown and back: ``client.kiosk.attract.AttractMachine`` decides; on the way back the language is
  reset and the loop starts again from the first stop, from wherever the visitor left the camera.

The caption shows while the camera dwells at a stop (and after a visitor's "next", until they move).
Clock: ``clock()`` gives client time for input that arrives between frames; frames pass their own ``t``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

import numpy as np

from proto.codec import encode
from proto.errors import ProtocolError
from proto.messages import DEFAULT_SUN, MAX_PLAN_KEYS, Error, TourPlan, Welcome
from proto.walkable import WalkableGrid, decode as decode_walkable

from ..gpu_memory import gpu_memory

from .attract import ATTRACT, COUNTDOWN, AttractMachine, reported_state
from .config import KioskConfig
from .heartbeat import Meter, rss_bytes
from .hours import CLOSED_LOOKS
from .overlay import Overlay, OverlayState
from .stops import Playlist, Segment, playlist_stops
from .walking import KioskNavigator

if TYPE_CHECKING:
    from ..frame_loop import FrameLoop
    from ..records import FrameRecord

__all__ = ["Director", "PLAN_BYTES", "PLAN_LEAD"]

#: A tour plan's encoded size at most (the server's client frame limit is 64 KiB).
PLAN_BYTES = 48 * 1024
#: The next part of a long plan goes this many seconds before the last one runs out.
PLAN_LEAD = 3.0
#: The slowest the attract loop plays (a black screen's loop need not stand still: it costs nothing to move).
SLOWEST = 0.05
#: Frame records a kiosk keeps (it runs all day: the run's lists must not grow with it).
KEEP_RECORDS = 600


class Director:
    """The camera, overlay and messages of a kiosk (``config``) in a ``size`` (width, height) frame."""

    def __init__(self, config: KioskConfig, *, clock: Callable[[], float], size: tuple[int, int]) -> None:
        self.config, self.clock = config, clock
        k = config.kiosk
        self.machine = AttractMachine(config.idle.idle_s, config.idle.countdown_s, now=clock())
        self.language = k.languages[0]
        self.overlay = Overlay(size[0], size[1], font=config.font, caption_px=k.caption_px)
        self.layout = self.overlay.layout
        self.meter = Meter(k.id, k.heartbeat_s, start=clock())
        self.playlist: Playlist | None = None
        self.navigator: KioskNavigator | None = None
        self.grid: WalkableGrid | None = None
        self.segment: Segment | None = None
        """The path the camera follows (the attract loop, or a visitor's "next"); None: the visitor drives."""
        self.stop = 0
        """The current stop (index into ``playlist.stops``): dwelt at, headed to, or last visited."""
        self.caption_pose: np.ndarray | None = None  # the visitor stands where a "next" left them: keep its caption
        self._closed: str | None = None
        """Outside the open hours: "dim" or "black" (set by the runner's schedule hook); None: open."""
        self.done = False
        """Set to end the run (the runner's exit hook)."""
        self.loop: FrameLoop | None = None
        self.compositor = None
        self.states: list[tuple[float, str]] = []
        """(client time, state) of every state entered, at the exact time the machine entered it."""
        self._out: list = []
        self._plan: list = []  # the active segment's TourKeys; sent in parts
        self._plan_next = 0  # first key not yet sent
        self._reconnects = 0
        self.gpu_memory: int | None = None
        """GPU memory in use at the last heartbeat (bytes), None where the driver does not tell."""
        self._pose: tuple | None = None
        self._dwelling = False  # the camera is at the current stop (its caption shows)

    # ----------------------------------------------------------------- the frame loop's side

    def attach(self, renderer) -> None:
        """Draw the overlay over ``renderer``'s frames (a new renderer: a new compositor)."""
        from .compositor import Compositor

        if self.compositor is not None and self.compositor.renderer is renderer:
            return
        self.release()
        self.compositor = Compositor(renderer)

    def begin(self, welcome: Welcome, t: float, loop: "FrameLoop") -> None:
        """The session is open: bounds, walkable ground, then the attract loop from the first stop (a later
        session of the same run carries on from where the camera is)."""
        self.loop = loop
        self.attach(loop.renderer)
        sun = np.asarray(welcome.sun if welcome.sun is not None else DEFAULT_SUN, np.float64)
        loop.renderer.sun = sun / np.linalg.norm(sun)  # the scene's sun, as the walkstream client lights it
        self._reconnects = 0
        nav = self.config.navigation
        if welcome.walkable:
            try:
                self.grid = decode_walkable(welcome.walkable)
            except ProtocolError as exc:
                loop.run.errors.append(Error(code=exc.code, message=f"walkable grid: {exc.message}"[:4096]))
        bounds = nav.bounds or welcome.bounds
        self.navigator = KioskNavigator(nav.mode, bounds=bounds, max_speed=nav.max_speed, max_turn=nav.max_turn,
                                        eye_height=nav.eye_height, grid=self.grid)
        first = self.playlist is None
        self.playlist = Playlist(playlist_stops(self.config.playlist), ground=self.grid, eye_height=nav.eye_height)
        if first:
            self._play(self.playlist.pose(0), t, 0)
            self.states.append((t, self.machine.state))
        else:
            self._play(self._pose if self._pose is not None else self.playlist.pose(0), t, 0)
            if self.machine.state != ATTRACT:
                self._take_over(t)

    def pose_at(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The pose for the frame at client time ``t``."""
        nav = self.navigator
        assert nav is not None and self.playlist is not None, "begin() first"
        if self.segment is None and (nav.controller.held or nav.controller._look.any()):
            self._input(t)  # a key held down or a drag still turning: the visitor is there
        for state, at in self.machine.tick(t):
            self._enter(state, t, at)
        seg = self.segment
        if seg is not None and t >= seg.end:
            if seg.loops:
                restart = seg.end if t - seg.end < seg.end - seg.start else t
                self._play(self.playlist.pose(int(seg.stops[0])), restart, int(seg.stops[0]))
            else:  # a visitor's "next" arrived and dwelt: they drive from the stop, its caption still up
                nav.place(seg.pose_at(seg.end), t)
                self.caption_pose = np.asarray(seg.pose_at(seg.end)[0])
                self.segment = None
        seg = self.segment
        if seg is not None:
            pose = seg.pose_at(t)
            self.stop, self._dwelling = seg.stop_at(t)
            self._send_plan(t)
        else:
            pose = nav.pose_at(t)
            self._dwelling = self.caption_pose is not None and bool(np.allclose(pose[0], self.caption_pose, atol=1e-6))
        self._pose = pose
        return pose

    def outgoing(self, t: float) -> list:
        """Messages to send now (tour plans, a heartbeat when due); taken, so each goes once."""
        loop = self.loop
        if loop is not None:
            n = len(loop.run.reconnects)
            if n != self._reconnects:  # a new connection (perhaps a restarted server): tell it the plan again
                self._reconnects = n
                self._resend(t)
        if self.meter.due(t) and loop is not None and self.playlist is not None:
            stop = self.playlist.stops[self.stop]
            self.gpu_memory = gpu_memory(loop.renderer.ctx.extensions)  # the frame loop's thread: its context
            self._out.append(self.meter.beat(
                t, state=self.state, rss=rss_bytes(), cache_bytes=loop.cache.held_bytes,
                reconnects=len(loop.run.reconnects), tour=stop.tour, stop=stop.index, gpu_memory=self.gpu_memory))
        out, self._out = self._out, []
        return out

    def drawn(self, t: float, record: "FrameRecord") -> None:
        """The frame at ``t`` was drawn (``record``): blend the overlay over it, count it."""
        self.meter.frame(record.time)
        image, changed = self.overlay.image(self.overlay_state(t))
        if self.compositor is not None:
            self.compositor.draw(image, changed)
        run = self.loop.run if self.loop is not None else None
        if run is not None:
            if len(run.frames) > 2 * KEEP_RECORDS:
                del run.frames[:-KEEP_RECORDS]
            if len(run.errors) > 2 * KEEP_RECORDS:
                del run.errors[:-KEEP_RECORDS]

    def release(self) -> None:
        if self.compositor is not None:
            self.compositor.release()
            self.compositor = None

    # ----------------------------------------------------------------- what is shown

    @property
    def link_up(self) -> bool:
        return self.loop is None or self.loop.ws is not None

    @property
    def state(self) -> str:
        """The state a heartbeat reports (``proto.messages.KIOSK_STATES``)."""
        return reported_state(self.machine.state, link_up=self.link_up, open_now=self.closed is None)

    @property
    def caption(self) -> str:
        """The current stop's caption in the current language, while the camera is at the stop."""
        if self.playlist is None or self.machine.state == COUNTDOWN:
            return ""
        stop = self.playlist.stops[self.stop]
        return stop.text(self.language, self.config.kiosk.languages[0]) if self._dwelling else ""

    def overlay_state(self, t: float) -> OverlayState:
        return OverlayState(caption=self.caption, language=self.language, countdown=self.machine.seconds_left(t),
                            reconnecting=not self.link_up, dim=1.0 - CLOSED_LOOKS[self.closed][0] if self.closed else 0.0)

    # ----------------------------------------------------------------- input (the window's callbacks)

    def key(self, name: str, pressed: bool) -> bool:
        if self.navigator is None:
            return False
        if pressed:
            now = self._input()
            self._take_over(now)
        return self.navigator.key(name, pressed)

    def look(self, dx: float, dy: float) -> None:
        if self.navigator is None:
            return
        now = self._input()
        self._take_over(now)
        self.navigator.look(dx, dy)

    def tap(self, x: float, y: float) -> str | None:
        """A tap (or click) at window pixel (x, y): a button's action, else the visitor takes the camera."""
        if self.navigator is None or self.playlist is None:
            return None
        now = self._input()
        button = self.layout.hit(x, y)
        n = len(self.playlist)
        if button in ("next", "previous", "home"):
            target = {"next": self.stop + 1, "previous": self.stop - 1, "home": 0}[button] % n
            self._guide(target, now)
        elif button == "language":
            langs = self.config.kiosk.languages
            self.language = langs[(langs.index(self.language) + 1) % len(langs)]
            self._take_over(now)
        else:
            self._take_over(now)
        return button

    def clear_input(self) -> None:
        if self.navigator is not None:
            self.navigator.clear_input()

    # ----------------------------------------------------------------- transitions

    def _input(self, now: float | None = None) -> float:
        now = self.clock() if now is None else now
        for state, at in self.machine.input(now):
            self._enter(state, now, at)
        return now

    def _enter(self, state: str, t: float, at: float) -> None:
        """``state`` was entered at ``at`` (exact), noticed at ``t``."""
        self.states.append((at, state))
        if state == ATTRACT:
            self.language = self.config.kiosk.languages[0]
            self.caption_pose = None
            if self.navigator is not None:
                self.navigator.clear_input()
            self._play(self._current(t), t, 0)

    def _current(self, t: float) -> tuple:
        if self.segment is not None:
            return self.segment.pose_at(t)
        if self.navigator is not None:
            return self.navigator.pose
        return self._pose if self._pose is not None else self.playlist.pose(0)

    def _take_over(self, now: float) -> None:
        """The visitor drives from the current pose; the server is told to predict from the samples again."""
        if self.segment is None:
            return
        pose = self.segment.pose_at(now)
        self.segment, self._plan, self._plan_next = None, [], 0
        self.caption_pose = None
        self.navigator.place(pose, now)
        self._out.append(TourPlan(t=max(now, 0.0), keys=[], tour=""))

    def _guide(self, stop: int, now: float) -> None:
        self._start(self.playlist.segment(self._current(now), now, stop, loop=False), now)
        self.stop = stop
        if self.navigator is not None:
            self.navigator.clear_input()

    def _play(self, pose: tuple, t: float, stop: int) -> None:
        rate = CLOSED_LOOKS[self._closed][1] if self._closed else 1.0
        self._start(self.playlist.segment(pose, t, stop, loop=True, rate=max(rate, SLOWEST)), t)
        self.stop = stop

    @property
    def closed(self) -> str | None:
        """None while the kiosk is open, else how it looks closed ("dim": darkened, the attract loop slowed;
        "black"). Set by the runner from the opening hours; a change replays the attract loop at its rate."""
        return self._closed

    @closed.setter
    def closed(self, value: str | None) -> None:
        if value == self._closed:
            return
        self._closed = value
        seg = self.segment
        if seg is not None and seg.loops and self.playlist is not None and self._pose is not None:
            t = self.clock()
            self._play(self._pose, t, seg.stop_at(t)[0])  # on from here to the stop it is at or heading to

    def _start(self, segment: Segment, t: float) -> None:
        self.segment = segment
        self.caption_pose = None
        self._plan, self._plan_next = segment.keys(MAX_PLAN_KEYS), 0
        self._send_plan(t)

    def _resend(self, t: float) -> None:
        if self.segment is None:
            self._out.append(TourPlan(t=max(t, 0.0), keys=[], tour=""))
            return
        i = int(np.searchsorted(self.segment.t[:len(self._plan)], t, side="right"))
        self._plan_next = max(0, i - 1)
        self._send_plan(t, force=True)

    def _send_plan(self, t: float, force: bool = False) -> None:
        """Send the next part of the active plan when it is due: at once for a new segment, else ``PLAN_LEAD``
        s before the part sent last runs out. A part starts with the key the last one ended on."""
        plan, i = self._plan, self._plan_next
        if i >= len(plan) or self.playlist is None:
            return
        if i > 0 and not force and t < plan[i - 1].t - PLAN_LEAD:
            return
        first = max(0, i - 1)
        n = min(len(plan) - first, 400)
        tour = self.playlist.stops[int(self.segment.stops[0])].tour if self.segment is not None else ""
        while True:
            msg = TourPlan(t=max(t, 0.0), keys=plan[first:first + n], tour=tour)
            if n <= 2 or len(encode(msg)) <= PLAN_BYTES:
                break
            n //= 2
        self._out.append(msg)
        self._plan_next = first + n
