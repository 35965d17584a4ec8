"""Generated benchmark scenes: sizes, the chair's LOD headroom, the tours and their viewpoints."""

from __future__ import annotations

import math

import fast_simplification
import numpy as np
import pytest
import trimesh

from proto.messages import TourKey
from server.scene.generate import auditorium, megacity
from server.scene.generate.auditorium import chair_mesh
from server.scene.lod import clean_mesh


@pytest.fixture(scope="module")
def hall():
    return auditorium(seed=0)


@pytest.fixture(scope="module")
def city():
    return megacity(buildings=300, seed=0)


def _pose(tour, t):
    key = min(tour, key=lambda k: abs(k["t"] - t))
    assert abs(key["t"] - t) < 1e-6
    f = np.array(key["forward"])
    return np.array(key["eye"]), f / np.linalg.norm(f)


def _chair_centres(scene):
    return np.array([o.levels[0].positions.mean(0) for o in scene.objects if o.cls == "chair"])


def _check_tour(tour, lo=None, hi=None):
    for k in tour:
        TourKey(**k)
    t = np.array([k["t"] for k in tour])
    assert t[0] == 0.0 and np.all(np.diff(t) > 0)
    first, last = tour[0], tour[-1]
    for name in ("eye", "forward", "up"):
        assert np.allclose(first[name], last[name], atol=1e-9)
    eye = np.array([k["eye"] for k in tour])
    step = np.linalg.norm(np.diff(eye, axis=0), axis=1) / np.diff(t)
    assert step.max() < 120.0  # no jumps
    if lo is not None:
        assert np.all(eye >= lo) and np.all(eye <= hi)
    return t


def test_auditorium_size(hall):
    scene, _, _ = hall
    chairs = [o for o in scene.objects if o.cls == "chair"]
    assert len(chairs) >= 400
    assert {o.cls for o in scene.objects} == {"chair", "hall", "prop"}
    total = sum(m.n_faces for o in scene.objects for m in o.levels)
    assert total >= 2_200_000
    for o in scene.objects:
        m = o.levels[-1]
        assert m.n_faces > 0 and m.faces.min() >= 0 and m.faces.max() < m.n_vertices


def test_chair_has_six_halvings():
    """~5,600 triangles in closed parts (so full detail costs what F&S's chairs did, see the module): the
    simplifier halves it at least six times before it stalls or reaches a dozen faces."""
    m = chair_mesh()
    assert 5000 <= m.n_faces <= 6500
    assert all(part.is_volume for part in trimesh.Trimesh(m.positions, m.faces).split(only_watertight=False))
    p, f = clean_mesh(m.positions, m.faces)
    levels = 0
    while True:
        p2, f2 = clean_mesh(*fast_simplification.simplify(p, f, target_reduction=0.5))
        if f2.shape[0] > 0.6 * f.shape[0] or f2.shape[0] < 12:
            break
        p, f, levels = p2, f2, levels + 1
    assert levels >= 6


def test_auditorium_deterministic():
    a, ta, va = auditorium(seed=3)
    b, tb, vb = auditorium(seed=3)
    c, _, _ = auditorium(seed=4)
    assert ta == tb and va == vb
    assert all(np.array_equal(x.levels[0].positions, y.levels[0].positions) for x, y in zip(a.objects, b.objects))
    assert not np.array_equal(_chair_centres(a), _chair_centres(c))


def test_auditorium_tour(hall):
    scene, tour, views = hall
    t = _check_tour(tour, lo=[-15, -2, 0], hi=[15, 34, 11])
    assert 60.0 <= t[-1] <= 90.0
    assert set(views) == {"A", "B", "C"} and all(0 < v < t[-1] for v in views.values())


def test_viewpoint_a_sees_many_near_chairs(hall):
    scene, tour, views = hall
    eye, fwd = _pose(tour, views["A"])
    d = _chair_centres(scene) - eye
    near = (np.linalg.norm(d, axis=1) < 8.0) & (d @ fwd > 0)
    assert near.sum() >= 30


def test_viewpoint_b_sees_few(hall):
    scene, tour, views = hall
    eye, fwd = _pose(tour, views["B"])
    d = _chair_centres(scene) - eye
    cos = (d @ fwd) / np.linalg.norm(d, axis=1)
    assert (cos > math.cos(math.radians(30))).sum() <= 5


def test_viewpoint_c_spins(hall):
    _, tour, views = hall
    tc = views["C"]
    keys = [k for k in tour if abs(k["t"] - tc) <= 1.5]
    yaw = np.unwrap([math.atan2(k["forward"][1], k["forward"][0]) for k in keys])
    assert abs(yaw[-1] - yaw[0]) >= math.radians(300)
    eyes = np.array([k["eye"] for k in keys])
    assert np.ptp(eyes, axis=0).max() < 1.0  # spinning on the spot


def test_megacity_size_and_tour(city):
    scene, tour, views = city
    buildings = [o for o in scene.objects if o.cls == "building"]
    assert len(buildings) == 300
    assert any(o.cls == "ground" for o in scene.objects)
    faces = np.array([o.levels[0].n_faces for o in buildings])
    assert faces.mean() >= 500
    for o in buildings:
        m = o.levels[0]
        assert m.faces.max() < m.n_vertices and m.positions[:, 2].min() >= -1e-9
    t = _check_tour(tour)
    assert 60.0 <= t[-1] <= 150.0
    fwd = np.array([k["forward"] for k in tour])
    assert np.allclose(np.linalg.norm(fwd, axis=1), 1.0)
    assert np.all(np.array([k["up"] for k in tour]) == [0.0, 0.0, 1.0])
    assert set(views) == {"street", "overview"}
    street, _ = _pose(tour, views["street"])
    high, _ = _pose(tour, views["overview"])
    assert street[2] < 5.0 and high[2] > 100.0


def test_megacity_deterministic():
    a, ta, _ = megacity(buildings=300, seed=1)
    b, tb, _ = megacity(buildings=300, seed=1)
    c, _, _ = megacity(buildings=300, seed=2)
    assert ta == tb
    assert [o.name for o in a.objects] == [o.name for o in b.objects]
    for x, y in zip(a.objects, b.objects):
        assert np.array_equal(x.levels[0].positions, y.levels[0].positions)
        assert np.array_equal(x.levels[0].faces, y.levels[0].faces)
    assert any(not np.array_equal(x.levels[0].positions, y.levels[0].positions)
               for x, y in zip(a.objects, c.objects) if x.cls == "building")


def test_megacity_buildings_apart(city):
    scene, _, _ = city
    b = [o.levels[0].positions for o in scene.objects if o.cls == "building"]
    lo = np.array([p.min(0) for p in b])[:, :2]
    hi = np.array([p.max(0) for p in b])[:, :2]
    over = np.minimum(hi[:, None], hi[None]) - np.maximum(lo[:, None], lo[None])  # (n, n, 2)
    area = np.clip(over, 0, None).prod(-1)
    np.fill_diagonal(area, 0.0)
    assert area.max() < 1.0  # at most touching details, never overlapping bodies
