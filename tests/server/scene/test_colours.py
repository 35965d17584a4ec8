"""server.scene.colours: colours transferred to every level, split where they meet, morph maps kept."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from server.scene import blocks, palette
from server.scene.colours import Appearance, coloured_levels, split_by_colour, transfer
from server.scene.lod import build_chain
from server.scene.source import Mesh

ROOF, WALL = np.array(palette.ROOF, np.uint8), np.array(palette.WALL, np.uint8)


def _house(subdivisions: int = 3) -> Mesh:
    """A 10 × 8 m box of 6 m walls under a 3 m gable roof, subdivided; roof faces ROOF, the rest WALL."""
    box = trimesh.creation.box((10.0, 8.0, 6.0))
    box.apply_translation((0, 0, 3.0))
    ridge = trimesh.Trimesh([[-5, -4, 6], [5, -4, 6], [5, 4, 6], [-5, 4, 6], [-5, 0, 9], [5, 0, 9]],
                            [[0, 1, 5], [0, 5, 4], [2, 3, 4], [2, 4, 5], [1, 2, 5], [3, 0, 4]])
    house = trimesh.util.concatenate([box, ridge])
    house.merge_vertices()
    for _ in range(subdivisions):
        house = house.subdivide()
    tri = house.vertices[house.faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    roof = (tri[:, :, 2].min(axis=1) >= 6.0 - 1e-9) & (np.abs(n[:, 2]) > 0.3 * np.linalg.norm(n, axis=1))
    colours = np.where(roof[:, None], ROOF, WALL).astype(np.uint8)
    return Mesh(house.vertices, house.faces, face_colours=colours)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 4))
def test_split_keeps_positions_and_shares_vertices_only_within_a_colour(seed: int, n_colours: int) -> None:
    rng = np.random.default_rng(seed)
    p = rng.random((30, 3))
    f = rng.integers(0, 30, (50, 3))
    palette_ = rng.integers(0, 256, (n_colours, 3)).astype(np.uint8)
    fc = palette_[rng.integers(0, n_colours, 50)]
    sp, sf, sc, src = split_by_colour(p, f, fc)
    np.testing.assert_array_equal(sp[sf], p[f])  # every face where it was
    np.testing.assert_array_equal(sc[sf], np.repeat(fc[:, None], 3, axis=1))  # every corner in its face's colour
    np.testing.assert_array_equal(sp, p[src])
    # One copy per (vertex, colour) used: no two copies of a vertex share a colour.
    key = src * (1 << 24) + (sc[:, 0].astype(np.int64) << 16) + (sc[:, 1].astype(np.int64) << 8) + sc[:, 2]
    assert np.unique(key).size == key.size


def test_a_block_model_takes_roof_and_wall_colours_from_the_house() -> None:
    house = _house(1)
    ref = Appearance.of(house)
    p, f = blocks.block_model(house.positions, house.faces)
    colours = transfer(ref, p, f)
    tri = p[f]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    top, side = n[:, 2] > 0.9, np.abs(n[:, 2]) < 0.1
    assert top.any() and side.any()
    assert (colours[top] == ROOF).all() and (colours[side] == WALL).all()


@pytest.mark.parametrize("morph", ["collapse", "nearest"])
def test_coloured_levels_keep_the_chain_and_its_morphs(morph: str) -> None:
    house = _house(3)
    chain = build_chain(house.positions, house.faces, morph=morph, min_saving=0.4)
    assert len(chain) >= 3
    levels, maps, colours = coloured_levels(Appearance.of(house), chain.levels, chain.morph)
    assert len(levels) == len(chain) and maps[0] is None
    for k, ((p, f), (cp, cf), c) in enumerate(zip(levels, chain.levels, colours)):
        assert f.shape == cf.shape and c.shape == (p.shape[0], 3)
        assert p.shape[0] >= cp.shape[0]  # split vertices, never fewer
        corners = c[f]
        assert (corners == corners[:, :1]).all()  # one colour per face
        assert (c == ROOF).all(axis=1).any() and (c == WALL).all(axis=1).any()
        # The same surface as the uncoloured level: the same set of triangles.
        a = np.sort(np.round(p[f], 6).reshape(-1, 9), axis=0)
        b = np.sort(np.round(cp[cf], 6).reshape(-1, 9), axis=0)
        assert np.allclose(np.sort(a.ravel()), np.sort(b.ravel()))
        if k:
            m = maps[k]
            assert m.shape == (p.shape[0],) and 0 <= m.min() and m.max() < levels[k - 1][0].shape[0]
            # Every vertex still morphs to where it did, and to a copy of its own colour where one exists.
            np.testing.assert_allclose(levels[k - 1][0][m], chain.levels[k - 1][0][chain.morph[k]][_sources(p, cp)],
                                       atol=1e-9)
            same = (colours[k - 1][m] == c).all(axis=1)
            assert same.mean() > 0.9


def _sources(split: np.ndarray, original: np.ndarray) -> np.ndarray:
    """For each split vertex, the original vertex at its position (positions are unique per original)."""
    from scipy.spatial import cKDTree

    d, i = cKDTree(original).query(split)
    assert (d < 1e-12).all()
    return i


def test_vertex_colours_are_interpolated_on_a_coarser_level() -> None:
    sphere = trimesh.creation.icosphere(4, radius=5.0)
    x = sphere.vertices[:, 0]
    gradient = np.column_stack([(x + 5) / 10 * 255, np.full(x.size, 100), 255 - (x + 5) / 10 * 255])
    ref = Appearance(np.asarray(sphere.vertices), np.asarray(sphere.faces),
                     vertex_colours=np.rint(gradient).astype(np.uint8))
    chain = build_chain(sphere.vertices, sphere.faces)
    levels, maps, colours = coloured_levels(ref, chain.levels, chain.morph)
    for (p, _), c in zip(levels, colours):
        expected = (p[:, 0] / np.linalg.norm(p, axis=1) * 5 + 5) / 10 * 255  # the gradient where p projects
        assert np.abs(c[:, 0].astype(float) - np.clip(expected, 0, 255)).max() < 40
        assert (c[:, 1] == 100).all()
    assert all(m is None or np.array_equal(m, cm) for m, cm in zip(maps, chain.morph))  # per vertex: no split


def test_merge_of_face_and_vertex_colours_is_per_vertex() -> None:
    house = Appearance.of(_house(0))
    painted = Appearance(house.positions + 20, house.faces,
                         vertex_colours=np.full((house.positions.shape[0], 3), 7, np.uint8))
    both = Appearance.merge([house, None, painted])
    assert not both.by_face and both.vertex_colours.shape == (2 * house.positions.shape[0], 3)
    assert Appearance.merge([house, house]).by_face
    assert Appearance.merge([None]) is None


def test_a_built_store_carries_colours_in_every_level_and_proxy(tmp_path) -> None:
    from proto.geometry import decode_geometry
    from proto.morph import decode_morph
    from server.scene.catalog import build_path
    from server.scene.data import data_file
    from server.scene.index import HLOD
    from server.scene.store import SceneStore

    out = tmp_path / "fzk.db"
    build_path(data_file("interior/AC20-FZK-Haus.city.json"), out, workers=1)
    with SceneStore.open(out) as store:
        idx = store.index
        assert (idx.object_kind == HLOD).any()
        blobs = store.geometries(range(idx.n_representations))
        geometries = [decode_geometry(b) for b in blobs]
        assert all(g.colours is not None for g in geometries)
        assert (idx.rep_bytes == [len(b) for b in blobs]).all()  # the byte cost is the coloured payload's
        seen = {tuple(c) for g in geometries for c in g.colours.tolist()}
        assert palette.ROOF in seen and palette.WALL in seen and palette.SURFACES["Window"] in seen
        for rep in np.flatnonzero(idx.rep_morph):
            decode_morph(store.morph(int(rep)), n_fine=geometries[rep].vertices,
                         n_coarse=geometries[rep - 1].vertices)
        roots = np.flatnonzero((idx.object_kind == HLOD) & (idx.object_parent < 0))
        root = geometries[int(idx.rep_first[roots[0]])]
        assert palette.ROOF in {tuple(c) for c in root.colours.tolist()}  # the house's roof, seen from afar


def test_generated_scenes_stay_colourless(demo_store) -> None:
    from proto.geometry import decode_geometry
    from server.scene.store import SceneStore

    with SceneStore.open(demo_store) as store:
        assert decode_geometry(store.geometry(0)).colours is None
