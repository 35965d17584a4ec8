"""The scene store: round trip, index arrays, clear errors, atomic writes, thread safety."""

from __future__ import annotations

import sqlite3
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from proto.geometry import decode_geometry
from server.scene.lod import build_chain, chain_errors
from server.scene.store import SCHEMA_VERSION, SceneStore, StoreError
from server.scene.writer import SceneWriter, object_box

TOUR = [
    {"t": 0.0, "eye": [0.0, -5.0, 1.7], "forward": [0.0, 1.0, 0.0], "up": [0.0, 0.0, 1.0]},
    {"t": 2.0, "eye": [1.0, -5.0, 1.7], "forward": [0.0, 1.0, -0.1], "up": [0.0, 0.0, 1.0]},
    {"t": 4.0, "eye": [0.0, -5.0, 1.7], "forward": [0.0, 1.0, 0.0], "up": [0.0, 0.0, 1.0]},
]


def _objects() -> list[tuple[str, str, list[tuple[np.ndarray, np.ndarray]], list[float]]]:
    """Three objects with 4, 3 and 1 levels at different places."""
    out = []
    for i, (subdiv, levels) in enumerate([(4, 4), (3, 3), (2, 1)]):
        m = trimesh.creation.icosphere(subdiv)
        v = m.vertices * (1.0 + 0.05 * np.sin(5 * m.vertices[:, :1])) + [3.0 * i, 0.0, 1.0]
        chain = build_chain(v, m.faces, levels=levels)
        out.append((f"obj{i}", ["rock", "column", "rock"][i], chain, chain_errors(chain)))
    return out


def _write(path: Path, objects=None) -> list:
    objects = objects or _objects()
    with SceneWriter(path, name="unit", generator="test", seed=7) as w:
        for name, cls, chain, errors in objects:
            w.add_object(name, cls, chain, errors)
        w.set_tour(TOUR)
        w.set_start({k: TOUR[0][k] for k in ("eye", "forward", "up")})
    return objects


@pytest.fixture(scope="module")
def written(tmp_path_factory) -> tuple[Path, list]:
    path = tmp_path_factory.mktemp("store") / "unit.db"
    return path, _write(path)


def test_round_trip_index(written) -> None:
    path, objects = written
    with SceneStore.open(path) as store:
        idx = store.index
        assert idx.name == "unit"
        assert idx.n_objects == 3 and idx.n_representations == 4 + 3 + 1
        np.testing.assert_array_equal(idx.rep_count, [4, 3, 1])
        np.testing.assert_array_equal(idx.rep_first, [0, 4, 7])
        np.testing.assert_array_equal(idx.rep_object, [0, 0, 0, 0, 1, 1, 1, 2])
        np.testing.assert_array_equal(idx.rep_level, [0, 1, 2, 3, 0, 1, 2, 0])
        faces = [f.shape[0] for _, _, chain, _ in objects for _, f in chain]
        verts = [p.shape[0] for _, _, chain, _ in objects for p, _ in chain]
        errors = [e for _, _, _, errs in objects for e in errs]
        np.testing.assert_array_equal(idx.rep_faces, faces)
        np.testing.assert_array_equal(idx.rep_vertices, verts)
        np.testing.assert_array_equal(idx.rep_error, np.float32(errors))
        assert idx.class_names == ["rock", "column"]
        np.testing.assert_array_equal(idx.object_class, [0, 1, 0])
        for o, (_, _, chain, _) in enumerate(objects):
            lo, hi = object_box(chain)
            np.testing.assert_allclose(idx.object_lo[o], lo, rtol=1e-6)
            np.testing.assert_allclose(idx.object_hi[o], hi, rtol=1e-6)
            full = chain[-1][0]  # the box is the full-detail one, give or take simplifier overshoot
            assert np.all(lo <= full.min(axis=0)) and np.all(hi >= full.max(axis=0))
            np.testing.assert_allclose(lo, full.min(axis=0), atol=0.05)
        np.testing.assert_allclose(idx.bounds, [idx.object_lo.min(0), idx.object_hi.max(0)], rtol=1e-6)
        assert idx.tour == TOUR
        assert idx.start == {k: TOUR[0][k] for k in ("eye", "forward", "up")}
        assert idx.meta["schema_version"] == SCHEMA_VERSION and idx.meta["seed"] == 7
        assert {"generator", "created", "bounds"} <= set(idx.meta)
        # dtypes are the documented ones
        assert idx.object_lo.dtype == np.float32 and idx.bounds.dtype == np.float64
        assert idx.object_class.dtype == np.int16 and idx.rep_level.dtype == np.int16
        for a in (idx.rep_first, idx.rep_count, idx.rep_object, idx.rep_faces, idx.rep_vertices, idx.rep_bytes):
            assert a.dtype == np.int32
        assert idx.rep_error.dtype == np.float32
        # untextured payloads: no representation carries a texture
        assert idx.rep_texels.dtype == np.int32 and idx.rep_texels.shape == idx.rep_faces.shape
        assert not idx.rep_texels.any()
        assert store.object_names() == ["obj0", "obj1", "obj2"]


def test_geometry_decodes_within_quantization(written) -> None:
    path, objects = written
    with SceneStore.open(path) as store:
        blobs = store.geometries(range(store.index.n_representations))
        np.testing.assert_array_equal(store.index.rep_bytes, [len(b) for b in blobs])
        reps = [(chain, level) for _, _, chain, _ in objects for level in range(len(chain))]
        for blob, (chain, level) in zip(blobs, reps):
            pos, fac = chain[level]
            lo, hi = object_box(chain)
            step = (hi - lo) / 65535.0  # quantization in the object's box
            g = decode_geometry(blob)
            assert g.faces == fac.shape[0] and g.vertices == pos.shape[0]
            d, nearest = cKDTree(pos).query(g.positions.astype(np.float64))
            assert np.all(np.abs(g.positions - pos[nearest]) <= step * 0.5 + 1e-5)
            # the same triangles, up to the encoder's reordering
            tri_in = {tuple(sorted(t)) for t in fac.tolist()}
            tri_out = {tuple(sorted(t)) for t in nearest[g.indices].tolist()}
            assert tri_in == tri_out


def test_geometries_order_and_unknown_rep(written) -> None:
    path, _ = written
    with SceneStore.open(path) as store:
        a, b, c = store.geometries([5, 0, 5])
        assert a == c == store.geometry(5) and b == store.geometry(0) and a != b
        for bad in (-1, store.index.n_representations):
            with pytest.raises(StoreError, match="unknown representation") as err:
                store.geometry(bad)
            assert str(path) in str(err.value)
    with pytest.raises(StoreError, match="closed"):
        store.geometry(0)


def test_geometry_from_threads(written) -> None:
    path, _ = written
    with SceneStore.open(path) as store:
        m = store.index.n_representations
        expected = store.geometries(range(m))
        with ThreadPoolExecutor(4) as pool:
            got = list(pool.map(lambda i: store.geometry(i % m), range(400)))
        assert got == [expected[i % m] for i in range(400)]


def test_missing_file(tmp_path) -> None:
    path = tmp_path / "nope.db"
    with pytest.raises(StoreError, match="no such scene store") as err:
        SceneStore.open(path)
    assert str(path) in str(err.value)


@pytest.mark.parametrize("content", [b"", b"hello, this is not a database" * 100])
def test_not_sqlite(tmp_path, content) -> None:
    path = tmp_path / "junk.db"
    path.write_bytes(content)
    with pytest.raises(StoreError, match="not a walkstream store") as err:
        SceneStore.open(path)
    assert str(path) in str(err.value)


def test_foreign_sqlite(tmp_path) -> None:
    path = tmp_path / "other.db"
    with sqlite3.connect(path) as conn:
        conn.execute("CREATE TABLE meta (key TEXT, value TEXT)")
    with pytest.raises(StoreError, match="not a walkstream store") as err:
        SceneStore.open(path)
    assert str(path) in str(err.value)


def _copy(src: Path, dst: Path) -> Path:
    dst.write_bytes(src.read_bytes())
    return dst


def test_schema_version_mismatch(written, tmp_path) -> None:
    path = _copy(written[0], tmp_path / "future.db")
    with sqlite3.connect(path) as conn:
        conn.execute("UPDATE meta SET value = '99' WHERE key = 'schema_version'")
    with pytest.raises(StoreError, match="schema version 99") as err:
        SceneStore.open(path)
    assert str(path) in str(err.value)


def test_missing_table(written, tmp_path) -> None:
    path = _copy(written[0], tmp_path / "broken.db")
    with sqlite3.connect(path) as conn:
        conn.execute("DROP TABLE representations")
    with pytest.raises(StoreError, match="missing table 'representations'") as err:
        SceneStore.open(path)
    assert str(path) in str(err.value)


def test_non_contiguous_levels_are_corrupt(written, tmp_path) -> None:
    path = _copy(written[0], tmp_path / "gap.db")
    with sqlite3.connect(path) as conn:
        conn.execute("UPDATE representations SET level = 5 WHERE id = 2")
    with pytest.raises(StoreError, match="corrupt"):
        SceneStore.open(path)


def _leftovers(directory: Path, keep: set[str]) -> list[str]:
    return sorted(p.name for p in directory.iterdir() if p.name not in keep)


def test_failed_build_leaves_nothing(tmp_path) -> None:
    path = tmp_path / "scene.db"
    objects = _objects()
    with pytest.raises(RuntimeError):
        with SceneWriter(path) as w:
            w.add_object(*objects[0])
            assert w.temporary_path.exists() and w.temporary_path.parent == tmp_path
            raise RuntimeError("build failed")
    assert _leftovers(tmp_path, set()) == []


def test_failed_build_keeps_existing_store(written, tmp_path) -> None:
    path = _copy(written[0], tmp_path / "scene.db")
    before = path.read_bytes()
    objects = _objects()
    with pytest.raises(ValueError):
        with SceneWriter(path) as w:
            w.add_object(*objects[1])
            w.add_object("bad", "rock", objects[0][2], [0.0])  # errors do not match levels
    assert path.read_bytes() == before
    assert _leftovers(tmp_path, {"scene.db"}) == []
    w = SceneWriter(path)
    w.add_object(*objects[1])
    w.abort()
    w.abort()  # twice is harmless
    assert path.read_bytes() == before
    assert _leftovers(tmp_path, {"scene.db"}) == []
    with pytest.raises(StoreError, match="already committed or aborted"):
        w.add_object(*objects[1])


def test_commit_replaces_existing_store(written, tmp_path) -> None:
    path = _copy(written[0], tmp_path / "scene.db")
    objects = _objects()[:1]
    _write(path, objects)
    with SceneStore.open(path) as store:
        assert store.index.n_objects == 1
    assert _leftovers(tmp_path, {"scene.db"}) == []


def test_empty_store_refused(tmp_path) -> None:
    path = tmp_path / "empty.db"
    with pytest.raises(StoreError, match="without objects"):
        SceneWriter(path).commit()
    assert _leftovers(tmp_path, set()) == []


def test_invalid_tour_refused(tmp_path) -> None:
    w = SceneWriter(tmp_path / "scene.db")
    try:
        with pytest.raises(ValueError):
            w.set_tour([{**TOUR[0], "forward": [0.0, 0.0, 0.0]}])
        with pytest.raises(ValueError):
            w.set_start({"eye": [0.0, 0.0, 1.0], "forward": [0.0, 0.0, 1.0], "up": [0.0, 0.0, 2.0]})
    finally:
        w.abort()


def test_start_defaults_to_first_tour_key(tmp_path) -> None:
    path = tmp_path / "scene.db"
    with SceneWriter(path) as w:
        w.add_object(*_objects()[2])
        w.set_tour(TOUR)
    with SceneStore.open(path) as store:
        assert store.index.start == {k: TOUR[0][k] for k in ("eye", "forward", "up")}
        assert store.index.name == "scene"
