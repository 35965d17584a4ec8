"""Coarse levels and HLOD proxies that keep their object's shape: the ladder, the measures, the guard."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from proto.geometry import decode_geometry
from server.scene.blocks import block_model, oriented_box
from server.scene.builder import BuildOptions, build_store
from server.scene.data import data_file
from server.scene.fidelity import Bounds, _draw, is_closed, measure, reference, surface_area
from server.scene.proxies import merge as _merge
from server.scene.generate.megacity import megacity
from server.scene.importers import load_source
from server.scene.index import HLOD, MESH
from server.scene.ladder import shaped_chain
from server.scene.lod import build_chain
from server.scene.source import SourceScene
from server.scene.store import SceneStore


@settings(max_examples=25, deadline=None)
@given(st.floats(2, 40), st.floats(2, 40), st.floats(3, 60), st.floats(0, np.pi))
def test_block_and_box_of_a_box_are_that_box(w, d, h, turn) -> None:
    m = trimesh.creation.box((w, d, h))
    m.apply_transform(trimesh.transformations.rotation_matrix(turn, [0, 0, 1]))
    m.apply_translation([100.0, -50.0, h / 2])
    for make in (block_model, oriented_box):
        p, f = make(m.vertices, m.faces)
        assert is_closed(f) and f.shape[0] == 12
        assert surface_area(p, f) == pytest.approx(m.area, rel=1e-3)
        out = trimesh.Trimesh(p, f, process=False)
        assert out.volume == pytest.approx(m.volume, rel=1e-3)  # outward faces: positive volume


def test_decimation_that_loses_the_walls_is_not_kept() -> None:
    """A megacity building: quadric decimation's coarsest level loses its walls; the ladder keeps none such."""
    src, _, _ = megacity(8)
    m = src.objects[0].levels[0]
    plain = build_chain(m.positions, m.faces)
    ref = reference(*plain.levels[-1])
    worst = measure(ref, *plain.levels[0], plain.errors[0])
    assert worst.iou < 0.5 and worst.area_ratio < 0.5  # the defect, as the plain chain has it
    shaped = shaped_chain(m.positions, m.faces, building=True)
    assert shaped.dropped + shaped.regenerated >= 1
    assert all(Bounds().passes(q, True) for q in shaped.fidelity)
    assert shaped.chain.faces[0] < m.n_faces * 0.2


def _mesh(geometry) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(geometry.positions, np.float64), np.asarray(geometry.indices, np.int64).reshape(-1, 3)


def _check_store(path, bounds: Bounds = Bounds(), remeasure: int = 6) -> dict:
    """Every measured coarse mesh level and every HLOD proxy passes the bounds (area where the
    measured mesh is closed); a few of each are measured again from the stored geometry, so the
    table cannot pass what the geometry does not. Returns counts."""
    with SceneStore.open(path) as store:
        idx = store.index
        fid = store.fidelity()
        assert fid is not None
        # every mesh but ground sheets is measured (those keep plain decimation)
        ground = [i for i, c in enumerate(idx.class_names) if c in ("terrain", "ground")]
        meshes = np.flatnonzero((idx.object_kind == MESH) & ~np.isin(idx.object_class, ground))
        full = idx.rep_first[meshes] + idx.rep_count[meshes] - 1
        coarse = np.concatenate([np.arange(a, b) for a, b in zip(idx.rep_first[meshes], full)] + [np.zeros(0, int)])
        rows = np.searchsorted(fid["rep"], coarse)
        assert (fid["rep"][rows] == coarse).all()
        assert (fid["iou"][rows] >= bounds.iou).all()
        assert not (fid["flip"][rows] > bounds.flip).any()
        closed = np.array([is_closed(decode_geometry(b).indices) for b in store.geometries(full.tolist())], bool)
        owner = np.repeat(np.arange(meshes.size), idx.rep_count[meshes] - 1)
        area = fid["area_ratio"][rows]
        assert (np.minimum(area, 1 / area)[closed[owner]] >= bounds.area).all()
        for r in coarse[:: max(1, coarse.size // remeasure)][:remeasure]:  # again, from the stored geometry
            o = idx.rep_object[r]
            level, finest = (_mesh(decode_geometry(b)) for b in store.geometries([int(r), int(idx.rep_first[o] + idx.rep_count[o] - 1)]))
            again = measure(reference(*finest), *level, 1.0, with_flip=False)
            assert again.iou >= bounds.iou - 0.02
            assert not is_closed(finest[1]) or min(again.area_ratio, 1 / again.area_ratio) >= bounds.area - 0.03
        # HLOD proxies: all measured, all within bounds; a few against their subtree's coarsest levels
        nodes = np.flatnonzero(idx.object_kind == HLOD)
        reps = idx.rep_first[nodes]
        at = np.searchsorted(fid["rep"], reps)
        assert (fid["rep"][np.minimum(at, fid["rep"].size - 1)] == reps).all()
        assert (fid["iou"][at] >= bounds.iou).all() and not (fid["flip"][at] > bounds.flip).any()
        node_area = np.minimum(fid["area_ratio"][at], 1 / fid["area_ratio"][at])
        assert (node_area[fid["closed"][at]] >= bounds.area).all()
        for node in nodes[:: max(1, nodes.size // remeasure)][:remeasure]:
            under = [o for o in meshes if node in _ancestors(idx.object_parent, o)]
            objs = [_mesh(decode_geometry(b)) for b in store.geometries(idx.rep_first[under].tolist())]
            proxy = _mesh(decode_geometry(store.geometries([int(idx.rep_first[node])])[0]))
            ref = reference(*_merge(objs), samples=4)
            again = measure(ref, *proxy, 1.0, with_flip=False)
            assert again.iou >= bounds.iou - 0.02
            closed_objects = all(is_closed(f) for _, f in objs)
            assert not closed_objects or min(again.area_ratio, 1 / again.area_ratio) >= bounds.area - 0.03
        return {"coarse": coarse.size, "hlod": nodes.size}


def _ancestors(parent: np.ndarray, o: int) -> set[int]:
    out = set()
    while parent[o] >= 0:
        o = int(parent[o])
        out.add(o)
    return out


@pytest.mark.parametrize("name", ["interior/AC20-FZK-Haus.city.json", "city/multi_lod.city.json",
                                  "city/DenHaag_01.city.json"])
def test_real_buildings_keep_only_levels_within_bounds(tmp_path, name) -> None:
    source = load_source(data_file(name))
    if len(source.objects) > 120:  # Den Haag: a block of it keeps the suite fast
        source = SourceScene(objects=source.objects[:120], crs=source.crs, sources=source.sources)
    out = tmp_path / "s.db"
    summary = build_store(out, source, options=BuildOptions(workers=1, hlod_min=16))
    got = _check_store(out)
    assert summary["levels"]["measured"] == got["coarse"] and summary["levels"]["below_bounds"] == 0
    proxies = summary.get("proxies", {"kept": 0, "below_bounds": 0})
    assert proxies["kept"] == got["hlod"] and proxies["below_bounds"] == 0


def test_megacity_block_has_walls_at_street_level(tmp_path) -> None:
    """Every kept coarse level and proxy passes; an along-the-street view of the coarsest cut (the
    roots of the kept HLOD forest at their coarsest) covers the walls."""
    src, _, _ = megacity(64)
    out = tmp_path / "m.db"
    summary = build_store(out, src, options=BuildOptions(workers=1))
    got = _check_store(out)
    assert summary["levels"]["dropped"] > 0  # the guard removed the wall-less levels decimation made
    assert got["hlod"] > 0 and summary["proxies"]["kept"] == got["hlod"]
    from server.scene.inspect import format_report, inspect_store

    report = inspect_store(out)
    assert report["kinds"]["hlod"]["fidelity"]["measured"] == got["hlod"]
    assert report["shape_guard"]["proxies"] == summary["proxies"]
    assert "\n".join(format_report(report)).count("all within bounds") == 2  # buildings and proxies
    with SceneStore.open(out) as store:
        idx = store.index
        building = idx.class_names.index("building")
        meshes = np.flatnonzero((idx.object_kind == MESH) & (idx.object_class == building))
        roots = np.flatnonzero((idx.object_parent == -1) & ((idx.object_kind == HLOD) | (idx.object_class == building)))
        coarse = [decode_geometry(b) for b in store.geometries(idx.rep_first[roots].tolist())]
        full = [decode_geometry(b) for b in store.geometries((idx.rep_first[meshes] + idx.rep_count[meshes] - 1).tolist())]

    def view(geoms):
        """Orthographic view along +y of the street level (0..8 m): per pixel, |n_z| of the nearest face."""
        pos = np.concatenate([np.asarray(g.positions, np.float64) for g in geoms])
        off = np.cumsum([0] + [len(g.positions) for g in geoms[:-1]])
        fac = np.concatenate([np.asarray(g.indices, np.int64).reshape(-1, 3) + o for g, o in zip(geoms, off)])
        lo = np.array([pos[:, 0].min(), 0.0])
        ext = np.array([np.ptp(pos[:, 0]), 8.0])
        res = np.array([512, 64])
        uv = np.column_stack([(pos[:, 0] - lo[0]) / ext[0] * res[0], (pos[:, 2] - lo[1]) / ext[1] * res[1], -pos[:, 1]])
        tri = pos[fac]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        nz = np.abs(n[:, 2]) / np.maximum(np.linalg.norm(n, axis=1), 1e-30)
        image, _ = _draw(uv[fac], nz, int(res[1]), int(res[0]))
        return image

    detail, cut = view(full), view(coarse)
    walls = (detail >= 0) & (detail < 0.3)  # faces within ~17° of vertical
    assert walls.sum() > 1000
    assert (cut[walls] >= 0).mean() >= 0.9


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 40))
def test_coverage_masks_match_the_z_buffer_rasteriser(seed, n) -> None:
    """The silhouettes' coverage kernel covers exactly the pixels the shading rasteriser draws."""
    from server.scene.fidelity import silhouettes

    rng = np.random.default_rng(seed)
    p = rng.uniform(-5, 5, (3 * n, 3))
    f = rng.permutation(3 * n).reshape(n, 3)
    lo, hi = p.min(axis=0) - 0.1, p.max(axis=0) + 0.1
    uv = (p[f] - lo) / (hi - lo) * 32
    masks = silhouettes(p, f, lo, hi, res=32)
    for axis in range(3):
        a, b = [k for k in range(3) if k != axis]
        image, _ = _draw(np.stack([uv[..., a], uv[..., b], uv[..., axis]], axis=-1), np.ones(n), 32, 32)
        assert np.array_equal(masks[axis], image > 0)


@settings(max_examples=30, deadline=None)
@given(st.floats(1, 30), st.floats(1, 30), st.floats(1, 30), st.integers(0, 11))
def test_is_closed_sees_a_missing_face(w, d, h, drop) -> None:
    m = trimesh.creation.box((w, d, h))
    assert is_closed(m.faces)
    assert not is_closed(np.delete(m.faces, drop, axis=0))


def test_inspect_reports_levels_and_proxies_against_the_bounds(tmp_path) -> None:
    """inspect counts, per kind and level (depth for proxies), what is below the bounds — an open
    mesh's area ratio is not — names the worst, and prints the build's guard counts."""
    from server.scene.inspect import format_report, inspect_store
    from server.scene.writer import SceneWriter, encode_levels

    box = trimesh.creation.box((10, 10, 10))
    tent = trimesh.creation.box((10, 10, 10))
    tent.faces = tent.faces[:-2]  # open: its area ratio does not count
    path = tmp_path / "s.db"
    with SceneWriter(path, name="t") as w:
        for name, mesh, q in (("good", box, ("prune", 0.95, 0.97, 0.02, True)),
                              ("thin", box, ("decimate", 0.3, 0.95, 0.02, True)),
                              ("open", tent, ("decimate", 0.3, 0.95, 0.02, False))):
            lo, hi, blobs, _ = encode_levels([(mesh.vertices, mesh.faces)] * 2, [None, None], reorder=False)
            w.add_encoded(name, "building", lo, hi, [0.5, 0.0], blobs, fidelity=[q, ("source", 1, 1, float("nan"), True)])
        lo, hi, blobs, _ = encode_levels([(box.vertices, box.faces)], [None], reorder=False)
        w.add_encoded("hlod_0", "hlod", lo, hi, [1.0], blobs, kind=HLOD, fidelity=[("box", 0.9, 0.8, 0.1, True)])
        w.set_tour([{"t": 0.0, "eye": [0, -40, 5], "forward": [0, 1, 0], "up": [0, 0, 1]},
                    {"t": 1.0, "eye": [0, -30, 5], "forward": [0, 1, 0], "up": [0, 0, 1]}])
        w.set_meta(shape_guard={"levels": {"measured": 3, "below_bounds": 0, "regenerated": 1, "dropped": 2},
                                "proxies": {"nodes": 3, "kept": 1, "below_bounds": 0, "regenerated": 0, "dropped": 2}})
    report = inspect_store(path)
    mesh, hlod = report["kinds"]["mesh"]["fidelity"], report["kinds"]["hlod"]["fidelity"]
    assert mesh["measured"] == 3 and mesh["below_bounds"] == 1 and mesh["worst"][0]["name"] in ("thin", "open")
    assert hlod["measured"] == 1 and hlod["below_bounds"] == 1 and hlod["levels"][0]["depth"] == 0
    assert hlod["worst"][0]["name"] == "hlod_0" and hlod["worst"][0]["method"] == "box"
    text = "\n".join(format_report(report))
    assert "1 below bounds" in text and "1 of 3 nodes kept" in text and "2 not kept" in text
