"""Batching changes what a tick costs, never what a session is sent: one scripted session alone and among
fifty others gets the same frames, byte for byte."""

from __future__ import annotations

import numpy as np
import pytest

from bench.loadtest.scripted import run_scripted
from server.scene.store import SceneStore
from server.session import Session, SessionConfig
from server.session.batch import poll_many


@pytest.fixture(scope="module")
def city(denhaag_store):
    store = SceneStore.open(denhaag_store)
    yield {store.index.name: store}
    store.close()


def _run(scenes, n: int, poll, seconds: float = 6.0):
    config = SessionConfig()
    # No stopwatch: every selection runs to completion and reports no compute time, so the frames depend on
    # the script alone.
    return run_scripted(scenes, n, seconds, make_session=lambda i: Session(scenes, f"s{i:03d}", config),
                        poll=poll, only=0, algorithms=("flat", "lit"), tick=0.05, stagger=0.1)


def test_a_session_gets_the_same_deltas_alone_and_among_fifty_others(city):
    alone = _run(city, 1, None)
    batched = []

    def poll(sessions, now):
        batched.append(len(sessions))
        return poll_many(sessions, now)

    crowd = _run(city, 51, poll)
    frames = alone.frames[0]
    deltas = [f for f in frames if len(f) > 64]
    assert len(deltas) >= 8  # a reset and a regular delta every τ
    assert crowd.frames[0] == frames
    # Sessions of the crowd were due together (their selections then share a pass), not one by one.
    assert max(batched) >= 10


def test_a_batch_culls_and_projects_each_session_as_alone(city):
    """The shared pass gives every session the rows and projections its own culling and projection give."""
    from server.select import options
    from server.select.selection import _cameras, cull_many

    config = SessionConfig()
    sessions = {}

    def make(i):
        sessions[i] = Session(city, f"s{i:03d}", config)
        return sessions[i]

    requests = []

    def poll(due, now):
        reqs = [s.selection_request(now) for s in due]
        requests.extend(r for r in reqs if r is not None)
        return poll_many(due, now)

    run_scripted(city, 12, 3.0, make_session=make, poll=poll, tick=0.05, stagger=0.1)
    assert len(requests) >= 24
    culled = cull_many(requests)
    for (scene, view, solver, margin, memory, t), c in zip(requests, culled):
        cams = _cameras(view, margin, t)
        rows = np.nonzero(options.cull(scene.flat, cams))[0]
        before, dts = options._before(memory, cams)
        size, offset, speed = options.project(scene.flat, rows, cams, before, dts)
        assert np.array_equal(c.rows, rows)
        assert np.array_equal(c.projected[0], size) and np.array_equal(c.projected[1], offset)
        assert [None if x is None else x.tolist() for x in c.projected[2]] == [
            None if x is None else x.tolist() for x in speed]
