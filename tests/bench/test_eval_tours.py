"""Which tour ``walkstream eval`` runs over: the named one, else the scene's own, else its walk, else its default."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bench.demo import ServerProcess
from bench.evaluate import RunSpec, eval_tour, evaluate, run_one, tour_of
from bench.methods import METHODS
from proto.tour import Tour
from server.scene.builder import BuildOptions, build_store
from server.scene.source import SourceObject, SourceScene
from server.scene.store import SceneStore
from server.scene.tour import named_tours
from tests.city import box


@pytest.fixture(scope="module")
def orbit_only(tmp_path_factory) -> Path:
    """One small box and no ground round it: no streets to walk, so its tours are the orbit alone."""
    path = tmp_path_factory.mktemp("eval") / "box.db"
    source = SourceScene(objects=[SourceObject("shed", "building", [box((0, 0, 0), (3, 2, 2.5))])])
    build_store(path, source, options=BuildOptions(workers=1, shape_guard=False, ground=False), default_tour="walk")
    return path


def test_eval_runs_over_the_scenes_own_tour_else_its_walk_else_its_default(demo_store, city_store, orbit_only):
    with SceneStore.open(demo_store) as demo, SceneStore.open(city_store) as city, SceneStore.open(orbit_only) as shed:
        assert eval_tour(demo.index) == "scene"  # the demo's flight came with it
        assert eval_tour(city.index) == "walk" and city.index.meta["default_tour"] == "walk"
        assert set(named_tours(shed.index)) == {"orbit"} and eval_tour(shed.index) == "orbit"
        flyover = named_tours(city.index)["flyover"]
    keys, viewpoints, length = tour_of(city_store, "flyover")
    assert keys == flyover["keys"] and viewpoints == {} and length == pytest.approx(flyover["duration"])
    with pytest.raises(KeyError, match="its tours: flyover, orbit, walk"):
        tour_of(city_store, "tram")
    with pytest.raises(ValueError, match="no tour 'tram'"):
        evaluate(city_store, methods=["static"], tour="tram", quality=False)


def test_a_run_follows_the_tour_it_names(city_store):
    with SceneStore.open(city_store) as s:
        flyover = Tour(named_tours(s.index)["flyover"]["keys"])
    path = flyover.pose_at(np.linspace(0.0, flyover.duration, 4000))[0]
    with ServerProcess([city_store]) as server:
        run, traces = run_one(server.url, "city", RunSpec(METHODS["static"], 50.0), duration=1.5,
                              viewport=(160, 90), calibrate=False, tour_name="flyover")
    assert run["summary"]["errors"] == 0 and traces
    assert max(np.linalg.norm(path - tr.eye, axis=1).min() for tr in traces) < 1.0


def test_evaluate_defaults_to_the_walk_of_a_users_city(city_store):
    res = evaluate(city_store, methods=["static"], budgets_ms=[50.0], duration=3.0, warmup=1.0, viewport=(160, 90),
                   quality=False, repeats=1, governor=False, pin=False)
    assert res["tour"] == "walk" and res["scene"] == "city" and res["runs"][0]["summary"]["errors"] == 0


def test_the_eval_command_names_the_tours_when_one_is_missing(city_store):
    done = subprocess.run([sys.executable, "-m", "walkstream", "eval", str(city_store), "--tour", "tram",
                           "--no-scenarios"], capture_output=True, text=True, timeout=300,
                          cwd=Path(__file__).resolve().parents[2])
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert "'tram'" in done.stderr and "flyover, orbit, walk" in done.stderr


def test_the_scenarios_take_their_anchor_from_the_tour_named(city_store, auditorium_store):
    from bench.scenarios.paths import anchor_of
    from bench.scenarios.run import tour_index

    index = tour_index(city_store, "flyover")
    flyover = Tour(index.tour)
    path = flyover.pose_at(np.linspace(0.0, flyover.duration, 4000))[0]
    anchor = anchor_of(index, viewport=(160, 90))
    assert np.linalg.norm(path - anchor.eye, axis=1).min() < 1.0 and "viewpoint" not in anchor.source
    with SceneStore.open(city_store) as s:
        assert index.tour == named_tours(s.index)["flyover"]["keys"] and index.start["eye"] == index.tour[0]["eye"]
    # The auditorium's viewpoints are times of its own tour: they stay with it, and go with any other.
    assert tour_index(auditorium_store, "scene").meta["viewpoints"].keys() == {"A", "B", "C"}
    assert tour_index(auditorium_store, "walk").meta["viewpoints"] == {}
    with pytest.raises(KeyError, match="its tours: scene, walk"):
        tour_index(auditorium_store, "orbit")
