"""The FastAPI service: ``/ws`` moves bytes between a websocket and a ``Session``.

The handler owns the clock and the socket and nothing else. A reader task
(``server.connection``) stamps, counts and rate-limits incoming frames and
queues them, bounded in bytes; the session
loop waits for a frame, the session's next deadline or the idle timeout,
whichever comes first, and sends what the session returns. Selections (and the
encoding of their deltas) run in ticks on the event loop (``server.ticker``),
which yields between two sessions' polls so each delta goes out at once; hellos,
restores and snapshots outside a tick run in the app's thread pool. The loop awaits each send
before it polls again: a client that does not read makes only its own session
wait (uvicorn's send waits while the transport's buffer is full).

Kiosks' heartbeats feed the fleet (``server.fleet``), shown at ``/fleet`` (HTML), ``/fleet.json`` and as
per-kiosk gauges at ``/metrics``; like ``/sessions`` they cover every worker of the replica.

Session state is saved to a ``StateStore`` after deltas, acks and frames that
changed it (at most every ``ReplicaLimits.save_interval``) and on disconnect, so a
client that lost its connection can resume on any replica sharing the store.
"""

from __future__ import annotations

import asyncio
import hmac
import logging
import os
import socket
import time
import uuid
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager
from typing import Callable, Mapping

from fastapi import Depends, FastAPI, HTTPException, Request, Response, WebSocket
from fastapi.responses import HTMLResponse, RedirectResponse
from pydantic import BaseModel

from proto.codec import decode_client, encode
from proto.errors import ProtocolError
from proto.messages import Delta, Error, Hello, Resume

from .admin import VIEW_COOKIE, AdminAuth
from .connection import CLOSE_POLICY, GONE, SOCKET_GONE, WAKE, Connection, error, read_frames
from .fair import FairPool
from .fleet import Fleet, merge
from .fleet_page import render as render_fleet
from .limits import MEASUREMENT_SOLVERS, WS_MAX_SIZE, Admission, RateGuard, ReplicaLimits, remote_address
from .metrics import CONTENT_TYPE_LATEST, Metrics
from .peers import Peers
from .scene.store import SceneStore
from .scene.tour import named_tours
from .session import Session, SessionConfig, SessionState
from .session.payloads import packed
from .session.table import SceneTable
from .startup import ServeError, load_scenes
from .state import MemoryStateStore, StateStore
from .ticker import Ticker

__all__ = ["create_app", "load_scenes", "ServeError", "WS_MAX_SIZE"]

log = logging.getLogger("walkstream.server")

_TICK = object()

#: Websocket close codes: normal, policy violation (flooding), try again later (busy).
CLOSE_NORMAL, CLOSE_RESTART, CLOSE_BUSY = 1000, 1012, 1013
#: Seconds between two reloads of the fleet page.
FLEET_REFRESH = 3


def create_app(
    scenes: Mapping[str, SceneStore],
    config: SessionConfig | None = None,
    *,
    state: StateStore | None = None,
    limits: ReplicaLimits | None = None,
    admin_token: str | None = None,
    replica: str | None = None,
    stopwatch: Callable[[], float] = time.perf_counter,
    peers: Peers | None = None,
) -> FastAPI:
    """The service for ``scenes``; ``state`` keeps session state for resumes (default: in this process's memory).

    ``stopwatch`` is the clock every session's selection is timed by (its deadline, the compute time it reports).
    ``peers``: the replica's other worker processes (``server.workers``), whose sessions ``/sessions`` lists too.
    """
    config = config or SessionConfig()
    limits = limits or ReplicaLimits()
    store: StateStore = state if state is not None else MemoryStateStore()
    replica = replica or socket.gethostname()
    for s in scenes.values():  # what every session of a scene shares, built once, before any session
        SceneTable.of(s.index).prepare(config.importance)
    conns: dict[str, Connection] = {}
    sessions: dict[str, Session] = {}  # the same, by session (tests and /sessions look here)
    metrics = Metrics(lambda: len(conns))
    fleet = Fleet()
    worker = os.getpid()

    def kiosk_rows() -> list[dict]:
        return [{**row, "worker": worker} for row in fleet.rows(time.monotonic())]
    metrics.watch_fleet(kiosk_rows)
    auth = AdminAuth(admin_token)
    admission = Admission(limits)

    def n_sessions() -> int:  # connections that said their hello: the ones holding a session slot
        return sum(1 for c in conns.values() if c.slot or c.session.state is not SessionState.AWAIT_HELLO)
    pool = ThreadPoolExecutor(max_workers=limits.threads, thread_name_prefix="walkstream-select")
    # What each session spent on its selections: a session that spends more than its neighbours waits behind
    # them in the ticks (which run on the event loop, so the ledger needs no threads of its own).
    fair = FairPool(0, name="walkstream-fair")

    def poll_encoded(session: Session, now: float, culled) -> tuple[list[tuple[bytes, str | None]], bool, float,
                                                                     bytes | None]:
        """In a tick (``ticker``): run what is due, encode it, and snapshot the state if a delta went out and the
        last save is ``save_interval`` old (a later one then saves it: the session stays dirty)."""
        began = time.thread_time()
        out = session.poll(now, culled)
        frames = [(encode(m, packed=packed), m.code if isinstance(m, Error) else None) for m in out]
        delta = any(isinstance(m, Delta) for m in out)
        cpu = time.thread_time() - began
        conn = conns.get(session.id)
        due = conn is None or time.monotonic() >= conn.last_save + limits.save_interval
        blob = session.snapshot() if delta and due else None
        return frames, delta, cpu, blob

    # Polls that fall due together run as one tick: their selections culled and projected in one pass.
    ticker = Ticker(fair, poll_encoded, observe=metrics.tick)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        refresh = asyncio.create_task(metrics.keep_fresh())
        try:
            yield
        finally:
            refresh.cancel()
            metrics.close()
            for conn in list(conns.values()):
                # Not "closed" (an administrator's end of the session): a client redials and resumes elsewhere.
                conn.request_close("busy", CLOSE_RESTART, "the server is shutting down; reconnect to resume")
            fair.shutdown()
            pool.shutdown(wait=True, cancel_futures=True)
            try:
                await store.close()
            except Exception:
                log.exception("closing the state store failed")
            for s in scenes.values():
                s.close()

    # The interactive docs would load their page from a public CDN: off unless asked for.
    docs = limits.docs
    app = FastAPI(title="walkstream", version="0.2.0", lifespan=lifespan, docs_url="/docs" if docs else None,
                  redoc_url=None, openapi_url="/openapi.json" if docs else None)
    app.state.sessions = sessions
    app.state.connections = conns
    app.state.metrics = metrics
    app.state.limits = limits
    app.state.store = store
    app.state.pool = pool
    app.state.fair = fair
    app.state.ticker = ticker
    app.state.fleet = fleet

    def register(conn: Connection) -> None:
        conns[conn.session.id] = conn
        sessions[conn.session.id] = conn.session

    def unregister(conn: Connection) -> None:
        sid = conn.session.id
        if conns.get(sid) is conn:
            del conns[sid]
            sessions.pop(sid, None)

    # ------------------------------------------------------------------ REST

    require_admin = auth.require

    @app.get("/health")
    async def health() -> dict:
        sessions_now = n_sessions()
        return {"status": "ok", "replica": replica, "sessions": sessions_now, "connections": len(conns),
                "pending": len(conns) - sessions_now, "max_sessions": limits.max_sessions, "scenes": sorted(scenes), "worker": os.getpid()}

    @app.get("/scenes")
    async def list_scenes() -> list[dict]:
        out = []
        for name, s in sorted(scenes.items()):
            idx = s.index
            last = idx.rep_first + idx.rep_count - 1
            out.append(
                {
                    "name": name,
                    "objects": int(idx.n_objects),
                    "representations": int(idx.n_representations),
                    # As ``walkstream inspect`` counts: the scene's own objects, not the HLOD proxies over them.
                    "triangles_full_detail": int(idx.rep_faces[last[idx.flat]].sum()),
                    "bounds": idx.bounds.tolist(),
                    "tour_seconds": float(idx.tour[-1]["t"]) if idx.tour else 0.0,
                    # What a hello's ``tour`` may name.
                    "tours": {n: {"kind": t["kind"], "duration": t["duration"]} for n, t in named_tours(idx).items()},
                }
            )
        return out

    @app.get("/metrics")
    async def prometheus() -> Response:
        return Response(metrics.render(), media_type=CONTENT_TYPE_LATEST)

    @app.get("/sessions", dependencies=[Depends(require_admin)], include_in_schema=False)
    async def list_sessions(request: Request, local: bool = False) -> list[dict]:
        """This replica's sessions: this worker's, and (unless ``local``) every other worker's."""
        now = time.monotonic()
        rows = [{**c.info(now), "selection_cpu_s": round(fair.total(c.session.id), 4),
                 "selection_cpu_recent_s": round(fair.spent(c.session.id), 4), "worker": os.getpid()}
                for c in conns.values()]
        if peers is not None and not local:
            auth = {"authorization": request.headers.get("authorization", "")}
            for status, body in await peers.ask("GET", "/sessions", auth):
                rows += body if status == 200 and isinstance(body, list) else []
        return rows

    @app.delete("/sessions/{session_id}", dependencies=[Depends(require_admin)], include_in_schema=False)
    async def close_session(session_id: str, request: Request, local: bool = False) -> dict:
        conn = conns.get(session_id)
        if conn is None and peers is not None and not local:  # held by another worker of this replica?
            auth = {"authorization": request.headers.get("authorization", "")}
            for status, body in await peers.ask("DELETE", f"/sessions/{session_id}", auth):
                if status == 200:
                    return body
        if conn is None:
            raise HTTPException(404, f"no session {session_id!r} on this replica")
        conn.request_close("closed", CLOSE_NORMAL)
        try:
            await asyncio.wait_for(conn.done.wait(), 5.0)
        except asyncio.TimeoutError:  # stuck in a send to a client that does not read: keepalive ends it
            return {"session": session_id, "closed": False}
        return {"session": session_id, "closed": True}

    async def fleet_data(local: bool) -> dict:
        """This worker's kiosks and live sessions, and (unless ``local``) every other worker's, merged."""
        now = time.monotonic()
        keys = ("session", "kiosk", "scene", "state", "frames", "selections", "connected_s", "idle_s")
        mine = {"kiosks": kiosk_rows(),
                "sessions": [{**{k: info.get(k) for k in keys}, "worker": worker}
                             for info in (c.info(now) for c in conns.values())
                             if info.get("state") != SessionState.AWAIT_HELLO.value]}
        parts = [mine]
        if peers is not None and not local:
            parts += [body for status, body in await peers.ask("GET", "/fleet.json", auth.peer_headers())
                      if status == 200 and isinstance(body, dict)]
        return merge(parts)

    @app.get("/fleet.json", dependencies=[Depends(auth.require_view)], include_in_schema=False)
    async def fleet_json(local: bool = False) -> dict:
        return {"replica": replica, **await fleet_data(local)}

    @app.get("/fleet", dependencies=[Depends(auth.require_view)], include_in_schema=False)
    async def fleet_page(request: Request, local: bool = False) -> Response:
        if auth.query_ok(request):  # from a typed URL: a cookie instead, and the token out of the address bar
            back = RedirectResponse("fleet?local=1" if local else "fleet", status_code=303)
            back.set_cookie(VIEW_COOKIE, auth.view_cookie(), max_age=12 * 3600, httponly=True, samesite="strict",
                            secure=request.url.scheme == "https")
            return back
        page = render_fleet(await fleet_data(local), replica, FLEET_REFRESH)
        return HTMLResponse(page, headers={"Cache-Control": "no-store"})

    # ------------------------------------------------------------------ state

    async def save(session: Session) -> None:
        """Snapshot (in a worker: it packs arrays) and store the session for a later resume."""
        if session.state is not SessionState.ACTIVE:
            return
        loop = asyncio.get_running_loop()
        try:
            blob = await loop.run_in_executor(pool, session.snapshot)
            if not await store.save(session.id, session.token, blob, limits.state_ttl, fence=session.fence):
                metrics.state_failures.labels("fenced").inc()  # resumed elsewhere since: that state wins
        except Exception as exc:
            metrics.state_failures.labels("save").inc()
            log.warning("saving session %s failed: %s", session.id, exc)

    async def resume(conn: Connection, ask: Resume, scene: str) -> str:
        """Take over session ``ask.session`` if the store has it, the token matches and it is of ``scene``;
        returns the outcome (``other_scene``: refused, and the saved state is left as it was)."""
        try:
            found = await store.load(ask.session)
        except Exception as exc:
            metrics.state_failures.labels("load").inc()
            log.warning("loading session %s failed: %s", ask.session, exc)
            return "not_found"
        if found is None:
            return "not_found"
        if not hmac.compare_digest(found[0].encode(), ask.token.encode()):
            return "bad_token"
        loop = asyncio.get_running_loop()
        probe = Session(scenes, ask.session, config, stopwatch=stopwatch)
        try:
            await loop.run_in_executor(pool, probe.restore, found[1])
        except ValueError:
            pass  # the restore below says so, and starts afresh
        else:
            if probe.restored_scene != scene:
                conn.refused_resume = probe.restored_scene
                return "other_scene"
        finally:
            probe.close()
        old = conns.get(ask.session)
        if old is not None and old is not conn:
            # The old connection is not yet noticed as dead: end it, and take the state it saves on leaving.
            old.request_close("closed", CLOSE_NORMAL, "the session was resumed on another connection")
            try:
                await asyncio.wait_for(old.done.wait(), 5.0)
            except asyncio.TimeoutError:
                log.warning("session %s: the old connection did not end in time; resuming from the last save",
                            ask.session)
            found = await store.load(ask.session) or found
        # A new token for the new owner (the welcome carries it); saves are fenced by the one resumed from, so
        # the old owner's late saves — under the old token — no longer overwrite this session's state.
        session = Session(scenes, ask.session, config, stopwatch=stopwatch)
        session.fence = found[0]
        try:
            await loop.run_in_executor(pool, session.restore, found[1])
        except ValueError as exc:
            log.warning("session %s: saved state does not restore (%s); starting afresh", ask.session, exc)
            return "corrupt"
        unregister(conn)
        conn.session = session
        conn.resumed = True
        register(conn)
        return "resumed"

    # ------------------------------------------------------------------ websocket

    @app.get("/ws", include_in_schema=False)
    async def ws_over_http() -> Response:
        """A plain HTTP GET of the websocket's path: say what it is rather than 404."""
        return Response("this is walkstream's websocket endpoint: connect with a websocket client "
                        "(ws:// or wss://), e.g. `walkstream client ws://HOST:PORT/ws`\n",
                        status_code=426, headers={"Upgrade": "websocket"}, media_type="text/plain")

    async def refuse(ws: WebSocket, reason: str, code: str, close_code: int, message: str) -> None:
        metrics.refused.labels(reason).inc()
        metrics.errors.labels(code).inc()
        try:
            await ws.send_bytes(encode(error(code, message)))
            await ws.close(close_code)
        except SOCKET_GONE:
            pass

    @app.websocket("/ws")
    async def ws_endpoint(ws: WebSocket) -> None:
        address = remote_address(ws.client.host if ws.client else None, ws.headers, limits.trusted_proxies)
        await ws.accept()
        refusal = admission.admit(address, time.monotonic(), n_sessions(), len(conns) - n_sessions())
        if refusal is not None:
            reason, message = refusal
            return await refuse(ws, reason, "busy", CLOSE_BUSY if reason in ("busy", "pending") else CLOSE_POLICY,
                                message)
        try:
            await serve_connection(ws, address)
        finally:
            admission.release(address)

    async def serve_connection(ws: WebSocket, address: str) -> None:
        loop = asyncio.get_running_loop()
        now = time.monotonic()
        conn = Connection(ws, Session(scenes, uuid.uuid4().hex, config, stopwatch=stopwatch), now, address)
        register(conn)
        guard = RateGuard(limits, now)

        async def send(frames: list[tuple[bytes, str | None]]) -> None:
            for frame, code in frames:
                conn.send_since = time.monotonic()
                await ws.send_bytes(frame)
                conn.send_since = None
                metrics.bytes_out.inc(len(frame))
                if code is not None:
                    metrics.errors.labels(code).inc()

        def encoded(messages: list[BaseModel]) -> list[tuple[bytes, str | None]]:
            return [(encode(m, packed=packed), m.code if isinstance(m, Error) else None) for m in messages]

        async def first(data, t: float) -> list[BaseModel]:
            """A frame before the session is open: a hello (resumed if it asks and may) or a refusal."""
            try:
                message = decode_client(data)
            except ProtocolError:
                return conn.session.receive(data, t)  # answers with the error frame and counts it
            if isinstance(message, Hello):
                if n_sessions() >= limits.max_sessions:
                    metrics.refused.labels("busy").inc()
                    conn.request_close("busy", CLOSE_BUSY, f"this replica serves its maximum of "
                                       f"{limits.max_sessions} sessions; try another or later")
                    return []
                conn.slot = True  # taken before the first await: hellos that come together cannot all pass
                try:
                    return await opened(message, t)
                finally:  # from here the session's own state holds the slot, or the hello failed
                    conn.slot = False
            return conn.session.receive(message, t)

        async def opened(message: Hello, t: float) -> list[BaseModel]:
            """A hello within the session limit: refused, resumed or fresh."""
            if message.solver in MEASUREMENT_SOLVERS and not limits.allow_measurement_solvers:
                return [error("solver_refused", f"solver {message.solver!r} is for measurement only; this "
                               "replica offers it to clients only when started with --allow-measurement-solvers")]
            outcome = "fresh" if message.resume is None else await resume(conn, message.resume, message.scene)
            metrics.resumes.labels(outcome).inc()
            if outcome == "other_scene":
                return [error("bad_state", f"session {message.resume.session} is of scene "
                               f"{conn.refused_resume!r}, not {message.scene!r}: resume it with scene "
                               f"{conn.refused_resume!r} (its state is kept), or say hello without resume")]
            # A hello builds the session's scene tables: off the loop.
            return await loop.run_in_executor(pool, conn.session.receive, message, t)

        read_task = asyncio.create_task(read_frames(ws, conn, guard, limits, metrics))
        try:
            while True:
                if conn.gone:
                    break
                if conn.closing is not None:
                    code, close_code, text = conn.closing
                    await send(encoded([error(code, text)]))
                    await ws.close(close_code)
                    break
                session = conn.session
                deadline = session.next_deadline()
                now = time.monotonic()
                wake = conn.last_heard + limits.idle_timeout
                if session.state is SessionState.AWAIT_HELLO:
                    wake = min(wake, conn.opened + limits.hello_timeout)
                if deadline is not None:
                    wake = min(wake, deadline)
                if session.dirty and session.state is SessionState.ACTIVE:
                    wake = min(wake, conn.last_save + limits.save_interval)
                # What arrived goes first: a due selection then reads the newest pose, never a stale one.
                item = await conn.inbox.get(wake - now, _TICK)
                if item is GONE:
                    break
                if item is WAKE:
                    continue
                try:
                    if item is _TICK:
                        now = time.monotonic()
                        if session.state is SessionState.AWAIT_HELLO and now >= conn.opened + limits.hello_timeout:
                            metrics.refused.labels("no_hello").inc()
                            conn.request_close("no_hello", CLOSE_POLICY, f"no valid hello within "
                                                                         f"{limits.hello_timeout:g} s; closing")
                            continue
                        if now >= conn.last_heard + limits.idle_timeout:
                            metrics.refused.labels("idle").inc()
                            conn.request_close("idle", CLOSE_NORMAL, f"nothing heard for {limits.idle_timeout:g} s; "
                                                                     "the session is closed")
                            continue
                        if deadline is not None and now >= deadline:
                            frames, delta, cpu, blob = await ticker.poll(session)
                            await send(frames)
                            if delta:
                                metrics.selection_seconds.observe(time.monotonic() - deadline)
                                metrics.selection_cpu_seconds.observe(cpu)
                            if blob is not None:
                                conn.last_save = time.monotonic()
                                try:
                                    if not await store.save(session.id, session.token, blob, limits.state_ttl,
                                                            fence=session.fence):
                                        metrics.state_failures.labels("fenced").inc()
                                except Exception as exc:
                                    metrics.state_failures.labels("save").inc()
                                    log.warning("saving session %s failed: %s", session.id, exc)
                        elif session.dirty and now >= conn.last_save + limits.save_interval:
                            conn.last_save = now
                            await save(session)
                        continue
                    if isinstance(item, Error):  # the reader's rate_limited answer
                        await send(encoded([item]))
                        continue
                    data, t, size = item
                    conn.taken(size)
                    if session.state is SessionState.AWAIT_HELLO:
                        out = await first(data, t)
                    else:
                        out = session.receive(data, t)
                    if any(isinstance(m, Error) for m in out):  # refused: it never counts as being heard
                        conn.bad_frames += 1
                        if conn.bad_frames > limits.max_bad_frames:
                            metrics.refused.labels("bad_frames").inc()
                            conn.request_close("bad_frames", CLOSE_POLICY, f"more than {limits.max_bad_frames} "
                                               "refused frames on this connection; closing")
                    else:
                        conn.last_heard = max(conn.last_heard, t)
                        beat = conn.session.heartbeat
                        if beat is not None and beat is not conn.heartbeat:
                            conn.heartbeat = beat
                            metrics.heartbeats.inc()
                            fleet.heard(conn.session.id, beat, t)
                except SOCKET_GONE:
                    raise
                except Exception:  # a bug of ours: log loudly, tell the client, keep the session
                    log.exception("session %s failed", conn.session.id)
                    out = [error("internal", "the server failed handling that message")]
                await send(encoded(out))
                session = conn.session
                if session.dirty and time.monotonic() >= conn.last_save + limits.save_interval:
                    conn.last_save = time.monotonic()
                    await save(session)
        except SOCKET_GONE:
            pass  # the client went away mid-send: nothing to tell it
        finally:
            read_task.cancel()
            session = conn.session
            try:
                # On disconnect: the state a resume continues from — unless a newer connection took the session
                # over (it saves its own), or nothing changed since the last save (no stale write over a newer one).
                if conns.get(session.id) is conn and session.dirty:
                    await save(session)
            finally:
                session.close()
                fair.forget(session.id)
                if conns.get(session.id) is conn:  # not taken over by a newer connection, which reports it
                    fleet.closed(session.id, time.monotonic())
                unregister(conn)
                conn.done.set()

    return app

