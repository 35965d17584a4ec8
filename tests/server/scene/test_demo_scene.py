"""The demo scene: real meshes, LOD chains, a valid closed tour, deterministic builds."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from proto.messages import Pose, TourKey
from server.scene.demo import CLASS_NAMES, build_demo, generate_demo
from server.scene.lod import build_chain
from server.scene.store import SceneStore

N = 12


@pytest.fixture(scope="module")
def scene():
    return generate_demo(objects=N, seed=0)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    path = tmp_path_factory.mktemp("demo") / "demo.db"
    calls: list[tuple[int, int]] = []
    summary = build_demo(path, objects=N, seed=0, progress=lambda d, t: calls.append((d, t)))
    return path, summary, calls


def test_objects_are_closed_detailed_meshes(scene) -> None:
    sculptures = [o for o in scene.objects if o.cls != "ground"]
    assert len(sculptures) == N
    assert {o.cls for o in scene.objects} <= set(CLASS_NAMES)
    assert scene.objects[0].cls == "ground"
    assert len({o.name for o in scene.objects}) == len(scene.objects)
    for obj in sculptures:
        pos, faces = obj.mesh()
        assert 4000 <= faces.shape[0] <= 20000, obj.name
        mesh = trimesh.Trimesh(pos, faces, process=False)
        assert mesh.is_watertight and mesh.is_winding_consistent, obj.name
        assert mesh.volume > 0, f"{obj.name} faces point inward"
        assert pos[:, 2].min() < 0.0 < pos[:, 2].max()  # stands on the ground
        chain = build_chain(pos, faces)
        counts = [f.shape[0] for _, f in chain]
        assert len(chain) >= 3 and counts == sorted(set(counts)), obj.name


def test_ground_tiles_meet_at_every_level() -> None:
    """Neighbouring tiles share their edge vertices exactly, and simplification keeps them."""
    tiles = [o for o in generate_demo(objects=256, seed=0).objects if o.cls == "ground"]
    assert len(tiles) == 9  # 91 m square in 3 × 3 tiles: tile size 30.33… is not exact in binary
    a, b = (build_chain(*t.mesh()) for t in tiles[1:3])
    assert len(a) >= 3 and len(b) >= 3
    y = a[-1][0][:, 1].max()
    assert y == b[-1][0][:, 1].min()

    def edge(p: np.ndarray) -> np.ndarray:
        e = p[p[:, 1] == y]
        return e[np.argsort(e[:, 0])]

    reference = edge(a[-1][0])
    assert reference.shape[0] == 65
    for p, _ in a + b:
        np.testing.assert_array_equal(edge(p), reference)


def test_tour_is_valid_and_closed(scene) -> None:
    tour = scene.tour
    keys = [TourKey(**k) for k in tour]
    t = np.array([k.t for k in keys])
    assert t[0] == 0.0 and (np.diff(t) > 0).all()
    assert 40.0 <= t[-1] <= 60.0
    first, last = tour[0], tour[-1]
    assert {k: first[k] for k in ("eye", "forward", "up")} == {k: last[k] for k in ("eye", "forward", "up")}
    assert scene.start == {k: first[k] for k in ("eye", "forward", "up")}
    Pose(**scene.start)
    eye = np.array([k["eye"] for k in tour])
    assert (eye[:, 2] >= 1.7).all() and (eye[:, 2] <= 3.0).all()
    # the camera flies along avenues: never through an object
    for obj in scene.objects:
        if obj.cls == "ground":
            continue
        pos, _ = obj.mesh()
        lo, hi = pos.min(0)[:2] - 0.5, pos.max(0)[:2] + 0.5
        assert not ((eye[:, :2] > lo) & (eye[:, :2] < hi)).all(axis=1).any(), obj.name
    speed = np.linalg.norm(np.diff(eye, axis=0), axis=1) / np.diff(t)
    assert speed.max() < 10.0


def test_default_scene_is_heavy_enough() -> None:
    scene = generate_demo()
    sculptures = [o for o in scene.objects if o.cls != "ground"]
    assert len(sculptures) == 576
    faces = np.array([o.params["faces"] for o in sculptures])
    assert 3.5e6 < faces.sum() < 6e6  # several 50 ms frames of llvmpipe's ~14 M triangles/s
    assert faces.min() >= 4000 and faces.max() > 2 * faces.min()


def test_build_writes_a_store(built) -> None:
    path, summary, calls = built
    with SceneStore.open(path) as store:
        idx = store.index
        assert summary["objects"] == idx.n_objects == len(calls)
        assert summary["representations"] == idx.n_representations
        assert calls[-1] == (idx.n_objects, idx.n_objects) and [d for d, _ in calls] == list(range(1, len(calls) + 1))
        assert (idx.rep_count >= 3).all()
        full = idx.rep_first + idx.rep_count - 1
        assert summary["triangles"] == int(idx.rep_faces[full].sum())
        assert idx.class_names == CLASS_NAMES
        assert idx.tour == generate_demo(objects=N, seed=0).tour
        for o in range(idx.n_objects):
            errors = idx.rep_error[idx.rep_first[o] : idx.rep_first[o] + idx.rep_count[o]]
            assert errors[-1] == 0.0 and (np.diff(errors) <= 0).all() and errors[0] > 0


def _blobs(path) -> list[bytes]:
    with SceneStore.open(path) as store:
        return store.geometries(range(store.index.n_representations))


def test_build_is_deterministic(built, tmp_path) -> None:
    path, _, _ = built
    again = tmp_path / "again.db"
    build_demo(again, objects=N, seed=0)
    assert _blobs(again) == _blobs(path)
    other = tmp_path / "other.db"
    build_demo(other, objects=N, seed=1)
    assert _blobs(other) != _blobs(path)


def test_workers_do_not_change_the_result(tmp_path) -> None:
    one, two = tmp_path / "one.db", tmp_path / "two.db"
    build_demo(one, objects=3, seed=5, workers=1)
    build_demo(two, objects=3, seed=5, workers=2)
    assert _blobs(one) == _blobs(two)
