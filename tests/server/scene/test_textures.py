"""Base-colour textures from a glTF through import, every level and the store's byte counts."""

from __future__ import annotations

import logging

import msgpack
import numpy as np
import pytest
import trimesh
from hypothesis import given
from hypothesis import strategies as st
from PIL import Image
from trimesh.visual.material import PBRMaterial

from proto.geometry import decode_geometry, encode_geometry
from proto.texture import encode_texture
from server.scene.catalog import build_path
from server.scene.importers import load_source
from server.scene.source import Mesh
from server.scene.store import SceneStore
from server.scene.texcoords import COARSEST_SIDE, FINEST_SIDE, level_sides

RED, GREEN = (220, 30, 30), (30, 200, 40)
RADIUS, HEIGHT = 6.0, 4.0


def checker(side: int, cells: int) -> np.ndarray:
    """(side, side, 3) uint8: a bold red/green checkerboard of cells × cells squares."""
    tex = np.zeros((side, side, 3), np.uint8)
    odd = (np.indices((side, side)) // (side // cells)).sum(axis=0) % 2 == 1
    tex[~odd], tex[odd] = RED, GREEN
    return tex


def curved_wall(texture: np.ndarray | None, cols: int = 64, rows: int = 16) -> trimesh.Trimesh:
    """An open half-cylinder wall (glTF's y up), u along the arc and v up the wall; fine enough that the
    builder makes several levels of it."""
    th, z = np.meshgrid(np.linspace(0, np.pi, cols + 1), np.linspace(0, HEIGHT, rows + 1))
    v = np.column_stack([RADIUS * np.cos(th).ravel(), z.ravel(), -RADIUS * np.sin(th).ravel()])
    i = (np.arange(rows)[:, None] * (cols + 1) + np.arange(cols)[None, :]).ravel()
    f = np.concatenate([np.column_stack([i, i + 1, i + cols + 2]), np.column_stack([i, i + cols + 2, i + cols + 1])])
    mesh = trimesh.Trimesh(v, f, process=False)
    material = PBRMaterial(baseColorFactor=[255, 255, 255, 255],
                           baseColorTexture=None if texture is None else Image.fromarray(texture))
    mesh.visual = trimesh.visual.TextureVisuals(uv=np.column_stack([(th / np.pi).ravel(), (z / HEIGHT).ravel()]),
                                                material=material)
    return mesh


@pytest.fixture(scope="module")
def wall_store(tmp_path_factory):
    folder = tmp_path_factory.mktemp("textures")
    trimesh.Scene(curved_wall(checker(2048, 16))).export(folder / "wall.glb")
    build_path(folder / "wall.glb", folder / "wall.db", workers=1)
    return folder / "wall.db"


def test_a_textured_gltf_keeps_its_uvs_and_texture_and_its_mean_colour(tmp_path) -> None:
    tex = checker(64, 8)
    trimesh.Scene(curved_wall(tex, 8, 2)).export(tmp_path / "wall.glb")
    mesh = load_source(tmp_path / "wall.glb").objects[0].levels[0]
    assert mesh.textured and mesh.uv.shape == (mesh.n_vertices, 2)
    np.testing.assert_array_equal(mesh.texture, tex)
    # flat and lit still draw the texture's mean colour
    np.testing.assert_allclose(mesh.face_colours[0], tex.reshape(-1, 3).mean(axis=0), atol=1)
    # the UVs came through with their vertices: u runs along the arc (z-up after import)
    theta = np.arctan2(mesh.positions[:, 1], mesh.positions[:, 0])
    np.testing.assert_allclose(mesh.uv[:, 0], theta / np.pi, atol=1e-6)


def test_an_unreadable_texture_leaves_the_factor_with_a_warning(tmp_path, caplog) -> None:
    trimesh.Scene(curved_wall(checker(64, 8), 8, 2)).export(tmp_path / "wall.glb")
    data = bytearray((tmp_path / "wall.glb").read_bytes())
    at = data.find(b"IDAT")
    data[at + 8: at + 40] = bytes(32)  # corrupt the image's pixel data
    (tmp_path / "bad.glb").write_bytes(bytes(data))
    with caplog.at_level(logging.WARNING):
        mesh = load_source(tmp_path / "bad.glb").objects[0].levels[0]
    assert not mesh.textured
    np.testing.assert_array_equal(mesh.face_colours[0], (255, 255, 255))
    assert "texture cannot be read" in caplog.text


def test_a_mesh_refuses_half_a_texture_or_misfit_uvs() -> None:
    p, f = np.eye(3), np.array([[0, 1, 2]])
    with pytest.raises(ValueError, match="uv and texture together"):
        Mesh(p, f, uv=np.zeros((3, 2)))
    with pytest.raises(ValueError, match="uv must be"):
        Mesh(p, f, uv=np.zeros((2, 2)), texture=np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(ValueError, match="texture must be"):
        Mesh(p, f, uv=np.zeros((3, 2)), texture=np.zeros((8, 8), np.uint8))


@given(st.integers(1, 8192), st.integers(1, 8192), st.integers(1, 12))
def test_level_sides_halve_from_at_most_1024_and_stop_at_8(h: int, w: int, n: int) -> None:
    sides = level_sides((h, w, 3), n)
    assert len(sides) == n and all(s & (s - 1) == 0 for s in sides)  # powers of two
    assert COARSEST_SIDE <= sides[0] and sides[-1] <= FINEST_SIDE
    for coarse, fine in zip(sides, sides[1:]):
        assert coarse == max(COARSEST_SIDE, fine // 2)
    # the finest is the image's larger side to within a factor √2 (the nearest power of two), within the caps
    want = min(max(max(h, w), COARSEST_SIDE), FINEST_SIDE)
    assert want / 2 ** 0.5 - 1e-9 <= sides[-1] <= want * 2 ** 0.5 + 1e-9


def test_every_level_carries_uvs_and_its_own_texture_halving_per_level(wall_store) -> None:
    with SceneStore.open(wall_store) as store:
        idx = store.index
        origin = np.asarray(idx.meta["origin"], np.float64)
        first, count = int(idx.rep_first[0]), int(idx.rep_count[0])
        assert count >= 3, "the wall should decimate into several levels"
        sides = []
        for rep in range(first, first + count):
            g = decode_geometry(store.geometry(rep))
            assert g.uv is not None and g.texture is not None
            s = g.texture.shape[0]
            assert g.texture.shape == (s, s, 3)
            sides.append(s)
            # the transferred UVs follow the source's map: u along the arc, v up the wall
            p = g.positions.astype(np.float64) + origin
            theta = np.arctan2(p[:, 1], p[:, 0])
            on_arc = np.abs(np.hypot(p[:, 0], p[:, 1]) - RADIUS) < 0.05 * RADIUS
            assert np.abs(g.uv[on_arc, 0] - theta[on_arc] / np.pi).max() < 0.02
            assert np.abs(g.uv[:, 1] - p[:, 2] / HEIGHT).max() < 0.02
            # and the texture is still a red/green checker, with both colours
            flat = g.texture.reshape(-1, 3).astype(int)
            assert (np.abs(flat - RED).max(axis=1) < 40).mean() > 0.3
            assert (np.abs(flat - GREEN).max(axis=1) < 40).mean() > 0.3
        assert sides[-1] == FINEST_SIDE  # the source is 2048 px: the finest level gets the cap
        for coarse, fine in zip(sides, sides[1:]):
            assert coarse == max(COARSEST_SIDE, fine // 2)


def test_a_textured_representations_bytes_count_its_png(wall_store) -> None:
    """The store's byte column — what the byte gate, the cost model and the client's cache budget read — is
    the payload's length, texture included: more than the untextured payload by at least the PNG."""
    with SceneStore.open(wall_store) as store:
        idx = store.index
        for rep in range(int(idx.rep_first[0]), int(idx.rep_first[0] + idx.rep_count[0])):
            blob = store.geometry(rep)
            assert int(idx.rep_bytes[rep]) == len(blob)
            fields = msgpack.unpackb(blob)
            g = decode_geometry(blob)
            plain = encode_geometry(g.positions, g.indices, np.asarray(fields["lo"]),
                                    np.asarray(fields["lo"]) + np.asarray(fields["ext"]), reorder=False,
                                    colours=g.colours)
            png = encode_texture(g.texture)
            assert fields["tx"] == png
            assert int(idx.rep_bytes[rep]) >= len(plain) + len(png)


def test_the_store_records_each_levels_texels_and_an_older_store_reads_none(wall_store, tmp_path) -> None:
    """The index knows which representations carry a texture (the selection prefers drawing it) without
    decoding a payload: texels = the level's texture's width × height. A store built before the column
    opens as before and reads as untextured."""
    import sqlite3

    with SceneStore.open(wall_store) as store:
        idx = store.index
        reps = list(range(idx.n_representations))
        want = [0 if g.texture is None else g.texture.shape[0] * g.texture.shape[1]
                for g in map(decode_geometry, store.geometries(reps))]
        assert idx.rep_texels.dtype == np.int32
        np.testing.assert_array_equal(idx.rep_texels, want)
        assert (idx.rep_texels[idx.rep_first[0]: idx.rep_first[0] + idx.rep_count[0]] > 0).all()
    old = tmp_path / "old.db"
    old.write_bytes(wall_store.read_bytes())
    with sqlite3.connect(old) as conn:
        conn.execute("ALTER TABLE representations DROP COLUMN texels")
    with SceneStore.open(old) as store:
        assert store.index.n_representations == len(want)
        np.testing.assert_array_equal(store.index.rep_texels, np.zeros(len(want), np.int32))
        assert decode_geometry(store.geometry(0)).texture is not None  # its textures still travel
