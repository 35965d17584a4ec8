"""Renderer on real EGL (llvmpipe): pixels where the mesh is, background elsewhere, exact counts, release."""

from __future__ import annotations

from pathlib import Path

import moderngl
import numpy as np
import pytest
import trimesh

from client.renderer import BACKGROUND, Renderer
from proto.geometry import Geometry, decode_geometry, encode_geometry

W, H = 160, 120
EYE, FORWARD, UP = np.array([0.0, 0.0, 5.0]), np.array([0.0, 0.0, -1.0]), np.array([0.0, 1.0, 0.0])


def _sphere(center: tuple[float, float, float] = (0, 0, 0), subdivisions: int = 2) -> Geometry:
    mesh = trimesh.creation.icosphere(subdivisions)
    return decode_geometry(encode_geometry(mesh.vertices + np.asarray(center), mesh.faces))


@pytest.fixture
def renderer() -> Renderer:
    with Renderer(W, H, fov_y=60.0) as r:
        yield r


def test_sphere_drawn_where_it_is(renderer: Renderer, tmp_path: Path) -> None:
    g = _sphere()
    renderer.upload(1, g, object_id=5)
    stats = renderer.draw(np.array([1]), EYE, FORWARD, UP, 0.1, 100.0)
    assert (stats.triangles, stats.vertices, stats.draws) == (g.faces, g.vertices, 1)
    assert 0 < stats.time < 1.0
    image = renderer.read_image()
    assert image.shape == (H, W, 3) and image.dtype == np.uint8
    background = np.round(np.array(BACKGROUND) * 255)
    # A unit sphere 5 m away at 60° fov covers ~ ±23 px around the centre of a 120 px tall image.
    assert np.abs(image[H // 2, W // 2] - background).max() > 20
    assert np.abs(image[H // 2 - 10 : H // 2 + 10, W // 2 - 10 : W // 2 + 10] - background).max(axis=2).min() > 20
    for y, x in [(2, 2), (2, W - 3), (H - 3, 2), (H - 3, W - 3), (H // 2, 10), (10, W // 2)]:
        np.testing.assert_allclose(image[y, x], background, atol=1)
    renderer.save_png(tmp_path / "frame.png")
    assert (tmp_path / "frame.png").stat().st_size > 100


def test_image_rows_are_top_down(renderer: Renderer) -> None:
    renderer.upload(1, _sphere(center=(0, 1.6, 0), subdivisions=1))
    renderer.draw(np.array([1]), EYE, FORWARD, UP, 0.1, 100.0)
    drawn = np.abs(renderer.read_image().astype(int) - np.round(np.array(BACKGROUND) * 255)).max(axis=2) > 20
    rows = np.nonzero(drawn.any(axis=1))[0]
    assert rows.size and rows.mean() < H / 2  # above the centre in world → upper half of the image


def test_depth_test_nearer_object_wins(renderer: Renderer) -> None:
    renderer.upload(1, _sphere((0, 0, 0)), object_id=1)
    renderer.upload(2, _sphere((0, 0, 2)), object_id=2)  # nearer
    renderer.draw(np.array([2]), EYE, FORWARD, UP, 0.1, 100.0)
    near_only = renderer.read_image()[H // 2, W // 2].copy()
    renderer.draw(np.array([2, 1]), EYE, FORWARD, UP, 0.1, 100.0)
    np.testing.assert_array_equal(renderer.read_image()[H // 2, W // 2], near_only)


def test_stats_count_exactly_and_skip_missing(renderer: Renderer) -> None:
    a, b = _sphere(subdivisions=1), _sphere((2, 0, 0), subdivisions=3)
    renderer.upload(1, a, object_id=1)
    renderer.upload(2, b, object_id=1)
    stats = renderer.draw(np.array([1, 2, 77]), EYE, FORWARD, UP, 0.1, 100.0)
    assert (stats.triangles, stats.vertices, stats.draws) == (a.faces + b.faces, a.vertices + b.vertices, 2)
    assert renderer.missing == 1
    empty = renderer.draw(np.zeros(0, np.int64), EYE, FORWARD, UP, 0.1, 100.0)
    assert (empty.triangles, empty.vertices, empty.draws) == (0, 0, 0) and empty.time > 0


def test_free_releases_gl_objects(renderer: Renderer) -> None:
    renderer.upload(1, _sphere())
    mesh = renderer.meshes[1]
    renderer.upload(1, _sphere(subdivisions=1))  # replacing releases the old buffers
    assert isinstance(mesh.vbo.mglo, moderngl.mgl.InvalidObject)
    mesh = renderer.meshes[1]
    renderer.free(1)
    renderer.free(1)  # unknown ids are ignored
    assert 1 not in renderer.meshes
    for obj in (mesh.vao, mesh.vbo, mesh.ibo):
        assert isinstance(obj.mglo, moderngl.mgl.InvalidObject)
    assert renderer.draw(np.array([1]), EYE, FORWARD, UP, 0.1, 100.0).draws == 0


def test_missing_egl_backend_gives_clear_error() -> None:
    from client.renderer import RendererError

    with pytest.raises(RendererError, match="libegl-mesa0"):
        Renderer(16, 16, backend="no-such-backend")
