"""The frame loop: one thread that owns the GL context and the websocket's sending side.

Per frame, in order: pose for ``t`` → ``Camera`` (carrying the last frame's
``FrameReport``: one message a frame) → apply queued deltas → the schedule's
representations and morph weights for ``t`` → draw them (fenced) → its report
→ ``FrameRecord``. The loop never sleeps: between frames it
waits on the receiver's queue (``client.connection``) until the next frame is
due, so a delta that arrives while the client is idle is decoded and uploaded
then — always outside the timed fence of a frame.

``FrameLoop`` is the loop's state (cache, schedules, the run being recorded)
and how it handles what the receiver and the redialler put on the queue;
``run_frames`` is the loop proper. While the link is down, sends are skipped
and frames go on from what is resident.
"""

from __future__ import annotations

import gc
import queue
import time
from contextlib import contextmanager
from typing import TYPE_CHECKING, Callable, Iterator, Protocol

import numpy as np
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import ClientConnection

from proto.camera import NEAR, far_plane
from proto.codec import encode
from proto.messages import MAX_LADDER_VERTICES, Ack, AlgorithmTerms, Camera, Delta, Error, FrameReport, Welcome
from proto.tour import Tour

from .cache import ResidentCache
from .connection import Arrived, Closed, GaveUp, Item, Link, Redialled
from .governor import Governor, GovernorLadder
from .navigation import Navigator
from .records import ClientRun, FrameRecord, FrameTrace, Reconnect
from .schedule import Drawn, Schedule

if TYPE_CHECKING:
    from .renderer import Renderer

__all__ = ["FrameLoop", "Director", "run_frames", "quiet_collector"]


class Director(Protocol):
    """Who moves the camera instead of a tour or a navigator (a kiosk's ``client.kiosk.director.Director``)."""

    done: bool

    def begin(self, welcome: Welcome, t: float, loop: "FrameLoop") -> None: ...
    def pose_at(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...
    def outgoing(self, t: float) -> list: ...
    def drawn(self, t: float, record: FrameRecord) -> None: ...


class FrameLoop:
    """The main loop's state: cache, renderer, inbox and the run being recorded.

    ``ws`` is the sending side (anything with ``send(bytes)``), None while the link
    is down; ``link`` (when given) redials a lost connection.
    """

    def __init__(self, run: ClientRun, renderer: Renderer, inbox: "queue.Queue[Item]",
                 ws: ClientConnection | None = None, cache_bytes: int | None = None, link: Link | None = None,
                 start: float = 0.0) -> None:
        self.run, self.renderer, self.inbox, self.ws, self.link = run, renderer, inbox, ws, link
        self.start = start
        self.cache = ResidentCache(cache_bytes)  # the Hello's cache_bytes: the server's mirror keeps to it
        self.splats = None  # the splat layer (client.splats) for tree groups and models, when there is one
        self.schedule = Schedule()
        self.vegetation = Schedule(continuous=True)
        # Rendering algorithm per object key, as (switch time, sorted keys, algorithms) from each delta:
        # a delta's algorithms govern from its t0, like its selection.
        self._algorithms: list[tuple[float, np.ndarray, np.ndarray]] = []
        self.last: Delta | None = None
        self.upload_time = 0.0
        self.applied_bytes = 0  # bytes of deltas applied since the last frame record
        self.drawn_vegetation: tuple[np.ndarray, np.ndarray] = (np.zeros(0, np.int64), np.zeros(0))
        self.closed = False
        self.failing = False  # a send failed: the receiver is ending, its Closed is on the way
        self.governor: Governor | None = None  # corrects the selection every frame along each delta's ladder
        self.governor_refused = 0  # rows the governor moved to what cannot be drawn, drawn as planned instead
        self._last_rows: tuple | None = None  # (keys, reps) the last frame's rows drew

    def send(self, msg) -> None:
        """Send on the current connection; a failure shuts it down so its receiver reports the loss."""
        ws = self.ws
        if ws is None or self.failing:
            return
        try:
            ws.send(encode(msg))
        except (ConnectionClosed, OSError) as exc:
            if self.link is None:
                self.closed, self.run.close_reason = True, f"connection lost while sending: {exc}"
                return
            self.failing = True
            ws.close_socket()

    def handle(self, item: Item) -> None:
        if isinstance(item, Arrived):
            delta = item.delta
            self.run.deltas_received += 1
            self.applied_bytes += item.nbytes
            t0 = time.perf_counter()
            if delta.add:
                added = np.fromiter((a.rep for a in delta.add), np.int64, len(delta.add))
                self.run.resent += int(self.cache.holds(added).sum())
                if self.run.reconnects:
                    self.run.adds_after_reconnect += len(delta.add)
            changes = self.cache.apply(delta)
            for rep in changes.frees:
                self.renderer.free(rep)
            self.renderer.reserve(sum(g.vertices for _, g in changes.uploads),
                                  sum(3 * g.faces for _, g in changes.uploads))
            for rep, geometry in changes.uploads:
                self.renderer.upload(rep, geometry, object_id=self.cache.resident[rep].object)
            if self.splats is not None:
                for model, points in changes.models:
                    self.splats.add_model(model, points)
                for rep in changes.group_frees:
                    self.splats.free_group(rep)
                for rep, instances in changes.groups:
                    self.splats.add_group(rep, instances)
            self.run.refused_full = self.cache.refused_full
            self.run.peak_cache_bytes = max(self.run.peak_cache_bytes, self.cache.held_bytes)
            m, scheduled = delta.morphs, delta
            held = self.cache.holds(np.asarray(m.rep, np.int64))
            if not held.all():  # a ramp to a rep the cache lacks (refused, or beyond the budget) can't be drawn
                keep = np.nonzero(held)[0].tolist()
                cols = {k: [getattr(m, k)[i] for i in keep] for k in ("rep", "level_from", "level_to", "t0", "t1")}
                scheduled = delta.model_copy(update={"morphs": m.model_copy(update=cols)})
            self._schedule(scheduled, item.t)
            if self.governor is not None:
                self._ladder(delta)
            self.upload_time += time.perf_counter() - t0
            self.last = delta
            cache = self.cache  # what it holds now, so the server can check its mirror
            self.send(Ack(seq=delta.seq, t=item.t, rejected=changes.rejected, held=cache.held,
                          held_bytes=cache.held_bytes, digest=cache.digest))
        elif isinstance(item, Error):
            if item.code == "closed":  # an administrator ended the session: the run ends, no redial
                self.closed, self.run.close_reason = True, f"the server closed the session: {item.message}"
            else:
                self.run.errors.append(item)
        elif isinstance(item, Closed):
            self._lost(item.reason)
        elif isinstance(item, Redialled):
            self._resumed(item)
        elif isinstance(item, GaveUp):
            self.closed, self.run.close_reason = True, item.reason
            if item.error is not None:
                self.run.errors.append(item.error)
        else:
            self.run.errors.append(Error(code="bad_state", message=f"unexpected {item.type} during the session"))

    def _lost(self, reason: str) -> None:
        """The current connection ended while the run has time left: redial, or end the run saying why."""
        link = self.link
        self.ws, self.failing = None, False
        if link is None:
            self.closed, self.run.close_reason = True, reason
            return
        self.count_connection(link.counter)
        now = time.monotonic() - self.start
        if not link.can_redial:
            link.ws = None
            why = ("reconnecting is off (reconnect_timeout=0)" if link.patience <= 0
                   else "the server offers no resume (its welcome carried no token)")
            self.closed, self.run.close_reason = True, reason
            self.run.errors.append(Error(code="connection_lost",
                                         message=f"{reason} at t={now:.2f} s; {why}"[:4096]))
            return
        link.redial(self.cache.held_reps(), self.cache.seq, now, reason, self.inbox)

    def count_connection(self, counter: list[int]) -> None:
        """Fold one finished connection's counters into the run."""
        self.run.bytes_per_connection.append(counter[0])
        self.run.pings += counter[1]
        self.run.deltas_per_connection.append(counter[2])

    def _resumed(self, item: Redialled) -> None:
        """A redial was welcomed: the new connection carries on the session (or a fresh one that kept the cache)."""
        link = self.link
        assert link is not None
        w = item.welcome
        self.run.reconnects.append(Reconnect(
            lost_at=link.lost_at, resumed_at=time.monotonic() - self.start, resumed=w.resumed, held=link.held,
            welcome_held=w.held, session=w.session, attempts=item.attempts, reason=link.reason, url=item.url))
        link.attach(item.ws, w, item.nbytes, self.inbox, url=item.url or None)
        self.ws = item.ws

    def _schedule(self, delta: Delta, arrived: float) -> None:
        """Hand the delta's schedule to the executors and build the morph targets it will draw."""
        reps, levels = self.cache.levels(delta.selection)
        if delta.algorithm:
            sel = np.asarray(delta.selection, np.int64)
            alg = np.asarray(delta.algorithm, np.int64)[np.isin(sel, reps)]  # aligned with ``reps``
            keys = reps - levels.astype(np.int64)
            order = np.argsort(keys, kind="stable")
            gen = (delta.t0, keys[order], alg[order])
            if delta.reset or delta.start is None:
                self._algorithms = [gen]
            else:
                self._algorithms = [g for g in self._algorithms if g[0] < delta.t0][-1:] + [gen]
        elif delta.reset or delta.start is None:
            self._algorithms = []
        m = delta.morphs
        to = np.asarray(m.level_to, np.float64)
        key = np.asarray(m.rep, np.int64) - to.astype(np.int64)
        start = delta.t0 if delta.start is None else delta.start
        late = self.schedule.apply(start, delta.t0, reps - levels.astype(np.int64), levels,
                                   (key, np.asarray(m.level_from), to, np.asarray(m.t0), np.asarray(m.t1)),
                                   reset=delta.reset or delta.start is None, now=arrived)
        self.run.late += int(late)
        r = delta.ramps
        self.vegetation.apply(start, delta.t0, np.asarray(delta.vegetation, np.int64), np.asarray(delta.resolution),
                              (np.asarray(r.rep, np.int64), np.asarray(r.level_from), np.asarray(r.level_to),
                               np.asarray(r.t0), np.asarray(r.t1)),
                              reset=delta.reset or delta.start is None, now=arrived)
        # Every level a ramp passes through is drawn morphed from the one below it.
        lo = np.minimum(np.asarray(m.level_from), to)
        hi = np.maximum(np.asarray(m.level_from), to)
        for k0, a, b in zip(key.tolist(), lo.tolist(), hi.tolist()):
            for level in range(int(a) + 1, int(b) + 1):
                rep = k0 + level
                if rep in self.cache and not self.renderer.has_morph_target(rep):
                    self._give_morph_target(rep)

    def _give_morph_target(self, rep: int) -> None:
        """Give an uploaded level its morph target, where the cache holds the level below it."""
        targets = self.cache.morph_targets(rep)
        if targets is not None:
            self.renderer.set_morph_target(rep, targets, self.cache.morph_target_colours(rep),
                                           merge=self.cache.resident[rep].morph)

    def _ladder(self, delta: Delta) -> None:
        """Give the governor the delta's ladder, over the steps whose both ends the cache holds (a chain stops at
        a level it lacks). The morph targets a step needs are made when the governor first draws it
        (``governed``): most steps of a ladder are never taken, and making them all would stall the frame
        loop on every delta."""
        rep = np.asarray(delta.ladder_rep, np.int64)
        to = np.asarray(delta.ladder_to, np.int64)
        held = self.cache.holds(rep) & self.cache.holds(to)
        rep, to = rep[held], to[held]
        reps, levels = self.cache.levels(rep.tolist())
        if reps.size != rep.size:  # a tree group or an unknown kind: no steps for it
            keep = np.isin(rep, reps)
            rep, to, held_idx = rep[keep], to[keep], np.nonzero(held)[0][keep]
        else:
            held_idx = np.nonzero(held)[0]
        cost = np.asarray(delta.ladder_cost, np.float64)[held_idx]
        value = np.asarray(delta.ladder_value, np.float64)[held_idx]
        key = reps - levels.astype(np.int64)
        self.governor.take(GovernorLadder.build(delta.t0, key, to - rep, cost, value, delta.ladder_base, levels),
                           reset=delta.reset or delta.start is None)

    def _expect(self, d: Drawn, view: tuple) -> None:
        """Tell the governor what the last frame's levels draw from the camera about to draw."""
        rep = d.rep
        last = self._last_rows
        if last is not None and last[0].size == d.key.size and np.array_equal(last[0], d.key):
            rep = last[1]  # the same rows as the last frame (most frames): no lookup
        elif last is not None and last[0].size and d.key.size:
            order = np.argsort(last[0], kind="stable")
            k = last[0][order]
            p = np.searchsorted(k, d.key)
            pc = np.minimum(p, k.size - 1)
            found = (p < k.size) & (k[pc] == d.key)
            rep = np.where(found, last[1][order][pc], d.rep)
        seen, vertices = self.renderer.in_view(rep, *view)
        self.governor.expect(float(vertices[seen].sum()), d.key[seen])

    def governed(self, t: float, d: Drawn) -> Drawn:
        """The schedule's rows with the governor's levels, where what they draw is resident (else as planned)."""
        gov = self.governor
        if gov is None:
            return d
        level = gov.apply(t, d.key, d.level)
        changed = level != d.level
        if not changed.any():
            return d
        k = np.maximum(np.ceil(level - 1e-9), 0.0)
        rep = d.key + k.astype(np.int64)
        weight = np.where(k > 0, np.clip(level - (k - 1.0), 0.0, 1.0), 1.0)
        weight = np.where(weight <= 1e-12, 0.0, weight)
        # Drawn only where resident and, when morphing, with its morph target (the ladder's steps have theirs;
        # a schedule mid-ramp that the governor pushes past its step does not).
        ok = self.cache.holds(rep)
        morph = ok & changed & (weight < 1.0)
        if morph.any():
            has = self.renderer.have_morph_targets(rep[morph])
            if not has.all():  # a level the schedule's own ramp passes: its target, once, where both levels are here
                for r in np.unique(rep[morph][~has]).tolist():
                    self._give_morph_target(r)
                has = self.renderer.have_morph_targets(rep[morph])
            ok[np.nonzero(morph)[0][~has]] = False
        ok |= ~changed
        self.governor_refused = int((~ok).sum())
        if self.governor_refused:
            gov.hold(d.key[~ok], np.zeros(self.governor_refused))
        return Drawn(d.key, np.where(ok, level, d.level), np.where(ok, rep, d.rep), np.where(ok, weight, d.weight))

    def drawn(self, t: float, view: tuple | None = None):
        """Representations, morph weights and the full schedule rows to draw at client time t (``view``: the
        camera about to draw, (eye, forward, up, near, far), for the governor's prediction)."""
        self.schedule.advance(t)
        d = self.schedule.at(t)
        if view is not None and self.governor is not None:
            self._expect(d, view)
        d = self.governed(t, d)
        self._last_rows = (d.key, d.rep)
        here = self.cache.holds(d.rep)
        self.run.skipped += int((~here).sum())
        return d, d.rep[here], d.weight[here]

    def algorithms(self, keys: np.ndarray, t: float) -> np.ndarray | None:
        """(s,) rendering algorithm of each object key at time t (the latest delta governing by then), or None."""
        while len(self._algorithms) > 1 and self._algorithms[1][0] <= t:
            self._algorithms.pop(0)
        if not self._algorithms:
            return None
        _, k, a = self._algorithms[0]
        if k.size == 0:
            return np.zeros(keys.size, np.int64)
        pos = np.minimum(np.searchsorted(k, keys), k.size - 1)
        return np.where(k[pos] == keys, a[pos], 0)

    def vegetation_at(self, t: float) -> None:
        """Give the splat layer the tree groups and resolutions the vegetation schedule draws at t."""
        if self.splats is None:
            return
        self.vegetation.advance(t)
        v = self.vegetation.at(t)
        x = np.clip(np.asarray(v.level, np.float64), 0.0, 1.0)
        keep = x > 0
        self.drawn_vegetation = (np.asarray(v.key, np.int64)[keep], x[keep])
        self.splats.set_resolutions(*self.drawn_vegetation)

    def pump(self, deadline: float | None) -> None:
        """Handle queued messages; with a deadline, wait for more until it (monotonic s)."""
        while not self.closed:
            try:
                if deadline is None:
                    item = self.inbox.get_nowait()
                else:
                    item = self.inbox.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                return
            self.handle(item)


@contextmanager
def quiet_collector() -> Iterator[None]:
    """Keep the cyclic garbage collector off the frame loop's critical path.

    A full (generation 2) collection scans every tracked object — the imported libraries' tens of
    thousands — and is long enough to land inside a frame, whose measured time the cost model would then
    take for the cost of that frame's work. Everything alive when the loop starts is frozen
    (``gc.freeze``), so later collections scan only what the run itself made; it is unfrozen afterwards,
    so what becomes garbage later is collected again as usual.
    """
    gc.collect()
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def run_frames(
    loop: FrameLoop,
    welcome: Welcome,
    start: float,
    duration: float,
    period: float,
    on_frame: Callable[[FrameRecord], None] | None,
    trace: bool = False,
    *,
    window=None,
    navigator: Navigator | None = None,
    tour_keys: list[dict] | None = None,
    director: "Director | None" = None,
) -> None:
    """The frame loop proper; returns after ``duration`` s, when the connection ends or the window closes.

    With a ``navigator`` the user's input moves the camera, from the welcome's start pose. A ``director``
    (a kiosk's, ``client.kiosk.director``) moves it instead: it is told the session began (``begin``), gives
    each frame's pose (``pose_at``) and messages to send (``outgoing``), and gets each drawn frame
    (``drawn``), after the timed draw and before it is shown, to draw over; its ``done`` ends the loop.
    """
    if tour_keys is not None:
        tour = Tour(tour_keys)
    else:
        tour = Tour(welcome.tour) if welcome.tour else Tour([{"t": 0.0, **welcome.start.model_dump()}])
    if navigator is not None:
        navigator.place(welcome.start)
        tour = navigator
    if director is not None:
        director.begin(welcome, time.monotonic() - start, loop)
        tour = director
    bounds = welcome.bounds
    cache, renderer = loop.cache, loop.renderer
    first = time.monotonic()
    frame = 0
    report: FrameReport | None = None  # the last frame's, sent with the next pose
    while not loop.closed and not (director is not None and director.done):
        now = time.monotonic()
        if now - first >= duration:
            break
        t = now - start
        eye, forward, up = tour.pose_at(t)
        # While the link is down, sends are skipped and frames go on from what is resident.
        # The last frame's report rides with this pose: one message a frame (``Camera.report``).
        loop.send(Camera(t=t, eye=eye.tolist(), forward=forward.tolist(), up=up.tolist(), report=report))
        report = None
        if director is not None:
            for msg in director.outgoing(t):
                loop.send(msg)
        loop.pump(None)
        far = far_plane(eye, bounds)
        rows, reps, weights = loop.drawn(t, (eye, forward, up, NEAR, far))
        here = cache.holds(rows.rep)
        loop.vegetation_at(t)
        layers = (loop.splats,) if loop.splats is not None else ()
        drawn_algorithms = loop.algorithms(rows.key[here], t)
        stats = renderer.draw(reps, eye, forward, up, NEAR, far, weights=weights,
                              algorithms=drawn_algorithms, levels=rows.level[here],
                              layers=layers)
        terms = stats.terms
        gov = loop.governor
        if gov is not None:
            drew = (gov.down, gov.up, gov.units, gov.predicted, gov.binding, gov.steer, gov.ledger.quantile())
            keys = rows.key[here]
            gov.observe(stats.time, stats.vertices, keys if stats.seen is None else keys[stats.seen])
        else:
            drew = (0, 0, 0.0, 0.0, False, 0.0, 0.0)
        report = FrameReport(
            frame=frame, t=t, time=min(max(stats.time, 1e-9), 60.0), triangles=stats.triangles,
            vertices=stats.vertices, draws=stats.draws, selection=cache.seq, pixels=stats.pixels,
            splats=stats.splats, gpu_time=None if stats.gpu_time is None else min(stats.gpu_time, 60.0),
            cpu_time=min(stats.cpu_time, 60.0),
            terms=None if terms is None else AlgorithmTerms(
                triangles=terms.triangles, vertices=terms.vertices, pixels=terms.pixels, draws=terms.draws),
            governor_down=drew[0], governor_up=drew[1], governor_cost=min(max(drew[2], 0.0), MAX_LADDER_VERTICES),
            governor_spare=gov is not None and not drew[4],
        )
        last = loop.last
        record = FrameRecord(
            frame=frame, t=t, time=stats.time, triangles=stats.triangles, vertices=stats.vertices,
            draws=stats.draws, seq=cache.seq, cost_coeff=last.cost_coeff if last else 0.0,
            budget=last.budget if last else 0.0, predicted_cost=last.predicted_cost if last else 0.0,
            upload_time=loop.upload_time, morphs=stats.morphs, pixels=stats.pixels, splats=stats.splats,
            gpu_time=stats.gpu_time, cpu_time=stats.cpu_time, prepare_time=stats.prepare_time,
            terms=None if terms is None else {"triangles": list(terms.triangles), "vertices": list(terms.vertices),
                                              "pixels": list(terms.pixels), "draws": list(terms.draws)},
            bytes=loop.applied_bytes, compute=last.compute if last else 0.0,
            governor_down=drew[0], governor_up=drew[1], governor_cost=drew[2], governor_predicted=drew[3],
            governor_bound=bool(drew[4]), governor_aim=float(drew[5]), governor_quantile=float(drew[6]),
        )
        if trace:
            veg, res = loop.drawn_vegetation
            loop.run.trace.append(FrameTrace(
                t, rows.key, rows.level, rows.rep, rows.weight, eye=np.asarray(eye, np.float64).copy(),
                forward=np.asarray(forward, np.float64).copy(), up=np.asarray(up, np.float64).copy(), drawn=here,
                algorithm=None if drawn_algorithms is None else np.asarray(drawn_algorithms, np.int64),
                vegetation=veg, resolution=res))
        loop.upload_time = 0.0
        loop.applied_bytes = 0
        loop.run.frames.append(record)
        if director is not None:
            director.drawn(t, record)
        if on_frame is not None:
            on_frame(record)
        frame += 1
        if window is not None:
            window.present(renderer)
            window.poll()
            if window.should_close:
                break
        loop.pump(now + period if period > 0 else None)
    if report is not None and not loop.closed:
        loop.send(report)  # the last frame has no pose after it
