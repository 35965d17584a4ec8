"""Street tours: the walk stays on open ground at eye height, the flyover above the roofs; stores keep tours by name."""

from __future__ import annotations

import json
import sqlite3

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st

from proto.tour import Tour
from proto.walkable import WalkableGrid
from server.scene.builder import BuildOptions, build_store
from server.scene.index import MESH, TREES
from server.scene.inspect import format_report, inspect_store
from server.scene.source import SourceObject, SourceScene
from server.scene.store import SceneStore
from server.scene.streets import dense_blocks, street_loop
from server.scene.tour import (EYE_HEIGHT, FLY_HEIGHT, FLY_SECONDS, FLY_SPEED, FLY_TURN, MIN_FLY, MIN_WALK, ROOF_CLEARANCE,
                               WALK_SECONDS, WALK_SPEED, WALK_TURN, flyover_tour, named_tours, tour_for, walk_tour)
from server.scene.walkable import GROUND_CLASSES
from server.scene.writer import SceneWriter
from tests.city import City, box, city_source

FLY_BUDGET = FLY_SPEED * FLY_SECONDS


def _dense(keys: list[dict], per_key: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Poses along the tour between its keys (``per_key`` a key interval), as a client plays it."""
    tour = Tour(keys)
    t = np.linspace(tour.t[0], tour.t[-1], per_key * (len(keys) - 1), endpoint=False)
    return tour.pose_at(t)


def _check_loop(keys: list[dict], speed: float, turn_deg: float) -> np.ndarray:
    """Keys every half second or so, closed, at ``speed``, turning within ``turn_deg``/s; the key eyes (k, 3)."""
    t = np.array([k["t"] for k in keys])
    eye = np.array([k["eye"] for k in keys])
    fwd = np.array([k["forward"] for k in keys])
    assert keys[0]["eye"] == keys[-1]["eye"] and keys[0]["forward"] == keys[-1]["forward"]  # loops without a jump
    dt = np.diff(t)
    assert (dt > 0).all() and np.allclose(dt, dt[0], rtol=1e-3) and dt[0] <= 0.5 + 1e-6
    # Keys lie evenly along the path at ``speed``: the straight step between two is that or, round a corner, less.
    step = np.linalg.norm(np.diff(eye[:, :2], axis=0), axis=1)
    assert (step / dt <= speed * 1.001).all() and np.median(step / dt) == pytest.approx(speed, rel=0.01)
    assert step.sum() / (t[-1] - t[0]) > 0.95 * speed
    turn = np.degrees(np.arccos(np.clip(np.sum(fwd[1:] * fwd[:-1], axis=1), -1.0, 1.0)))
    assert (turn <= turn_deg * dt + 1e-6).all(), turn.max()
    return eye


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 2**32 - 1))
def test_the_walk_keeps_to_open_ground_at_eye_height(seed):
    city = City(seed)
    loop = city.loop(WALK_SPEED * WALK_SECONDS, MIN_WALK)
    assert loop is not None  # streets of 8 m and more always let a walk through
    keys = walk_tour(city.grid, loop)
    assert keys is not None
    eye = _check_loop(keys, WALK_SPEED, WALK_TURN)
    assert keys[-1]["t"] <= WALK_SECONDS * 1.4  # the budget, and the detours it allows
    # Every key stands EYE_HEIGHT above the grid's ground ...
    np.testing.assert_allclose(eye[:, 2], city.grid.height(eye) + EYE_HEIGHT, atol=1e-4)
    # ... and so does every pose between keys (the ground under it a cell's slope away), none in a building.
    e, f, _ = _dense(keys)
    assert city.grid.walkable(e).all()
    assert not city.inside(e).any()
    ground = city.grid.height(e)
    assert np.abs(e[:, 2] - ground - EYE_HEIGHT).max() <= np.abs(city.slope).sum() * city.grid.cell + 1e-3
    assert (f[:, 2] < 0).all() and (f[:, 2] > -0.2).all()  # looking ahead, a little down


@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 2**32 - 1))
@example(580)  # four dense blocks close together: the loop through them is 90 m, under MIN_FLY
def test_the_flyover_stays_above_every_roof(seed):
    city = City(seed)
    loop = city.loop(FLY_BUDGET, MIN_FLY)
    if loop is None:
        # A city whose dense blocks lie close together gets no flyover, by design: the loop through them is
        # shorter than a flight. Any other reason is a failure; such a city is then not a flyover's example.
        short = city.loop(FLY_BUDGET, 0.0)
        assert short is not None and short.length < MIN_FLY
    assume(loop is not None)
    keys = flyover_tour(city.grid, loop, city.lo, city.hi)
    eye = _check_loop(keys, FLY_SPEED, FLY_TURN)
    assert (eye[:, 2] >= city.ground(eye[:, :2]) + FLY_HEIGHT - 0.5).all()  # the grid's ground: a cell's slope
    e, f, _ = _dense(keys)
    assert (e[:, 2] >= city.roof_under(e) + ROOF_CLEARANCE - 1e-6).all()
    assert (f[:, 2] < -0.3).all()  # looking forward and down


def test_one_house_is_walked_round_and_a_lot_too_small_gets_no_walk():
    ground = np.zeros((40, 40), np.float32)
    ground[15:25, 15:25] = np.nan  # a 5 m house on a 20 m lot
    grid = WalkableGrid((0.0, 0.0), 0.5, ground)
    blocks = dense_blocks(grid, np.array([[7.5, 7.5]]), np.array([[12.5, 12.5]]))
    assert len(blocks) == 1
    loop = street_loop(grid, blocks, WALK_SPEED * WALK_SECONDS, MIN_WALK)
    assert loop is not None and loop.length >= MIN_WALK
    keys = walk_tour(grid, loop)
    e, _, _ = _dense(keys)
    assert grid.walkable(e).all()
    turned = np.unwrap(np.arctan2(e[:, 1] - 10.0, e[:, 0] - 10.0))
    assert abs(turned[-1] - turned[0]) > 1.5 * np.pi  # round the house, not out and back
    small = np.zeros((16, 16), np.float32)
    small[6:10, 6:10] = np.nan  # a 2 m shed on an 8 m lot: no walk of MIN_WALK fits
    grid = WalkableGrid((0.0, 0.0), 0.5, small)
    blocks = dense_blocks(grid, np.array([[3.0, 3.0]]), np.array([[5.0, 5.0]]))
    assert street_loop(grid, blocks, WALK_SPEED * WALK_SECONDS, MIN_WALK) is None
    assert street_loop(grid, np.zeros((0, 2)), 100.0, 1.0) is None


# --------------------------------------------------------------------------- stores


def test_a_city_store_keeps_its_walk_flyover_and_orbit_by_name(city_store):
    with SceneStore.open(city_store) as store:
        idx = store.index
        grid = store.walkable()
        tours = named_tours(idx)
        assert set(tours) == {"walk", "flyover", "orbit"}
        assert {n: t["kind"] for n, t in tours.items()} == {"walk": "walk", "flyover": "flyover", "orbit": "orbit"}
        assert idx.meta["default_tour"] == "walk" and idx.tour == tours["walk"]["keys"]
        assert idx.start == {k: tours["walk"]["keys"][0][k] for k in ("eye", "forward", "up")}
        for t in tours.values():
            assert t["duration"] == pytest.approx(t["keys"][-1]["t"] - t["keys"][0]["t"])
        # The stored walk, on the stored grid: eye height above walkable ground all the way.
        e, _, _ = _dense(tours["walk"]["keys"])
        assert grid.walkable(e).all()
        np.testing.assert_allclose(e[:, 2] - grid.height(e), EYE_HEIGHT, atol=0.05)
        keys, start = tour_for(idx, "flyover")
        assert keys == tours["flyover"]["keys"] and start["eye"] == keys[0]["eye"]
        with pytest.raises(KeyError, match="no tour 'nowhere'; its tours: flyover, orbit, walk"):
            tour_for(idx, "nowhere")
        assert tour_for(idx, None) == (idx.tour, idx.start)


def test_inspect_lists_the_tours(city_store):
    report = inspect_store(city_store)
    rows = {t["name"]: t for t in report["tours"]}
    assert set(rows) == {"walk", "flyover", "orbit"}
    assert rows["walk"]["default"] and not rows["orbit"]["default"] and rows["flyover"]["kind"] == "flyover"
    assert rows["walk"]["duration"] > MIN_WALK / WALK_SPEED and rows["orbit"]["duration"] == pytest.approx(60.0)
    json.dumps(report)
    line = next(x for x in format_report(report) if x.strip().startswith("tours:"))
    assert "walk (walk," in line and "default" in line and "flyover (flyover," in line and "orbit (orbit, 60 s)" in line


def test_a_named_scene_keeps_its_own_tour_the_default(tmp_path):
    """A scene that comes with a tour (the auditorium's, the demo's) keeps it as the default, named "scene";
    one without keeps the orbit: the street tours come beside them."""
    source, _ = city_source(seed=11)
    own = [{"t": 0.0, "eye": [1.0, 1.0, 1.7], "forward": [1.0, 0.0, 0.0], "up": [0.0, 0.0, 1.0]},
           {"t": 4.0, "eye": [5.0, 1.0, 1.7], "forward": [1.0, 0.0, 0.0], "up": [0.0, 0.0, 1.0]}]
    opts = BuildOptions(workers=1, shape_guard=False)
    build_store(tmp_path / "own.db", source, tour=own, options=opts, recentre=False)
    summary = build_store(tmp_path / "orbit.db", source, options=opts)
    assert set(summary["tours"]) == {"orbit", "walk", "flyover"} and summary["tours"]["orbit"] == 60.0
    with SceneStore.open(tmp_path / "own.db") as a, SceneStore.open(tmp_path / "orbit.db") as b:
        assert a.index.meta["default_tour"] == "scene" and [k["eye"] for k in a.index.tour] == [k["eye"] for k in own]
        assert set(named_tours(a.index)) == {"scene", "walk", "flyover"}
        assert named_tours(a.index)["scene"]["kind"] == "scene"
        assert b.index.meta["default_tour"] == "orbit" and set(named_tours(b.index)) == {"orbit", "walk", "flyover"}


def test_a_store_of_an_older_build_has_its_one_tour_named_scene(tmp_path):
    keys = [{"t": 0.0, "eye": [0.0, -5.0, 1.0], "forward": [0.0, 1.0, 0.0], "up": [0.0, 0.0, 1.0]},
            {"t": 2.0, "eye": [0.0, -4.0, 1.0], "forward": [0.0, 1.0, 0.0], "up": [0.0, 0.0, 1.0]}]
    with SceneWriter(tmp_path / "old.db", walkable=False) as w:
        w.add_object("box", "box", [(box((0, 0, 0), (1, 1, 1)).positions, box((0, 0, 0), (1, 1, 1)).faces)], [0.0])
        w.set_tour(keys)
    with sqlite3.connect(tmp_path / "old.db") as conn:  # as a store built before tours had names
        conn.execute("DELETE FROM meta WHERE key IN ('tours', 'default_tour')")
    conn.close()
    with SceneStore.open(tmp_path / "old.db") as store:
        idx = store.index
        assert "tours" not in idx.meta
        assert named_tours(idx) == {"scene": {"kind": "scene", "duration": 2.0, "keys": keys}}
        assert inspect_store(tmp_path / "old.db")["tours"][0]["name"] == "scene"


def test_the_writer_refuses_a_bad_tour_name_or_kind(tmp_path):
    with SceneWriter(tmp_path / "bad.db") as w:
        w.add_object("box", "box", [(box((0, 0, 0), (1, 1, 1)).positions, box((0, 0, 0), (1, 1, 1)).faces)], [0.0])
        key = {"t": 0.0, "eye": [0.0, 0.0, 2.0], "forward": [1.0, 0.0, 0.0], "up": [0.0, 0.0, 1.0]}
        with pytest.raises(ValueError, match="tour name 'a walk'"):
            w.add_tour("a walk", "walk", [key])
        with pytest.raises(ValueError, match="kind 'stroll'"):
            w.add_tour("walk", "stroll", [key])
        with pytest.raises(ValueError, match="set by the writer"):
            w.set_meta(tours={})
        w.abort()


def test_den_haag_gets_a_walk_and_a_flyover_beside_its_orbit(denhaag_store):
    """The real city: a named scene keeps its orbit the default; its walk keeps to the streets at eye height, its
    flyover clears every building and tree group it passes over."""
    rows = {t["name"]: t for t in inspect_store(denhaag_store)["tours"]}
    assert set(rows) == {"orbit", "walk", "flyover"} and rows["orbit"]["default"]
    with SceneStore.open(denhaag_store) as store:
        idx = store.index
        grid = store.walkable()
        tours = named_tours(idx)
    assert idx.tour == tours["orbit"]["keys"]
    _check_loop(tours["walk"]["keys"], WALK_SPEED, WALK_TURN)
    e, _, _ = _dense(tours["walk"]["keys"])
    assert grid.walkable(e).all()
    assert np.abs(e[:, 2] - grid.height(e) - EYE_HEIGHT).max() < 0.35  # a kerb between two keys at most
    _check_loop(tours["flyover"]["keys"], FLY_SPEED, FLY_TURN)
    e, _, _ = _dense(tours["flyover"]["keys"])
    ground = np.isin(np.array(idx.class_names)[idx.object_class], GROUND_CLASSES)
    solid = np.flatnonzero((idx.object_kind == TREES) | ((idx.object_kind == MESH) & ~ground))
    lo, hi = idx.object_lo[solid], idx.object_hi[solid]
    over = ((e[:, None, :2] >= lo[None, :, :2]) & (e[:, None, :2] <= hi[None, :, :2])).all(axis=2)
    assert (e[:, 2] >= np.where(over, hi[None, :, 2], -np.inf).max(axis=1) + ROOF_CLEARANCE - 1e-3).all()


def test_a_lone_house_on_its_generated_ground_is_walked_round_but_not_flown_over(tmp_path):
    source = SourceScene(objects=[SourceObject("house", "building", [box((0, 0, 0), (8, 6, 7))])])
    build_store(tmp_path / "house.db", source, options=BuildOptions(workers=1, shape_guard=False), default_tour="walk")
    with SceneStore.open(tmp_path / "house.db") as store:
        tours = named_tours(store.index)
        grid = store.walkable()
        centre = (store.index.object_lo[0, :2] + store.index.object_hi[0, :2]) / 2  # recentred
    assert set(tours) == {"orbit", "walk"}
    e, _, _ = _dense(tours["walk"]["keys"])
    assert grid.walkable(e).all()
    turned = np.unwrap(np.arctan2(e[:, 1] - centre[1], e[:, 0] - centre[0]))
    assert abs(turned[-1] - turned[0]) > 1.5 * np.pi
