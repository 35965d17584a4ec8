"""The FastAPI service: ``/ws`` moves bytes between a websocket and a ``Session``.

The handler owns the clock and the socket and nothing else. A reader task
queues incoming frames; the main loop waits for a frame or for the session's
next deadline, whichever comes first, and sends what the session returns.
Selections run in a worker thread so that one session's solve never stalls the
event loop for the others.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import time
import uuid
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Mapping

from fastapi import FastAPI, WebSocket, WebSocketDisconnect

from proto.codec import MAX_CLIENT_FRAME, encode
from proto.messages import Error

from .scene.store import SceneStore
from .session import Session, SessionConfig

__all__ = ["create_app", "load_scenes", "serve"]

log = logging.getLogger("walkstream.server")

#: Frames above this are refused by the websocket layer itself (close 1009); between
#: MAX_CLIENT_FRAME and this, the codec answers with a ``too_large`` error frame.
WS_MAX_SIZE = 1024 * 1024
_TICK = object()
_GONE = object()


def load_scenes(paths: list[Path]) -> dict[str, SceneStore]:
    """Open scene stores by path; each is served under the name recorded in it."""
    scenes: dict[str, SceneStore] = {}
    for path in paths:
        store = SceneStore.open(path)
        name = store.index.name
        if name in scenes:
            raise ValueError(f"two stores name their scene {name!r}: {path} and another")
        scenes[name] = store
    return scenes


def create_app(scenes: Mapping[str, SceneStore], config: SessionConfig | None = None) -> FastAPI:
    config = config or SessionConfig()
    sessions: dict[str, Session] = {}

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        yield
        for store in scenes.values():
            store.close()

    app = FastAPI(title="walkstream", version="0.1.0", lifespan=lifespan)
    app.state.sessions = sessions

    @app.get("/health")
    async def health() -> dict:
        return {"status": "ok", "sessions": len(sessions), "scenes": sorted(scenes)}

    @app.get("/scenes")
    async def list_scenes() -> list[dict]:
        out = []
        for name, store in sorted(scenes.items()):
            idx = store.index
            last = idx.rep_first + idx.rep_count - 1
            out.append(
                {
                    "name": name,
                    "objects": int(idx.n_objects),
                    "representations": int(idx.n_representations),
                    "triangles_full_detail": int(idx.rep_faces[last].sum()),
                    "bounds": idx.bounds.tolist(),
                    "tour_seconds": float(idx.tour[-1]["t"]) if idx.tour else 0.0,
                }
            )
        return out

    @app.get("/sessions")
    async def list_sessions() -> list[dict]:
        return [s.stats for s in sessions.values()]

    @app.websocket("/ws")
    async def ws_endpoint(ws: WebSocket) -> None:
        await ws.accept()
        loop = asyncio.get_running_loop()
        session = Session(scenes, uuid.uuid4().hex, config)
        sessions[session.id] = session
        inbox: asyncio.Queue = asyncio.Queue(maxsize=256)

        async def reader() -> None:
            try:
                while True:
                    msg = await ws.receive()
                    if msg["type"] == "websocket.disconnect":
                        break
                    data = msg.get("bytes")
                    # Stamped on arrival: a pong's round trip must not include a selection it waited behind.
                    await inbox.put((data if data is not None else (msg.get("text") or ""), time.monotonic()))
            except (WebSocketDisconnect, RuntimeError, OSError):
                pass
            finally:
                await inbox.put(_GONE)

        def poll_encoded(now: float) -> list[bytes]:
            # Selection and the msgpack of a delta full of geometry both run off the event loop.
            return [encode(m) for m in session.poll(now)]

        read_task = asyncio.create_task(reader())
        try:
            while True:
                deadline = session.next_deadline()
                timeout = None if deadline is None else max(0.0, deadline - time.monotonic())
                try:
                    item = await asyncio.wait_for(inbox.get(), timeout)
                except asyncio.TimeoutError:
                    item = _TICK
                if item is _GONE:
                    break
                try:
                    if item is _TICK:
                        frames = await loop.run_in_executor(None, poll_encoded, time.monotonic())
                    else:
                        frames = [encode(m) for m in session.receive(*item)]
                except Exception:  # a bug of ours: log loudly, tell the client, keep the session
                    log.exception("session %s failed", session.id)
                    frames = [encode(Error(code="internal", message="the server failed handling that message"))]
                for frame in frames:
                    await ws.send_bytes(frame)
        except (WebSocketDisconnect, RuntimeError, OSError):
            pass  # the client went away mid-send: nothing to tell it
        finally:
            read_task.cancel()
            session.close()
            sessions.pop(session.id, None)

    return app


def serve(
    paths: list[Path],
    host: str = "127.0.0.1",
    port: int = 8765,
    config: SessionConfig | None = None,
    log_level: str = "warning",
    announce=print,
) -> None:
    """Run uvicorn on ``host:port`` (port 0: any free port, announced once listening)."""
    import uvicorn

    scenes = load_scenes(paths)
    app = create_app(scenes, config)
    sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind((host, port))
    sock.listen(128)  # connections queue in the backlog until uvicorn accepts them
    bound = sock.getsockname()[1]
    announce(f"walkstream: serving {', '.join(sorted(scenes))} on http://{host}:{bound} (websocket /ws)")
    server = uvicorn.Server(
        uvicorn.Config(app, log_level=log_level, ws_max_size=WS_MAX_SIZE, ws_ping_interval=20, ws_ping_timeout=20)
    )
    server.run(sockets=[sock])
