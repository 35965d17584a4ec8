"""The walkable grid: built from real stores, stored at build time, read back, and sent on the wire."""

from __future__ import annotations

import shutil
import sqlite3

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from proto.walkable import decode, encode
from server.scene.builder import BuildOptions, build_store
from server.scene.inspect import inspect_store
from server.scene.source import HeightGrid, SourceScene
from server.scene.store import SceneStore
from server.scene.walkable import CLEARANCE, MAX_CELLS, STEP, cell_size, walkable_grid
from server.scene.writer import SceneWriter


def _box(lo, hi) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    m = trimesh.creation.box(hi - lo)
    m.apply_translation((lo + hi) / 2)
    return m


def _plane(half: float, z: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    p = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]], float)
    return p, np.array([[0, 1, 2], [0, 2, 3]])


def _store(path, objects) -> SceneStore:
    """A store of (name, class, (positions, faces)) objects, the walkable grid computed at commit."""
    with SceneWriter(path, name="t") as w:
        for name, cls, mesh in objects:
            pos, fac = (mesh.vertices, mesh.faces) if isinstance(mesh, trimesh.Trimesh) else mesh
            w.add_object(name, cls, [(np.asarray(pos, float), np.asarray(fac))], [0.0])
    return SceneStore.open(path)


def _at(grid, x, y) -> float:
    return float(grid.height(np.array([[x, y]]))[0])


def test_a_building_blocks_its_cells_and_the_street_around_it_is_ground(tmp_path):
    objects = [
        ("ground", "ground", _plane(10.0)),
        ("house", "building", _box((-2, -2, 0), (2, 2, 6))),
        ("table", "table", trimesh.util.concatenate([_box((4, -1, 0.7), (6, 1, 0.75))] + [
            _box((x, y, 0), (x + 0.05, y + 0.05, 0.7)) for x in (4, 5.95) for y in (-1, 0.95)])),
        ("bridge", "bridge", _box((-9, 4, 3.0), (-5, 8, 3.4))),
        ("kerb", "pavement", _box((4, 4, 0), (8, 8, 0.15))),
    ]
    with _store(tmp_path / "t.db", objects) as store:
        grid = store.walkable()
    for x, y in [(0, 0), (1.8, -1.8), (-1.5, 1.9), (5, 0), (4.5, 0.5)]:  # in the house, under the table
        assert np.isnan(_at(grid, x, y)), (x, y)
    assert _at(grid, 2.3, 0) == pytest.approx(0.0, abs=1e-3)  # the street beside the wall
    assert _at(grid, -7, 6) == pytest.approx(0.0, abs=1e-3)  # under the bridge: headroom enough
    assert _at(grid, 6, 6) == pytest.approx(0.15, abs=1e-3)  # a kerb is stepped onto
    assert _at(grid, 3.0, 3.0) == pytest.approx(0.0, abs=1e-3)
    # The roof is flat and has headroom, but no one walks onto it: too high a step, too small a region.
    assert np.isnan(grid.ground[grid.cells(np.array([[0.0, 0.0]]))[:2]]).all()


def test_terrain_heights_come_through_and_a_cliff_is_not_walkable(tmp_path):
    x = np.arange(41.0)
    heights = np.tile(np.where(x < 25, 0.2 * x, 0.2 * x + 6.0), (41, 1))  # 11° slope, then a 6 m cliff
    source = SourceScene(grids=[HeightGrid("dem", heights, (1000.0, 2000.0), (1.0, 1.0))])
    path = tmp_path / "terrain.db"
    build_store(path, source, options=BuildOptions(workers=1, shape_guard=False))
    with SceneStore.open(path) as store:
        grid = store.stored_walkable()
        origin = np.asarray(store.index.meta["origin"])
    assert grid is not None
    px = np.array([3.3, 10.0, 17.7, 30.2, 37.0])
    xy = np.column_stack([1000.0 + px, np.full(px.size, 2020.0)]) - origin[:2]
    expected = np.where(px < 25, 0.2 * px, 0.2 * px + 6.0) - origin[2]
    np.testing.assert_allclose(grid.height(xy), expected, atol=0.02)
    cliff = np.column_stack([1000.0 + np.linspace(24.0, 25.0, 11), np.full(11, 2020.0)]) - origin[:2]
    assert np.isnan(grid.height(cliff)).any()  # the top of the cliff's face


def test_the_auditorium_is_walkable_between_rows_and_inside_its_hall(auditorium_store):
    from server.scene.generate.auditorium import FIRST_ROW_Y, RISER, ROW_PITCH

    with SceneStore.open(auditorium_store) as store:
        grid = store.walkable()
        origin = np.asarray(store.index.meta["origin"])

    def at(x, y):
        return _at(grid, x - origin[0], y - origin[1]) + origin[2]

    row = lambda r: FIRST_ROW_Y + r * ROW_PITCH  # noqa: E731
    assert at(0.0, row(10)) == pytest.approx(10 * RISER, abs=0.02)  # the central aisle, on tier 10
    assert at(-3.0, row(10) - 0.45) == pytest.approx(10 * RISER, abs=0.02)  # between rows 9 and 10, in a block
    assert np.isnan(at(-3.0, row(10)))  # a chair of row 10
    assert at(-13.5, 20.0) == pytest.approx(np.floor((20.0 - FIRST_ROW_Y + ROW_PITCH / 2) / ROW_PITCH) * RISER,
                                            abs=0.02)  # the side aisle climbs with the tiers
    assert np.isnan(at(-15.15, 20.0)) and np.isnan(at(15.15, 20.0))  # the walls
    assert at(0.0, 7.5) == pytest.approx(0.0, abs=0.02)  # the floor before the stage
    share = np.isfinite(grid.ground).mean()
    assert 0.5 < share < 0.95


def test_a_store_built_before_grids_computes_the_same_grid_on_first_use(demo_store, tmp_path):
    old = tmp_path / "old.db"
    shutil.copy(demo_store, old)
    with sqlite3.connect(old) as conn:
        conn.execute("DROP TABLE walkable")
    assert inspect_store(old)["walkable"] == {"stored": False}
    with SceneStore.open(demo_store) as built, SceneStore.open(old) as store:
        assert store.stored_walkable() is None
        computed = store.walkable()
        np.testing.assert_array_equal(computed.ground, built.stored_walkable().ground)
        assert computed.cell == built.walkable().cell and computed.origin == built.walkable().origin


def test_the_wire_bytes_are_encoded_once_and_decode_to_the_stored_grid(demo_store):
    with SceneStore.open(demo_store) as store:
        grid = store.walkable()
        data = store.walkable_encoded()
        assert store.walkable_encoded() is data  # cached: every welcome shares one encoding
        assert data == encode(grid)
    back = decode(data)
    assert back.shape == grid.shape and back.origin == grid.origin and back.cell == grid.cell
    both = np.isfinite(grid.ground)
    np.testing.assert_array_equal(np.isfinite(back.ground), both)
    np.testing.assert_allclose(back.ground[both], grid.ground[both], atol=2e-3)


def test_inspect_reports_the_grid(demo_store):
    report = inspect_store(demo_store)["walkable"]
    with SceneStore.open(demo_store) as store:
        grid = store.walkable()
    assert report["stored"] and report["shape"] == list(grid.shape)
    assert report["cell"] == pytest.approx(grid.cell, abs=1e-4)
    assert report["walkable_share"] == pytest.approx(np.isfinite(grid.ground).mean(), abs=1e-4)
    assert 0.9 < report["walkable_share"] <= 1.0  # a sculpture garden: the sculptures are what is blocked


@given(st.floats(1.0, 1e5), st.floats(1.0, 1e5))
def test_the_cell_size_keeps_the_grid_within_its_limit(w, h):
    cell = cell_size(np.array([[0.0, 0.0], [w, h]]))
    assert np.ceil(w / cell) * np.ceil(h / cell) <= MAX_CELLS
    assert cell >= 0.1


_boxes = st.lists(st.tuples(st.floats(-8, 6), st.floats(-8, 6), st.floats(0.5, 3), st.floats(0.5, 3),
                            st.floats(0.0, 1.5), st.floats(0.05, 5.0)), min_size=1, max_size=5)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(_boxes)
def test_every_walkable_cell_is_finite_in_range_and_never_inside_an_obstacle(tmp_path, boxes):
    objects = [("ground", "ground", _plane(10.0))]
    for i, (x, y, w, d, z0, h) in enumerate(boxes):
        objects.append((f"b{i}", "thing", _box((x, y, z0), (x + w, y + d, z0 + h))))
    path = tmp_path / "h.db"
    path.unlink(missing_ok=True)
    with SceneWriter(path, name="h", walkable=False) as w:
        for name, cls, mesh in objects:
            pos, fac = (mesh.vertices, mesh.faces) if isinstance(mesh, trimesh.Trimesh) else mesh
            w.add_object(name, cls, [(np.asarray(pos, float), np.asarray(fac))], [0.0])
    with SceneStore.open(path) as store:
        grid = walkable_grid(store)
        lo, hi = store.index.bounds[:, 2]
    g = grid.ground[np.isfinite(grid.ground)]
    assert g.size and (g >= lo - 1e-4).all() and (g <= hi + 1e-4).all()  # (float32 heights)
    ny, nx = grid.shape
    jj, ii = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    centre = np.column_stack([grid.origin[0] + (ii.ravel() + 0.5) * grid.cell,
                              grid.origin[1] + (jj.ravel() + 0.5) * grid.cell])
    ground = grid.ground.ravel()
    tol = 1e-3
    for x, y, w, d, z0, h in boxes:
        over = ((centre[:, 0] > x + grid.cell) & (centre[:, 0] < x + w - grid.cell)
                & (centre[:, 1] > y + grid.cell) & (centre[:, 1] < y + d - grid.cell))
        g = np.where(np.isfinite(ground), ground, np.inf)
        in_headroom = (z0 <= g + CLEARANCE - tol) & (z0 + h > g + STEP + tol)
        at_feet = (z0 < g + 0.05 - tol) & (z0 + h > g + 0.05 + tol)  # standing inside the box
        assert not (over & (in_headroom | at_feet)).any()


def test_a_walk_path_goes_round_a_wall_and_never_through_it():
    from proto.walkable import WalkableGrid
    from proto.walkpath import NoPath, largest_region, walk_path

    ground = np.zeros((40, 40), np.float32)
    ground[:30, 20] = np.nan  # a wall from y = 0 to 15 at x = 10
    grid = WalkableGrid(origin=(0.0, 0.0), cell=0.5, ground=ground)
    path = walk_path(grid, (2.0, 2.0), (18.0, 2.0))
    assert np.allclose(path[0], [2, 2]) and np.allclose(path[-1], [18, 2])
    s = np.linspace(0.0, 1.0, 400)[:, None]
    for a, b in zip(path[:-1], path[1:]):
        assert grid.walkable(a + s * (b - a)).all()
    assert path[:, 1].max() >= 15.0  # round the wall's end
    assert largest_region(grid).sum() == np.isfinite(ground).sum()
    ground[:, 20] = np.nan  # the wall now splits the floor
    with pytest.raises(NoPath, match="different regions"):
        walk_path(WalkableGrid(origin=(0.0, 0.0), cell=0.5, ground=ground), (2.0, 2.0), (18.0, 2.0))
