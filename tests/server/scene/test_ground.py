"""server.scene.ground: a ground under scenes without terrain, never above an object's base, built as terrain."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from server.scene.builder import BuildOptions, build_store
from server.scene.data import data_file
from server.scene.ground import GROUND_NAME, SINK, ground_grid, needs_ground
from server.scene.importers import load_source
from server.scene.index import TERRAIN
from server.scene.source import HeightGrid, Mesh, SourceObject, SourceScene
from server.scene.store import SceneStore


def _box(x: float, y: float, z: float, size: float = 10.0) -> SourceObject:
    lo = np.array([x, y, z])
    corners = lo + np.array([[i, j, k] for i in (0, size) for j in (0, size) for k in (0, size)])
    faces = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
             [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    return SourceObject(f"b{x}_{y}", "building", [Mesh(corners, faces)])


def _height_at(grid: HeightGrid, xy: np.ndarray) -> np.ndarray:
    """The grid's samples nearest each point (the ground under a box's plan is lowered on whole cells)."""
    c = np.rint((xy[:, 0] - grid.origin[0]) / grid.spacing[0]).astype(int)
    r = np.rint((xy[:, 1] - grid.origin[1]) / grid.spacing[1]).astype(int)
    return grid.heights[r, c]


@settings(max_examples=25, deadline=None)
@given(st.lists(st.tuples(st.floats(-300, 300), st.floats(-300, 300), st.floats(-5, 20)), min_size=1, max_size=12))
def test_the_ground_is_never_above_a_base_and_covers_the_padded_plan(boxes) -> None:
    scene = SourceScene(objects=[_box(*b) for b in boxes])
    grid = ground_grid(scene)
    lo = np.array([[x, y] for x, y, _ in boxes])
    hi = lo + 10.0
    extent = float(np.max(hi.max(axis=0) - lo.min(axis=0)))
    margin = max(50.0, 0.5 * extent)
    ny, nx = grid.heights.shape
    far = np.array(grid.origin) + np.array(grid.spacing) * [nx - 1, ny - 1]
    assert (np.array(grid.origin) <= lo.min(axis=0) - margin + 1e-6).all() and (far >= hi.max(axis=0) + margin - 1e-6).all()
    assert np.isfinite(grid.heights).all() and grid.attributes["class"] == "ground"
    for (x, y, z) in boxes:  # under every box's plan (corners and centre) the ground is below its base
        plan = np.array([[x, y], [x + 10, y], [x, y + 10], [x + 10, y + 10], [x + 5, y + 5]])
        assert (_height_at(grid, plan) <= z - SINK + 1e-9).all()
    assert grid.heights.min() >= min(z for _, _, z in boxes) - SINK - 1e-9  # and never below the lowest base


def test_a_flat_city_gets_a_flat_ground_at_its_base() -> None:
    scene = SourceScene(objects=[_box(x, y, 3.0) for x in (0, 40, 80) for y in (0, 30)])
    grid = ground_grid(scene)
    assert np.allclose(grid.heights, 3.0 - SINK)


def test_only_scenes_without_terrain_need_a_ground() -> None:
    city = SourceScene(objects=[_box(0, 0, 0)])
    assert needs_ground(city)
    assert not needs_ground(SourceScene())
    chair = SourceObject("chair_1", "chair", city.objects[0].levels)
    assert not needs_ground(SourceScene(objects=[chair]))  # a chair in space is no city
    assert not needs_ground(dataclasses.replace(city, grids=[HeightGrid("dem", np.zeros((2, 2)), (0, 0), (1, 1))]))
    tin = SourceObject("tin", "terrain", [Mesh(np.eye(3), [[0, 1, 2]])])
    assert not needs_ground(dataclasses.replace(city, objects=[*city.objects, tin]))


def test_a_built_city_stands_on_its_ground_and_its_tour_frames_the_buildings(tmp_path) -> None:
    source = load_source(data_file("trees/berlin_buildings_lod2.gml"))
    stores = {}
    for ground in (True, False):
        out = tmp_path / f"berlin_{ground}.db"
        build_store(out, source, options=BuildOptions(ground=ground, workers=1))
        stores[ground] = SceneStore.open(out)
    with stores[True] as with_ground, stores[False] as without:
        idx = with_ground.index
        assert idx.meta["ground"] == "generated" and without.index.meta["ground"] == "none"
        names = with_ground.object_names()
        patches = [i for i, n in enumerate(names) if n.startswith(f"{GROUND_NAME}/patch_")]
        assert patches and (idx.object_kind[patches] == TERRAIN).all()
        assert (idx.object_kind == TERRAIN).sum() == len(patches)
        # The ground reaches beyond the buildings on every side; the orbit tour is the one without it.
        buildings = idx.object_kind != TERRAIN
        assert (idx.object_lo[patches].min(axis=0)[:2] < idx.object_lo[buildings].min(axis=0)[:2] - 50).all()
        assert with_ground.index.tour == without.index.tour


def test_den_haag_keeps_its_terrain(denhaag_store) -> None:
    with SceneStore.open(denhaag_store) as store:
        assert not any(n.startswith(f"{GROUND_NAME}/patch_") for n in store.object_names())
        assert store.index.meta.get("ground") in ("terrain", None)


@pytest.mark.parametrize("cells", [32, 64])
def test_the_ground_grid_fits_the_terrain_patches(cells) -> None:
    grid = ground_grid(SourceScene(objects=[_box(0, 0, 0, 100.0)]), cells=cells)
    assert max(grid.heights.shape) == cells + 1
