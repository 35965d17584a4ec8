"""Every named scene and every kind of user file, built into a real store and read back as a client would."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from proto.geometry import decode_geometry
from proto.morph import decode_morph
from proto.points import decode_instances, decode_points
from server.scene.builder import BuildOptions, build_store
from server.scene.catalog import build_named, build_path
from server.scene.data import data_file
from server.scene.importers import load_source
from server.scene.inspect import inspect_store
from server.scene.source import SourceError
from server.scene.index import HLOD, KINDS, MESH, TERRAIN, TREES
from server.scene.store import SceneStore


# --------------------------------------------------------------------------- what every store must satisfy


def _rotated(faces: np.ndarray) -> np.ndarray:
    """Each triangle with its smallest index first, orientation kept."""
    k = np.argmin(faces, axis=1)
    return np.stack([faces[np.arange(len(faces)), (k + i) % 3] for i in range(3)], axis=1)


def check_chains(store: SceneStore, objects: np.ndarray, *, exact: bool = True) -> None:
    """Levels monotonic; every vertex of a finer level maps to a vertex of the next coarser one, and
    (``exact``: collapse maps) the geomorph at weight 0 reproduces the coarser surface triangle for triangle
    — where the coarser level was decimated (the shape ladder's proxies take Zach's nearest-vertex maps)."""
    idx = store.index
    fid = store.fidelity()
    made = {} if fid is None else dict(zip(fid["rep"].tolist(), fid["method"].tolist()))
    for o in objects:
        first, count = int(idx.rep_first[o]), int(idx.rep_count[o])
        reps = np.arange(first, first + count)
        assert (np.diff(idx.rep_faces[reps]) > 0).all(), f"object {o}: faces must grow toward full detail"
        assert (np.diff(idx.rep_error[reps]) <= 1e-6).all() and idx.rep_error[reps[-1]] == 0.0
        geoms = [decode_geometry(b) for b in store.geometries(reps.tolist())]
        assert [g.faces for g in geoms] == idx.rep_faces[reps].tolist()
        assert not idx.rep_morph[reps[0]] and idx.rep_morph[reps[1:]].all()
        for k in range(1, count):
            fine, coarse = geoms[k], geoms[k - 1]
            m = decode_morph(store.morph(int(reps[k])), fine.vertices, coarse.vertices)
            assert m.shape == (fine.vertices,) and (m < coarse.vertices).all()
            if not exact or made.get(int(reps[k - 1]), "decimate") != "decimate":
                continue
            # weight 0 puts every fine vertex on its target: the fine mesh collapses onto the coarse one
            tris = m[fine.indices]
            tris = tris[(tris[:, 0] != tris[:, 1]) & (tris[:, 1] != tris[:, 2]) & (tris[:, 0] != tris[:, 2])]
            np.testing.assert_array_equal(np.unique(_rotated(tris), axis=0),
                                          np.unique(_rotated(coarse.indices), axis=0),
                                          err_msg=f"object {o} level {k}")


def check_hierarchy(idx, kind: int, one_root: bool = True) -> None:
    """Every object of ``kind`` lies under exactly one root-to-leaf path; children inside their parent.

    one_root: the hierarchy has a single root (an HLOD tree whose every node kept its proxy does;
    one whose upper nodes had no proxy within the bounds is a forest of the kept nodes).
    """
    objs = np.nonzero(idx.object_kind == kind)[0]
    assert objs.size
    parent = idx.object_parent
    assert (parent < np.arange(idx.n_objects)).all()
    # walk each object up to its root: one path, one root per hierarchy
    roots = set()
    for o in objs:
        path = [int(o)]
        while parent[path[-1]] >= 0:
            path.append(int(parent[path[-1]]))
            assert len(path) <= idx.height
        roots.add(path[-1])
    assert len(roots) == 1 or not one_root, f"{KINDS[kind]} has {len(roots)} roots"
    # CSR children are the inverse of parent
    for o in objs[:400]:
        for c in idx.children(int(o)):
            assert parent[c] == o
    inner = parent[parent >= 0]
    slack = 1e-3 * float(np.abs(idx.bounds).max() + 1)
    children = np.nonzero(parent >= 0)[0]
    assert (idx.object_lo[children] >= idx.object_lo[inner] - slack).all()
    assert (idx.object_hi[children] <= idx.object_hi[inner] + slack).all()


def check_tour(idx) -> None:
    assert len(idx.tour) >= 2
    times = [k["t"] for k in idx.tour]
    assert times == sorted(times)
    lo, hi = idx.bounds
    span = float(np.max(hi - lo))
    for key in idx.tour:
        assert np.linalg.norm(key["forward"]) == pytest.approx(1, abs=1e-3)
        assert np.linalg.norm(np.asarray(key["eye"]) - (lo + hi) / 2) < 4 * span


# --------------------------------------------------------------------------- named scenes


@pytest.fixture(scope="module")
def auditorium(tmp_path_factory):
    """A build of the auditorium with seed 0, the seed of the session's ``auditorium_store``: the determinism
    test compares the two, so the module adds one build (~12 s) to a suite that makes the other anyway."""
    path = tmp_path_factory.mktemp("aud") / "auditorium.db"
    summary = build_named("auditorium", path, seed=0)
    return path, summary


def test_auditorium_is_funkhouser_and_sequins_test(auditorium) -> None:
    """440 copies of one detailed chair whose chain halves it down to a few dozen triangles; 2.5 M in all."""
    from server.scene.generate.auditorium import ROWS, SEATS_PER_ROW, chair_mesh

    path, summary = auditorium
    chair_faces = chair_mesh().n_faces
    with SceneStore.open(path) as store:
        idx = store.index
        chairs = np.nonzero(idx.object_class == idx.class_names.index("chair"))[0]
        assert chairs.size == ROWS * SEATS_PER_ROW >= 400
        full = idx.rep_first + idx.rep_count - 1
        assert (idx.rep_faces[full[chairs]] == chair_faces).all() and chair_faces >= 5000
        assert summary["triangles"] >= 2_200_000 and int(idx.rep_faces[full].sum()) == summary["triangles"]
        # Every chair's chain is the same sensible one: ≥ 4 levels, each about half the next finer one,
        # and it stops where halving again would lose the legs' silhouette (the shape guard).
        levels = idx.rep_count[chairs]
        assert (levels == levels[0]).all() and levels[0] >= 4
        fid = store.fidelity()
        assert fid is not None and (fid["iou"] >= 0.9).all()
        counts = idx.rep_faces[idx.rep_first[chairs][:, None] + np.arange(levels[0])]
        halving = counts[:, :-1] / counts[:, 1:]
        assert ((halving > 0.4) & (halving <= 0.6)).all()
        vp = idx.meta["viewpoints"]
        assert set(vp) == {"A", "B", "C"} and all(0 < t < idx.tour[-1]["t"] for t in vp.values())
        check_tour(idx)
        check_chains(store, chairs[:5])
        check_chains(store, np.nonzero(idx.object_class != idx.class_names.index("chair"))[0][:10])


def test_auditorium_is_deterministic(auditorium, auditorium_store) -> None:
    """Two builds with one seed (this module's and the session's) hold the same counts, errors, boxes, tour,
    geometry and morph payloads."""
    path, _ = auditorium
    with SceneStore.open(path) as a, SceneStore.open(auditorium_store) as b:
        np.testing.assert_array_equal(a.index.rep_faces, b.index.rep_faces)
        np.testing.assert_array_equal(a.index.rep_error, b.index.rep_error)
        np.testing.assert_array_equal(a.index.object_lo, b.index.object_lo)
        assert a.index.tour == b.index.tour
        reps = list(range(0, a.index.n_representations, 97))
        assert a.geometries(reps) == b.geometries(reps)
        assert a.morphs(reps[1:]) == b.morphs(reps[1:])


def test_denhaag_buildings_hlod_terrain_and_trees(tmp_path) -> None:
    path = tmp_path / "denhaag.db"
    summary = build_named("denhaag", path, seed=0, size=400)
    with SceneStore.open(path) as store:
        idx = store.index
        assert idx.meta["crs"] == "EPSG:7415" and idx.meta["origin"][0] > 70_000
        names = idx.class_names
        buildings = np.isin(idx.object_class, [names.index(c) for c in ("building", "buildingpart")])
        assert buildings.sum() >= 1_900
        assert (idx.object_kind[buildings] == MESH).all()
        # HLOD: the kept nodes, every building under at most one path (a building whose ancestors
        # all lacked a proxy within the bounds is a root itself), every root's box around its subtree
        check_hierarchy(idx, HLOD, one_root=False)
        under = idx.object_parent[buildings]
        assert (idx.object_kind[under[under >= 0]] == HLOD).all() and (under >= 0).mean() > 0.5
        top = np.flatnonzero(buildings)
        while (idx.object_parent[top] >= 0).any():
            top = np.where(idx.object_parent[top] >= 0, idx.object_parent[top], top)
        b = np.flatnonzero(buildings)
        assert (idx.object_lo[top] <= idx.object_lo[b] + 1e-3).all() and (idx.object_hi[top] >= idx.object_hi[b] - 1e-3).all()
        # the TIN is a mesh object of class terrain
        terrain = np.nonzero(idx.object_class == names.index("terrain"))[0]
        assert terrain.size == 1 and idx.rep_faces[idx.rep_first[terrain[0]] + idx.rep_count[terrain[0]] - 1] > 5000
        check_chains(store, np.nonzero(buildings)[0][::150])
        check_chains(store, terrain)
        # trees on open ground: none stands on a roof
        groups = np.nonzero(idx.object_kind == TREES)[0]
        inst = [decode_instances(b) for b in store.geometries(idx.rep_first[groups].tolist())]
        assert sum(len(i) for i in inst) == idx.meta["tree_instances"] == summary["tree_instances"] == 400
        assert max(len(i) for i in inst) <= 64
        xy = np.concatenate([i.matrix[:, :2, 3] for i in inst])
        roofs = _footprints(store, np.nonzero(buildings)[0])
        assert not _inside_triangles(xy, roofs).any()


def _footprints(store: SceneStore, objects: np.ndarray) -> np.ndarray:
    idx = store.index
    full = (idx.rep_first[objects] + idx.rep_count[objects] - 1).tolist()
    tris = []
    for g in map(decode_geometry, store.geometries(full)):
        tris.append(g.positions[g.indices][:, :, :2])
    return np.concatenate(tris).astype(np.float64)


def _inside_triangles(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(k,) bool: point strictly inside any (non-degenerate) triangle's xy projection."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    keep = np.abs(area) > 1e-2
    a, b, c, area = a[keep], b[keep], c[keep], area[keep]
    inside = np.zeros(len(p), bool)
    for s in range(0, len(p), 64):
        q = p[s : s + 64, None, :]
        w0 = ((b[:, 0] - q[..., 0]) * (c[:, 1] - q[..., 1]) - (b[:, 1] - q[..., 1]) * (c[:, 0] - q[..., 0])) / area
        w1 = ((c[:, 0] - q[..., 0]) * (a[:, 1] - q[..., 1]) - (c[:, 1] - q[..., 1]) * (a[:, 0] - q[..., 0])) / area
        w2 = 1 - w0 - w1
        inside[s : s + 64] = ((w0 > 1e-3) & (w1 > 1e-3) & (w2 > 1e-3)).any(axis=1)
    return inside


def test_sthelens_terrain_quadtree_under_a_forest(tmp_path) -> None:
    path = tmp_path / "sthelens.db"
    summary = build_named("sthelens", path, seed=1)
    with SceneStore.open(path) as store:
        idx = store.index
        assert summary["tree_instances"] >= 100_000 and idx.meta["tree_instances"] == summary["tree_instances"]
        check_hierarchy(idx, TERRAIN)
        terrain = np.nonzero(idx.object_kind == TERRAIN)[0]
        assert (idx.rep_count[terrain] == 1).all()
        # coarser nodes carry larger errors than their children
        child = terrain[idx.object_parent[terrain] >= 0]
        err = idx.rep_error[idx.rep_first]
        assert (err[idx.object_parent[child]] >= err[child]).all()
        # the finest patches cover the DEM: 466 × 327 samples at 30 m
        leaves = terrain[idx.leaf[terrain]]
        ext = idx.object_hi[leaves].max(axis=0) - idx.object_lo[leaves].min(axis=0)
        assert ext[0] == pytest.approx(326 * 30, rel=0.01) and ext[1] == pytest.approx(465 * 30, rel=0.01)
        # every tree once, ≤ 64 per group, each group's trees inside its box, on the ground
        groups = np.nonzero(idx.object_kind == TREES)[0]
        models = [decode_points(b) for b in store.model_geometries(range(len(idx.model_points)))]
        assert len(models) == len(idx.model_points) and all(len(m.positions) >= 1024 for m in models)
        seen = 0
        for g, blob in zip(groups, store.geometries(idx.rep_first[groups].tolist())):
            inst = decode_instances(blob, models=len(models))
            assert 1 <= len(inst) <= 64
            root = inst.matrix[:, :3, 3]
            assert (root >= idx.object_lo[g] - 1e-2).all() and (root <= idx.object_hi[g] + 1e-2).all()
            seen += len(inst)
        assert seen == summary["tree_instances"]
        check_tour(idx)


def test_megacity_small_has_an_hlod_forest_of_kept_proxies(tmp_path) -> None:
    path = tmp_path / "mc.db"
    summary = build_named("megacity", path, seed=2, size=300)
    with SceneStore.open(path) as store:
        idx = store.index
        meshes = np.nonzero(idx.object_kind == MESH)[0]
        assert meshes.size >= 300  # buildings and the ground
        check_hierarchy(idx, HLOD, one_root=False)
        assert summary["proxies"]["kept"] == int((idx.object_kind == HLOD).sum()) > 0
        check_chains(store, meshes[::40])
        # an HLOD proxy never has more faces than everything under it
        hl = np.nonzero(idx.object_kind == HLOD)[0]
        below = np.zeros(idx.n_objects)
        coarse = idx.rep_faces[idx.rep_first].astype(float)
        for o in reversed(range(idx.n_objects)):
            p = idx.object_parent[o]
            if p >= 0:
                below[p] += coarse[o] if idx.object_kind[o] == MESH else below[o]
        assert (idx.rep_faces[idx.rep_first[hl]] <= np.maximum(below[hl], 12)).all()
        assert summary["hierarchy_depth"] >= 2


# --------------------------------------------------------------------------- user files


def _two_meshes(tmp_path: Path, suffix: str) -> Path:
    a = trimesh.creation.icosphere(subdivisions=4, radius=2.0)
    b = trimesh.creation.box(extents=(3, 1, 2))
    b.apply_translation((6, 0, 0))
    path = tmp_path / f"pair{suffix}"
    if suffix in (".glb", ".gltf"):
        trimesh.Scene({"sphere": a, "box": b}).export(path)
    else:
        trimesh.util.concatenate([a, b]).export(path)
    return path


@pytest.mark.parametrize("suffix", [".glb", ".obj", ".ply"])
def test_user_mesh_files_build(tmp_path, suffix) -> None:
    src = _two_meshes(tmp_path, suffix)
    out = tmp_path / "user.db"
    summary = build_path(src, out)
    with SceneStore.open(out) as store:
        idx = store.index
        assert idx.n_objects == (2 if suffix == ".glb" else 1) == summary["objects"]["mesh"]
        assert summary["triangles"] == 5120 + 12  # icosphere(4) and a box
        check_chains(store, np.arange(idx.n_objects))
        check_tour(idx)


def test_multi_lod_cityjson_keeps_the_source_chain(tmp_path) -> None:
    out = tmp_path / "multi.db"
    build_path(data_file("city/multi_lod.city.json"), out)
    source = load_source(data_file("city/multi_lod.city.json"))
    with SceneStore.open(out) as store:
        idx = store.index
        multi = [o for o in source.objects if len(o.levels) >= 3]
        assert len(multi) == 10
        names = store.object_names()
        fid = store.fidelity()
        chains = []
        for o in multi:
            # the full LoD is kept; a coarser one only if it has fewer faces and passes the shape
            # guard, else the ladder's block or box stands in, or nothing
            i = names.index(o.name)
            reps = np.arange(idx.rep_first[i], idx.rep_first[i] + idx.rep_count[i])
            faces = idx.rep_faces[reps].tolist()
            assert faces[-1] == o.levels[-1].n_faces and faces == sorted(set(faces))
            rows = np.searchsorted(fid["rep"], reps[:-1])
            assert (fid["rep"][rows] == reps[:-1]).all() and (fid["iou"][rows] >= 0.9).all()
            chains.append(int(idx.rep_count[i]))
        assert max(chains) >= 2
        check_chains(store, np.flatnonzero(idx.object_kind == MESH), exact=False)  # not the ground's patches


def test_height_grid_and_citygml_trees_build(tmp_path) -> None:
    from matplotlib import cbook

    out = tmp_path / "jacksboro.db"
    build_path(cbook.get_sample_data("jacksboro_fault_dem.npz", asfileobj=False), out)
    with SceneStore.open(out) as store:
        check_hierarchy(store.index, TERRAIN)
        assert store.index.height >= 4
    out = tmp_path / "berlin.db"
    summary = build_path(data_file("trees/berlin_trees.gml"), out)
    assert summary["tree_instances"] == 288
    with SceneStore.open(out) as store:
        assert len(store.index.model_points) == 10
        assert store.index.meta["crs"] and "25833" in store.index.meta["crs"]


def test_a_broken_file_leaves_no_store(tmp_path) -> None:
    text = data_file("city/multi_lod.city.json").read_text()
    broken = tmp_path / "broken.city.json"
    broken.write_text(text[: len(text) // 2])
    out = tmp_path / "never.db"
    with pytest.raises(Exception) as err:
        build_path(broken, out)
    assert "broken.city.json" in str(err.value)
    assert list(tmp_path.iterdir()) == [broken]


def test_bad_source_is_named_and_leaves_no_store(tmp_path) -> None:
    source = load_source(data_file("trees/berlin_trees.gml"))
    source.trees.matrix[5, 0, 3] = np.nan
    out = tmp_path / "nan.db"
    with pytest.raises(SourceError, match=f"tree {source.trees.names[5]}: its matrix is not finite"):
        build_store(out, source, options=BuildOptions(workers=1))
    source = load_source(data_file("city/multi_lod.city.json"))
    source.objects[3].levels[1].faces[0, 0] = 10**6
    with pytest.raises(SourceError, match=f"object '{source.objects[3].name}' level 1: a face index"):
        build_store(out, source, options=BuildOptions(workers=1))
    assert list(tmp_path.iterdir()) == []


def test_failure_while_writing_leaves_no_store(tmp_path, monkeypatch) -> None:
    """A build that fails after the writer has written objects leaves no store and no temporary file."""
    import server.scene.builder as builder

    real = builder.encode_geometry
    calls = {"n": 0}

    def fail_late(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 40:
            raise OSError("disk full")
        return real(*args, **kwargs)

    monkeypatch.setattr(builder, "encode_geometry", fail_late)
    out = tmp_path / "late.db"
    with pytest.raises(OSError, match="disk full"):
        build_named("sthelens", out, seed=0, size=2000)
    assert calls["n"] == 40 and list(tmp_path.iterdir()) == []


def test_cli_builds_a_path_and_inspects_it(tmp_path) -> None:
    src = _two_meshes(tmp_path, ".glb")
    out = tmp_path / "cli.db"
    run = [sys.executable, "-m", "walkstream"]
    done = subprocess.run([*run, "build", str(src), "-o", str(out), "-q"], capture_output=True, text=True, timeout=240)
    assert done.returncode == 0, done.stderr
    done = subprocess.run([*run, "inspect", str(out), "--json"], capture_output=True, text=True, timeout=240)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert report == {**inspect_store(out), "index_load_s": report["index_load_s"]}
    mesh = report["kinds"]["mesh"]
    assert mesh["objects"] == 2 and report["schema_version"] == 2
    assert sum(lv["triangles"] for lv in mesh["levels"]) == int(SceneStore.open(out).index.rep_faces.sum())
    done = subprocess.run([*run, "inspect", str(out)], capture_output=True, text=True, timeout=240)
    assert "mesh: 2 objects" in done.stdout and "level 0" in done.stdout
    done = subprocess.run([*run, "inspect", str(tmp_path / "nope.db")], capture_output=True, text=True, timeout=240)
    assert done.returncode == 2 and "nope.db" in done.stderr


def test_sthelens_at_the_papers_grid_scale_keeps_its_extent(tmp_path) -> None:
    """--grid resamples the DEM (ZMK use 2049²); small here: same extent, heights within the DEM's range."""
    from server.scene.catalog import resample_grid
    from server.scene.importers.dem import load_dem

    dem = load_dem(data_file("terrain/SainteHelens.dem")).grids[0]
    fine = resample_grid(dem, 257)
    assert fine.heights.shape == (257, 257)
    rows, cols = dem.heights.shape
    assert fine.spacing[0] * 256 == pytest.approx(dem.spacing[0] * (cols - 1))
    assert fine.spacing[1] * 256 == pytest.approx(dem.spacing[1] * (rows - 1))
    # the same surface: against the DEM interpolated linearly at the fine samples' positions
    from scipy.interpolate import RegularGridInterpolator

    ys, xs = np.arange(rows) * dem.spacing[1], np.arange(cols) * dem.spacing[0]
    at = np.stack(np.meshgrid(np.arange(257) * fine.spacing[1], np.arange(257) * fine.spacing[0], indexing="ij"), -1)
    linear = RegularGridInterpolator((ys, xs), dem.heights)(np.minimum(at, [ys[-1], xs[-1]]))
    both = np.isfinite(linear) & np.isfinite(fine.heights)
    diff = np.abs(linear[both] - fine.heights[both])
    assert both.mean() > 0.8 and np.median(diff) < 2.0 and np.percentile(diff, 99) < 40.0
    assert np.nanmax(fine.heights) <= np.nanmax(dem.heights) + 50 and np.isnan(fine.heights).mean() < 0.2
    out = tmp_path / "fine.db"
    build_named("sthelens", out, size=1000, grid=257)
    with SceneStore.open(out) as store:
        idx = store.index
        terrain = np.nonzero(idx.object_kind == TERRAIN)[0]
        assert (idx.leaf[terrain]).sum() == (256 // 32) ** 2 and idx.meta["tree_instances"] == 1000
    with pytest.raises(ValueError, match="sthelens"):
        build_named("megacity", tmp_path / "x.db", grid=257)
