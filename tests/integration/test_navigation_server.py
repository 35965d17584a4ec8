"""The navigation against a real server: the walkable grid in the welcome, and selecting along a tour plan.

``walkstream serve`` runs in its own process and scripted clients talk to it
over a loopback websocket (``Peer``); every wait is for a message.
"""

from __future__ import annotations

import numpy as np
import pytest

from bench.demo import ServerProcess
from proto.codec import encode
from proto.messages import Delta, TourKey, TourPlan
from proto.tour import Tour
from proto.walkable import decode
from server.scene.store import SceneStore

from .test_server_app import Peer


@pytest.fixture(scope="module")
def server(demo_store):
    with ServerProcess([demo_store]) as srv:
        yield srv


def test_a_hello_with_walkable_gets_the_scenes_grid(server, demo_store):
    with SceneStore.open(demo_store) as store:
        grid = store.walkable()
    peer = Peer(server.url, walkable=True)
    try:
        got = decode(peer.welcome.walkable)
    finally:
        peer.ws.close()
    assert got.shape == grid.shape and got.origin == grid.origin and got.cell == grid.cell
    both = np.isfinite(grid.ground)
    assert np.array_equal(np.isfinite(got.ground), both)
    assert np.allclose(got.ground[both], grid.ground[both], atol=2e-3)
    plain = Peer(server.url)
    plain.ws.close()
    assert plain.welcome.walkable is None


def test_a_session_sent_a_tour_plan_selects_for_the_plans_poses(server, demo_store):
    with SceneStore.open(demo_store) as store:
        tour = Tour(store.index.tour)
    poses = []
    for t, turn in ((tour.t[0], 1.0), (tour.t[0] + tour.duration / 4, -1.0)):
        eye, fwd, up = tour.pose_at(t)
        poses.append({"eye": eye.tolist(), "forward": (fwd * [turn, turn, 1.0]).tolist(), "up": up.tolist()})
    here, there = poses
    slow = dict(c_vertex=2e-5)  # the budget binds: what is in view decides the selection
    plan = TourPlan(t=0.0, keys=[TourKey(t=0.0, **there), TourKey(t=600.0, **there)], tour="still")
    peers = {"planned": Peer(server.url, plan=plan, **slow), "moved": Peer(server.url, **slow),
             "stayed": Peer(server.url, **slow)}
    try:
        for name, pose in (("planned", here), ("moved", there), ("stayed", here)):
            peers[name].camera(pose)
        first = {name: p.expect(Delta) for name, p in peers.items()}
        # The plan arrives as its own message, too: a session that stayed is told it will move.
        peers["stayed"].ws.send(encode(TourPlan(t=peers["stayed"].now(),
                                                keys=[TourKey(t=0.0, **there), TourKey(t=600.0, **there)])))
        peers["stayed"].camera(here)
        later = peers["stayed"].expect(Delta)
        while later.reset or later.seq < 2:
            later = peers["stayed"].expect(Delta)
    finally:
        for p in peers.values():
            p.ws.close()
    assert first["planned"].selection == first["moved"].selection
    assert first["planned"].selection != first["stayed"].selection
    assert not peers["stayed"].errors and not peers["planned"].errors
    assert later.selection == first["moved"].selection
