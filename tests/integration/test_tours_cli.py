"""Tours by name end to end: ``walkstream build`` makes them, ``inspect`` lists them, a real client follows the
one it names through a real server, and a name the scene lacks is a one-line error."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bench.demo import ServerProcess
from client.app import run_client
from client.connection import ClientError
from proto.tour import Tour
from server.scene.data import data_file
from server.scene.store import SceneStore
from server.scene.tour import FLY_HEIGHT, named_tours

from .test_cli import _one_line_error, _walkstream


@pytest.fixture(scope="module")
def server(city_store):
    with ServerProcess([city_store]) as srv:
        yield srv


def test_a_client_that_names_a_tour_follows_it(server, city_store):
    with SceneStore.open(city_store) as store:
        flyover = named_tours(store.index)["flyover"]["keys"]
        ground = float(np.nanmin(store.walkable().ground))
    run = run_client(server.url, "city", duration=2.0, viewport=(160, 90), tour_name="flyover", trace=True,
                     calibrate=False)
    assert [list(k.eye) for k in run.welcome.tour] == [k["eye"] for k in flyover]
    assert run.errors == [] and run.trace
    path = Tour(flyover).pose_at(np.linspace(0.0, Tour(flyover).duration, 4000))[0]
    for frame in run.trace:  # every frame drawn from the flyover, high above the streets
        assert np.linalg.norm(path - frame.eye, axis=1).min() < 1.0
        assert frame.eye[2] > ground + FLY_HEIGHT - 1.0
    with pytest.raises(ClientError, match="unknown_tour.*'tram'.*its tours: flyover, orbit, walk"):
        run_client(server.url, "city", duration=1.0, viewport=(160, 90), tour_name="tram", calibrate=False)


def test_the_client_command_names_the_tours_when_one_is_missing(server):
    done = _walkstream("client", server.url, "--scene", "city", "--tour", "tram", "--duration", "1",
                       "--width", "160", "--height", "90")
    _one_line_error(done, "unknown_tour", "'tram'", "flyover, orbit, walk")
    done = _walkstream("client", server.url, "--scene", "city", "--tour", "walk", "--duration", "3",
                       "--width", "160", "--height", "90")
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout.strip().splitlines()[-1])  # frames after its 2 s warm-up
    assert summary["frames"] > 0 and summary["errors"] == 0
    done = _walkstream("client", server.url, "--scene", "city", "--tour", "a tram")
    assert done.returncode == 2 and "--tour" in done.stderr and "Traceback" not in done.stderr


def test_a_user_cityjson_builds_with_walk_flyover_and_orbit_and_inspect_lists_them(tmp_path):
    out = tmp_path / "multi.db"
    done = _walkstream("build", str(data_file("city/multi_lod.city.json")), "-o", str(out))
    assert done.returncode == 0, done.stderr
    assert set(json.loads(done.stdout.strip().splitlines()[-1])["tours"]) == {"walk", "flyover", "orbit"}
    done = _walkstream("inspect", str(out), "--json")
    assert done.returncode == 0, done.stderr
    tours = {t["name"]: t for t in json.loads(done.stdout)["tours"]}
    assert {n: t["kind"] for n, t in tours.items()} == {"walk": "walk", "flyover": "flyover", "orbit": "orbit"}
    assert tours["walk"]["default"] and all(t["duration"] > 10 for t in tours.values())
    text = _walkstream("inspect", str(out)).stdout
    assert "tours: orbit (orbit, 60 s), walk (walk, " in text and "s, default), flyover (flyover, " in text
