"""When a session selects, and for which cameras: the lead, the grid of switch times, the interval's views.

Selections run on a grid of switch times s, s + τ, … (client clock). The
selection for [s, s + τ) starts just early enough that its delta reaches the
client before its window opens — one τ before s with morphing (the down-morphs
run then), at s without. How early that is, the lead, is the session's own
estimate: a selection's time, plus half a round trip and the delta's bytes over
the link's bandwidth (``clock.Delivery``), plus a safety margin. A poll that
wakes within the margin after its deadline still arrives in time; one later
than that skips to the first slot it can still reach.

The cameras of an interval are the predicted path sampled over it and Zach's
conservative camera around it (2002, 3.3), or the last pose without a
prediction. Nothing here reads a clock: times come in as arguments.
"""

from __future__ import annotations

import logging

import numpy as np

from ..clock import ClockSync, Delivery
from ..select.camera import View
from ..select.predict import conservative_camera
from ..select.selection import Interval
from ..select.snapshot import dump_fields, load_fields

__all__ = ["Timing"]

log = logging.getLogger("walkstream.session")


class Timing:
    """The session's timer: lead estimates, the switch grid, the next deadline and the late check.

    tau, safety, select_limit, clock_wait : ``SessionConfig``'s
    morph : the session morphs (a schedule takes over one τ before its switch)
    """

    #: The fields a snapshot holds (among the session's fields), by their snapshot names.
    STATE = {"late": "late", "_select_time": "select_time", "_delta_bytes": "delta_bytes", "_switch": "switch",
             "_planned": "planned"}

    def __init__(self, tau: float, safety: float, select_limit: float, clock_wait: float, morph: bool = False) -> None:
        self.tau, self.safety, self.clock_wait = float(tau), float(safety), float(clock_wait)
        self.morph = bool(morph)
        self.select_time = float(select_limit)  # running estimate of a selection's compute time
        self.delta_bytes = 0.0  # running estimate of a (non-reset) delta's size
        self.switch: float | None = None  # the last delta's switch time (client clock)
        self.planned = 0.0  # the next delta's switch time
        self.reset = True  # the next delta replaces what is drawn (first, or after a teleport)
        self.next_selection: float | None = None  # server time from which a selection may run
        self.hello_at = 0.0
        self.late = 0  # deltas that arrived after their schedule started
        self._starts: dict[int, tuple[float, bool]] = {}  # seq → (start, reset), for the late check

    # ------------------------------------------------------------------ the lead and the grid

    def lead(self, delivery: Delivery, clock: ClockSync) -> float:
        """Seconds from starting a selection to its delta's arrival, as the session expects it now."""
        return self.select_time + delivery.estimate(self.delta_bytes, clock) + self.safety

    def window(self, switch: float) -> float:
        """When the schedule for ``switch`` takes over: one τ early with morphing (down-morphs), else at it."""
        return switch - self.tau if self.morph else switch

    def next_switch(self, client_now: float, lead: float) -> float:
        """The first switch on the grid, after the last one, whose window a delta started now reaches in time."""
        switch = self.switch + self.tau
        behind = client_now + lead - self.window(switch)
        # A poll wakes a little after its deadline (the event loop, a busy worker pool): lateness within the
        # safety margin the lead already holds still arrives in time. Counting it as late would skip every
        # other slot on a real server — one selection per 2τ.
        if behind > max(self.safety, 1e-6):
            switch += np.ceil(behind / self.tau - 1e-6) * self.tau
        return float(switch)

    def selection_due(self, has_camera: bool, lead: float, clock: ClockSync) -> float | None:
        """Server time the next selection is due, or None while waiting for the client's first pose."""
        if not has_camera or self.next_selection is None:
            return None
        if self.reset or self.switch is None:
            return self.next_selection
        # As late as still arrives in time: the prediction is then as short as it can be.
        due = clock.server_time(self.window(self.planned) - lead)
        if not clock.known:  # the lead is a guess until the first pong: wait for it, a while
            due = max(due, self.hello_at + self.clock_wait)
        return due

    def teleport(self, now: float) -> bool:
        """The camera jumped: the pipeline restarts with a reset delta, selected at once. Whether it had begun."""
        if self.switch is None:
            return False
        self.reset = True
        self.next_selection = now
        return True

    def restart(self) -> None:
        """A resumed session restarts its pipeline with a reset delta, as after a teleport."""
        self.switch, self.reset, self.next_selection = None, True, None

    # ------------------------------------------------------------------ one selection

    def plan(self, client_now: float, lead: float) -> tuple[bool, float, float, float, float]:
        """(reset, start, switch, t0, t1) of the selection started now: the schedule's start and switch, and the
        interval [t0, t1) the cameras are predicted over."""
        tau = self.tau
        if self.reset or self.switch is None:
            # Drawn from its arrival: select for the stretch until the pipeline's first regular switch.
            return True, client_now, client_now, client_now + lead, client_now + 2 * tau
        switch = self.next_switch(client_now, lead)
        return False, self.window(switch), switch, switch, switch + tau

    def selected(self, seq: int, now: float, client_now: float, start: float, switch: float, reset: bool,
                 took: float, nbytes: int, delivery: Delivery, clock: ClockSync) -> None:
        """Delta ``seq`` is built: keep the estimates (its compute time; the size of regular deltas) and move
        the grid on to the next switch."""
        self.select_time = max(took, 0.7 * self.select_time + 0.3 * took)
        if not reset:
            self.delta_bytes = 0.7 * self.delta_bytes + 0.3 * nbytes if self.delta_bytes else float(nbytes)
        self._starts[seq] = (start, reset)
        if len(self._starts) > 64:
            self._starts.pop(min(self._starts))
        self.switch, self.reset = switch, False
        self.planned = self.next_switch(client_now, self.lead(delivery, clock))
        self.next_selection = now

    def to_state(self) -> dict:
        return dump_fields(self, self.STATE)

    def from_state(self, fields) -> None:
        """Take in ``to_state``'s data (the session's fields); ValueError (timing unchanged) if it does not fit."""
        load_fields(self, fields, self.STATE, "session")

    def acked(self, seq: int, client_t: float, took: float | None, name: str = "") -> None:
        """The ack of delta ``seq`` came at client time ``client_t``: late if after its schedule started."""
        start = self._starts.pop(seq, None)
        if start is not None and not start[1] and client_t > start[0] + 1e-3:
            self.late += 1
            log.info("session %s: delta %d arrived %.3f s after its schedule started (took %s)",
                     name, seq, client_t - start[0], took)

    # ------------------------------------------------------------------ cameras

    def cameras(self, config, hello, camera, predictor, bounds: np.ndarray, client_now: float, t0: float,
                t1: float):
        """The cameras for [t0, t1) and the field of view added around them: predicted samples and the
        conservative camera, or the last pose (``SessionConfig``'s samples, conservative_weight, margins)."""
        vp = tuple(hello.viewport)
        if predictor is None or predictor.latest is None:
            return View.of_pose(camera.eye, camera.forward, camera.up, hello.fov_y, vp, bounds), config.margin_deg
        k = max(1, config.samples)
        poses = predictor.samples(t0, t1, k)
        views = tuple(View.of_pose(p.eye, p.forward, p.up, hello.fov_y, vp, bounds) for _, p in poses)
        # Zach's conservative camera covers every view reachable by the end of the interval.
        horizon = max(t1 - client_now, 1e-3)
        now_pose = predictor.pose(max(client_now, predictor.latest))
        stages = 3 if self.morph else 2
        pose, fov = conservative_camera(now_pose, hello.fov_y, vp[0] / vp[1], horizon / stages,
                                        predictor.theta, predictor.omega, stages=stages)
        conservative = View.of_pose(pose.eye, pose.forward, pose.up, fov, vp, bounds)
        interval = Interval(views, conservative, config.conservative_weight, tuple(t for t, _ in poses))
        return interval, config.predict_margin_deg
