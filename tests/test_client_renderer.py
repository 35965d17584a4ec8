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


# ----------------------------------------------------------------------------- geomorphing

from client.renderer import FrameStats, morph_targets  # noqa: E402


def _pyramid() -> tuple[Geometry, Geometry, np.ndarray]:
    """Two levels by hand: a square pyramid (apex toward the camera) and the square it collapses to.

    The fine level has the four corners and the apex (vertex 4); the map sends the
    apex to corner 0, so at w = 0 two fine triangles degenerate and the other two
    are exactly the coarse square's.
    """
    corners = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float32)
    fine = Geometry(np.vstack([corners, [[0.2, 0.1, 0.8]]]).astype(np.float32),
                    np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]], np.uint32))
    coarse = Geometry(corners, np.array([[0, 1, 2], [0, 2, 3]], np.uint32))
    return fine, coarse, np.array([0, 1, 2, 3, 0])


def _image(renderer: Renderer, rep: int, weight: float | None = None) -> np.ndarray:
    weights = None if weight is None else np.array([weight])
    renderer.draw(np.array([rep]), EYE, FORWARD, UP, 0.1, 100.0, weights=weights)
    return renderer.read_image().astype(int)


def test_morph_targets_gathers_and_checks() -> None:
    fine, coarse, vmap = _pyramid()
    t = morph_targets(fine.positions, coarse.positions, vmap)
    assert t.dtype == np.float32 and t.shape == (5, 3)
    np.testing.assert_array_equal(t, coarse.positions[[0, 1, 2, 3, 0]])
    assert Renderer.morph_targets is morph_targets
    with pytest.raises(ValueError):
        morph_targets(fine.positions, coarse.positions, vmap[:4])
    with pytest.raises(ValueError):
        morph_targets(fine.positions, coarse.positions, np.array([0, 1, 2, 3, 4]))  # 4 is not a coarse vertex


def test_morph_ends_reproduce_their_levels_and_midway_differs(renderer: Renderer) -> None:
    fine, coarse, vmap = _pyramid()
    renderer.upload(1, coarse, object_id=3)
    renderer.upload(2, fine, object_id=3)
    renderer.upload(3, fine, object_id=3)
    renderer.set_morph_target(3, morph_targets(fine.positions, coarse.positions, vmap))
    assert renderer.has_morph_target(3) and not renderer.has_morph_target(2) and not renderer.has_morph_target(99)
    image_coarse, image_fine = _image(renderer, 1), _image(renderer, 2)
    assert np.abs(image_fine - image_coarse).max() > 20  # the pop a switch would show
    # Through the morph program: a weight just under 1 is the fine level, 0 the coarse one.
    renderer.draw(np.array([3]), EYE, FORWARD, UP, 0.1, 100.0, weights=np.array([1.0]))
    np.testing.assert_array_equal(renderer.read_image(), image_fine)
    np.testing.assert_array_equal(_image(renderer, 3, 1.0 - 1e-7), image_fine)
    np.testing.assert_array_equal(_image(renderer, 3, 0.0), image_coarse)
    np.testing.assert_array_equal(_image(renderer, 3, -0.5), image_coarse)  # clamped to 0
    half = _image(renderer, 3, 0.5)
    assert np.abs(half - image_fine).max() > 10 and np.abs(half - image_coarse).max() > 10
    assert renderer.unmorphed == 0


def test_morph_program_at_weight_one_is_exact(renderer: Renderer) -> None:
    """The morph shader itself at w = 1 (not the static path draw() takes for w ≥ 1) draws the fine level."""
    fine, coarse, vmap = _pyramid()
    renderer.upload(2, fine, object_id=3)
    image_fine = _image(renderer, 2)
    renderer.set_morph_target(2, morph_targets(fine.positions, coarse.positions, vmap))
    renderer.draw(np.array([2]), EYE, FORWARD, UP, 0.1, 100.0, weights=np.array([0.5]))  # sets the morph uniforms
    renderer._u_weight.value = 1.0
    renderer.fbo.clear(*BACKGROUND, 1.0, depth=1.0)
    renderer.meshes[2].morph.vao.render(moderngl.TRIANGLES)
    np.testing.assert_array_equal(renderer.read_image(), image_fine)


def test_morph_of_a_decimated_sphere_ends_on_its_coarser_level(renderer: Renderer) -> None:
    from server.scene.lod import build_chain, morph_faces_match

    mesh = trimesh.creation.icosphere(3)
    chain = build_chain(mesh.vertices, mesh.faces, max_levels=3)
    k = len(chain) - 1
    assert k >= 1 and morph_faces_match(chain, k)
    (cp, cf), (fp, ff) = chain[k - 1], chain[k]
    coarse = Geometry(cp.astype(np.float32), cf.astype(np.uint32))
    fine = Geometry(fp.astype(np.float32), ff.astype(np.uint32))
    renderer.upload(1, coarse, object_id=9)
    renderer.upload(2, fine, object_id=9)
    renderer.set_morph_target(2, morph_targets(fine.positions, coarse.positions, chain.morph[k]))
    image_coarse, image_fine = _image(renderer, 1), _image(renderer, 2)
    # Same triangles at w = 0, possibly with their corners in another order: a few pixels may round differently.
    at_zero = np.abs(_image(renderer, 2, 0.0) - image_coarse).max(axis=2)
    assert (at_zero > 2).sum() <= 5
    half = _image(renderer, 2, 0.5)
    assert (np.abs(half - image_fine).max(axis=2) > 2).sum() > 20
    assert (np.abs(half - image_coarse).max(axis=2) > 2).sum() > 20


def test_morph_stats_order_and_unmorphed(renderer: Renderer) -> None:
    fine, coarse, vmap = _pyramid()
    a = _sphere((2, 0, 0), subdivisions=1)
    renderer.upload(1, a, object_id=1)
    renderer.upload(2, fine, object_id=3)
    renderer.set_morph_target(2, morph_targets(fine.positions, coarse.positions, vmap))
    stats = renderer.draw(np.array([1, 2, 77]), EYE, FORWARD, UP, 0.1, 100.0, weights=np.array([1.0, 0.3, 0.5]))
    # A morphing rep costs its own (finer) level; the missing one costs nothing.
    assert (stats.triangles, stats.vertices, stats.draws, stats.morphs) == (
        a.faces + fine.faces, a.vertices + fine.vertices, 2, 1)
    assert renderer.missing == 1 and renderer.unmorphed == 0
    # weight < 1 without a target: drawn at full detail, counted.
    image_sphere = _image(renderer, 1)
    stats = renderer.draw(np.array([1]), EYE, FORWARD, UP, 0.1, 100.0, weights=np.array([0.25]))
    np.testing.assert_array_equal(renderer.read_image(), image_sphere)
    assert (stats.draws, stats.morphs, stats.triangles) == (1, 0, a.faces) and renderer.unmorphed == 1
    renderer.draw(np.array([1, 1]), EYE, FORWARD, UP, 0.1, 100.0, weights=[0.0, 0.9])
    assert renderer.unmorphed == 3
    # No weights: nothing morphs, nothing counted; FrameStats' callers that do not know morphs still work.
    stats = renderer.draw(np.array([1, 2]), EYE, FORWARD, UP, 0.1, 100.0)
    assert stats.morphs == 0 and renderer.unmorphed == 3
    assert FrameStats(time=0.0, triangles=0, vertices=0, draws=0).morphs == 0
    with pytest.raises(ValueError):
        renderer.draw(np.array([1, 2]), EYE, FORWARD, UP, 0.1, 100.0, weights=np.array([0.5]))
    with pytest.raises(ValueError):
        renderer.draw(np.array([1]), EYE, FORWARD, UP, 0.1, 100.0, weights=np.array([np.nan]))


def test_morph_target_shape_checked_and_freed_with_the_rep(renderer: Renderer) -> None:
    fine, coarse, vmap = _pyramid()
    renderer.upload(2, fine)
    for bad in (np.zeros((4, 3), np.float32), np.zeros((5, 2), np.float32), np.zeros(15, np.float32)):
        with pytest.raises(ValueError):
            renderer.set_morph_target(2, bad)
    with pytest.raises(ValueError):
        renderer.set_morph_target(2, np.full((5, 3), np.inf, np.float32))
    with pytest.raises(KeyError):
        renderer.set_morph_target(99, np.zeros((5, 3), np.float32))
    assert not renderer.has_morph_target(2)
    targets = morph_targets(fine.positions, coarse.positions, vmap)
    renderer.set_morph_target(2, targets)
    first = renderer.meshes[2].morph
    renderer.set_morph_target(2, targets)  # replacing releases the old target
    for obj in (first.vao, first.tbo):
        assert isinstance(obj.mglo, moderngl.mgl.InvalidObject)
    morph = renderer.meshes[2].morph
    renderer.free(2)
    assert not renderer.has_morph_target(2)
    for obj in (morph.vao, morph.tbo):
        assert isinstance(obj.mglo, moderngl.mgl.InvalidObject)
    # Uploading over a rep drops its target too (the new geometry has other vertices).
    renderer.upload(2, fine)
    renderer.set_morph_target(2, targets)
    morph = renderer.meshes[2].morph
    renderer.upload(2, fine)
    assert not renderer.has_morph_target(2) and isinstance(morph.tbo.mglo, moderngl.mgl.InvalidObject)
    stats = renderer.draw(np.array([2]), EYE, FORWARD, UP, 0.1, 100.0, weights=np.array([0.5]))
    assert stats.morphs == 0 and renderer.unmorphed == 1
