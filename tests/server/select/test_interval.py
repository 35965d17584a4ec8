"""Selection over an interval of predicted cameras plus Zach's conservative camera."""

from __future__ import annotations

import numpy as np
import pytest

from server.scene.store import SceneStore
from server.select.camera import View
from server.select.cost import CostModel
from server.select.selection import Interval, Scene, select


@pytest.fixture(scope="module")
def scene(demo_store):
    with SceneStore.open(demo_store) as store:
        yield Scene.of(store.index), store.index


def _view(index, eye, target, fov=60.0):
    eye = np.asarray(eye, float)
    return View.of_pose(eye, np.asarray(target, float) - eye, [0, 0, 1.0], fov, (640, 360), index.bounds)


def test_the_mean_over_identical_samples_is_the_single_view(scene):
    sc, index = scene
    c = np.asarray(index.bounds).mean(axis=0)
    v = _view(index, c + [-60, -5, 10], c)
    cost = CostModel(c_vertex=2e-7)
    one = select(sc, v, cost, 0.002, "greedy", 0.0)
    three = select(sc, Interval((v, v, v)), cost, 0.002, "greedy", 0.0)
    assert one.reps.tolist() == three.reps.tolist() and three.cost == pytest.approx(one.cost)
    assert three.cost <= 0.002


def test_the_conservative_camera_brings_in_what_the_samples_miss(scene):
    sc, index = scene
    c = np.asarray(index.bounds).mean(axis=0)
    narrow = _view(index, c + [-60, 0, 10], c + [-60, 40, 10], fov=10.0)  # looks past the scene
    around = _view(index, c + [-90, 0, 10], c, fov=160.0)  # the conservative camera sees it all
    cost = CostModel(c_vertex=2e-7)
    alone = select(sc, Interval((narrow,), around, weight=0.0), cost, 0.05, "greedy", 0.0)
    with_it = select(sc, Interval((narrow,), around, weight=0.1), cost, 0.05, "greedy", 0.0)
    assert with_it.visible > alone.visible and with_it.reps.size > alone.reps.size
    with pytest.raises(ValueError):
        Interval(())
    with pytest.raises(ValueError):
        Interval((narrow,), around, weight=float("nan"))
