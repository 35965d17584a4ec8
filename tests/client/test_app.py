"""run_client against a tiny in-test protocol server on loopback: reports carry what was drawn."""

from __future__ import annotations

import socket
import threading
from pathlib import Path
from typing import Iterator

import numpy as np
import pytest
import trimesh
from websockets.sync.server import Server, ServerConnection, serve

from client.app import run_client
from client.connection import ClientError
from client.records import FrameRecord
from proto.codec import decode_client, encode
from proto.geometry import encode_geometry
from proto.messages import (
    PROTOCOL_VERSION, Camera, Delta, Error, FrameReport, Hello, Pose, RepresentationAdd, TourKey, Welcome,
)

SPHERES = {10: (1, trimesh.creation.icosphere(1)), 11: (2, trimesh.creation.icosphere(2))}
TRIANGLES = sum(len(m.faces) for _, m in SPHERES.values())
VERTICES = sum(len(m.vertices) for _, m in SPHERES.values())


def _welcome() -> Welcome:
    f, u = [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]
    return Welcome(
        session="s1", protocol=PROTOCOL_VERSION, scene="tiny", bounds=[[-3, -3, -3], [3, 3, 3]],
        start=Pose(eye=[0, 0, 6], forward=f, up=u), tau=0.5, solver="greedy",
        tour=[TourKey(t=0, eye=[0, 0, 6], forward=f, up=u), TourKey(t=2, eye=[1, 0, 6], forward=f, up=u)],
    )


def _delta() -> Delta:
    adds = [
        RepresentationAdd(
            rep=rep, object=obj, level=0,
            geometry=encode_geometry(m.vertices + [2 * i - 1, 0, 0], m.faces),
        )
        for i, (rep, (obj, m)) in enumerate(SPHERES.items())
    ]
    return Delta(seq=7, t0=0, t1=0.5, add=adds, selection=[10, 11], budget=0.05, predicted_cost=0.01, cost_coeff=1.5e-7)


class Recorder:
    """A protocol server in miniature: welcome, then one delta after the first camera; records the rest."""

    def __init__(self, refuse: bool = False, tour: bool = True, close_after: int | None = None) -> None:
        self.refuse, self.tour, self.close_after = refuse, tour, close_after
        self.hello: Hello | None = None
        self.messages: list[Camera | FrameReport] = []
        self.done = threading.Event()

    def handler(self, ws: ServerConnection) -> None:
        try:
            self.hello = decode_client(ws.recv())  # type: ignore[assignment]
            if self.refuse:
                ws.send(encode(Error(code="unknown_scene", message="no scene named tiny")))
                return
            welcome = _welcome() if self.tour else _welcome().model_copy(update={"tour": []})
            ws.send(encode(welcome))
            sent = False
            for data in ws:
                msg = decode_client(data)
                self.messages.append(msg)  # type: ignore[arg-type]
                if isinstance(msg, Camera) and not sent:
                    ws.send(encode(_delta()))
                    ws.send(encode(Error(code="internal", message="just testing")))
                    sent = True
                report = msg.report if isinstance(msg, Camera) else msg
                if self.close_after is not None and isinstance(report, FrameReport) \
                        and report.frame + 1 >= self.close_after:
                    ws.close()
        finally:
            self.done.set()


def _serve(recorder: Recorder) -> Iterator[tuple[Recorder, str]]:
    # No flow control on the test server's side: a handler that closes while an uncapped client streams
    # reports would otherwise stop reading at the queue's high-water mark and never read the client's
    # close frame (websockets' sync close then times out after 10 s).
    srv: Server = serve(recorder.handler, "127.0.0.1", 0, max_queue=None)
    thread = threading.Thread(target=srv.serve_forever, daemon=True)
    thread.start()
    try:
        yield recorder, f"ws://127.0.0.1:{srv.socket.getsockname()[1]}"
    finally:
        srv.shutdown()
        thread.join(5)


@pytest.fixture
def server() -> Iterator[tuple[Recorder, str]]:
    yield from _serve(Recorder())


def test_run_client_reports_what_it_drew(server: tuple[Recorder, str], tmp_path: Path) -> None:
    recorder, url = server
    seen: list[FrameRecord] = []
    run = run_client(
        url, "tiny", duration=1.0, viewport=(160, 90), target_frame_time=0.04, on_frame=seen.append,
        screenshot=tmp_path / "last.png", max_fps=60.0,
    )
    assert recorder.done.wait(5)
    assert recorder.hello is not None and recorder.hello.scene == "tiny" and recorder.hello.viewport == [160, 90]
    assert recorder.hello.target_frame_time == 0.04

    assert run.welcome.session == "s1" and run.deltas_received == 1 and run.bytes_received > 1000
    assert [e.code for e in run.errors] == ["internal"] and run.close_reason is None
    assert run.frames == seen and 20 < len(run.frames) <= 70  # paced at 60 fps for 1 s
    drawn = [f for f in run.frames if f.seq == 7]
    assert drawn and all((f.triangles, f.vertices, f.draws) == (TRIANGLES, VERTICES, 2) for f in drawn)
    assert all(f.cost_coeff == 1.5e-7 and f.budget == 0.05 and f.predicted_cost == 0.01 for f in drawn)
    assert all(f.triangles == 0 and f.cost_coeff == 0.0 for f in run.frames if f.seq == -1)
    assert sum(f.upload_time for f in run.frames) > 0

    # One message a frame: each pose carries the frame before it's report; the last frame's comes alone.
    cameras = [m for m in recorder.messages if isinstance(m, Camera)]
    alone = [m for m in recorder.messages if isinstance(m, FrameReport)]
    assert cameras[0].report is None and all(c.report is not None for c in cameras[1:])
    assert len(alone) == 1 and recorder.messages[-1] is alone[0]
    reports = [c.report for c in cameras[1:]] + alone
    assert len(reports) == len(cameras) == len(run.frames)
    assert [r.frame for r in reports] == list(range(len(reports)))
    assert [(r.triangles, r.selection) for r in reports if r.selection == 7] == [(TRIANGLES, 7)] * len(drawn)
    assert all(r.time == f.time for r, f in zip(reports, run.frames))
    ts = np.array([c.t for c in cameras])
    assert np.all(np.diff(ts) > 0) and np.allclose(ts, [r.t for r in reports])
    np.testing.assert_allclose(cameras[0].eye[0], ts[0] / 2, atol=1e-6)  # on the tour: x = t / 2
    assert (tmp_path / "last.png").stat().st_size > 100


def test_no_tour_holds_start_pose_and_server_close_ends_run() -> None:
    for recorder, url in _serve(Recorder(tour=False, close_after=3)):
        run = run_client(url, "tiny", duration=5.0, viewport=(64, 64), max_fps=None)
        assert recorder.done.wait(5)
    # The run ended on the close, long before the 5 s it asked for (uncapped frames: their count is the
    # machine's, so the end time says it, not a frame count).
    assert run.close_reason is not None and len(run.frames) >= 3 and run.frames[-1].t < 2.5
    cameras = [m for m in recorder.messages if isinstance(m, Camera)]
    assert all(c.eye == [0, 0, 6] and c.forward == [0, 0, -1] for c in cameras)


def test_refused_session_raises_client_error() -> None:
    recorder = Recorder(refuse=True)
    with serve(recorder.handler, "127.0.0.1", 0) as srv:
        thread = threading.Thread(target=srv.serve_forever, daemon=True)
        thread.start()
        with pytest.raises(ClientError, match="unknown_scene"):
            run_client(f"ws://127.0.0.1:{srv.socket.getsockname()[1]}", "tiny", duration=1.0, viewport=(64, 64))
        srv.shutdown()
    thread.join(5)


def test_unreachable_server_raises_client_error() -> None:
    with socket.socket() as sock:  # a port that was free a moment ago and has no listener now
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    with pytest.raises(ClientError, match="cannot connect"):
        run_client(f"ws://127.0.0.1:{port}", "tiny", duration=1.0, viewport=(64, 64), timeout=2.0)


def test_frames_run_with_the_startup_heap_frozen_out_of_the_collector(server: tuple[Recorder, str]) -> None:
    """A full collection over the libraries' objects was a 35–45 ms frame: during the frame loop they are
    frozen (``gc.freeze``), afterwards they are not."""
    import gc

    _, url = server
    frozen: list[int] = []
    run_client(url, "tiny", duration=0.5, viewport=(64, 64), max_fps=60.0,
               on_frame=lambda f: frozen.append(gc.get_freeze_count()))
    assert frozen and min(frozen) > 1000  # the imported libraries alone are tens of thousands of objects
    assert gc.get_freeze_count() == 0
