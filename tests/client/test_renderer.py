"""Renderer on real EGL (llvmpipe): pixels where the mesh is, background elsewhere, exact counts, release."""

from __future__ import annotations

from pathlib import Path

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


def test_free_returns_arena_space(renderer: Renderer) -> None:
    big, small = _sphere(), _sphere(subdivisions=1)
    renderer.upload(1, big)
    assert (renderer.vertex_arena.used, renderer.index_arena.used) == (big.vertices, 3 * big.faces)
    renderer.upload(1, small)  # replacing frees the old blocks
    assert (renderer.vertex_arena.used, renderer.index_arena.used) == (small.vertices, 3 * small.faces)
    assert renderer.draw(np.array([1]), EYE, FORWARD, UP, 0.1, 100.0).triangles == small.faces
    renderer.free(1)
    renderer.free(1)  # unknown ids are ignored
    renderer.free(12345)
    assert 1 not in renderer.meshes and not renderer.meshes
    assert renderer.vertex_arena.used == renderer.index_arena.used == 0
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


def test_morph_blend_at_weight_one_is_exact(renderer: Renderer) -> None:
    """Every draw goes through the blend; at w = 1 a rep whose target differs from its positions is the fine level."""
    fine, coarse, vmap = _pyramid()
    renderer.upload(2, fine, object_id=3)
    for algorithm in range(3):
        a = np.array([algorithm])
        renderer.draw(np.array([2]), EYE, FORWARD, UP, 0.1, 100.0, algorithms=a)
        image_fine = renderer.read_image()
        renderer.set_morph_target(2, morph_targets(fine.positions, coarse.positions, vmap))
        renderer.draw(np.array([2]), EYE, FORWARD, UP, 0.1, 100.0, algorithms=a)
        np.testing.assert_array_equal(renderer.read_image(), image_fine)
        renderer.draw(np.array([2]), EYE, FORWARD, UP, 0.1, 100.0, weights=np.array([1.0]), algorithms=a)
        np.testing.assert_array_equal(renderer.read_image(), image_fine)
        renderer.upload(2, fine, object_id=3)


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
    renderer.upload(1, coarse, object_id=0)
    image_coarse = _image(renderer, 1)
    renderer.upload(2, fine, object_id=0)
    renderer.set_morph_target(2, fine.positions)  # a target equal to the positions: w = 0 is the fine level
    image_fine = _image(renderer, 2)
    np.testing.assert_array_equal(_image(renderer, 2, 0.0), image_fine)
    renderer.set_morph_target(2, targets)  # replacing the target
    np.testing.assert_array_equal(_image(renderer, 2, 0.0), image_coarse)
    renderer.free(2)
    assert not renderer.has_morph_target(2)
    # Uploading over a rep drops its target too (the new geometry has other vertices).
    renderer.upload(2, fine)
    renderer.set_morph_target(2, targets)
    renderer.upload(2, fine)
    assert not renderer.has_morph_target(2)
    stats = renderer.draw(np.array([2]), EYE, FORWARD, UP, 0.1, 100.0, weights=np.array([0.5]))
    assert stats.morphs == 0 and renderer.unmorphed == 1


# ----------------------------------------------------------------------------- batching, algorithms, measurement

from client.renderer import FrameTerms  # noqa: E402
from client.shading import smooth_normals, target_normals  # noqa: E402
from proto.messages import ALGORITHMS  # noqa: E402

_BG = np.round(np.array(BACKGROUND) * 255)


def _drawn(image: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels that are not the clear colour."""
    return np.abs(image.astype(int) - _BG).max(axis=2) > 0


def _grid(renderer: Renderer, first: int = 10, n: int = 9) -> np.ndarray:
    """n small spheres on a 3 × 3 grid that do not overlap on screen; returns their rep ids."""
    reps = np.arange(first, first + n)
    for i, rep in enumerate(reps.tolist()):
        renderer.upload(rep, _sphere(_grid_centre(i), subdivisions=1 + i % 3), object_id=i)
    return reps


def _grid_centre(i: int) -> tuple[float, float, float]:
    return ((i % 3 - 1) * 2.4, (i // 3 - 1) * 2.3, -3.0)


def test_batched_equals_drawn_one_by_one(renderer: Renderer) -> None:
    reps = _grid(renderer)
    algorithms = np.arange(reps.size) % 3
    levels = np.linspace(0, 4, reps.size)
    for false_colour in (False, True):
        renderer.false_colour = false_colour
        stats = renderer.draw(reps, EYE, FORWARD, UP, 0.1, 100.0, algorithms=algorithms, levels=levels)
        batched = renderer.read_image()
        assert stats.draws == reps.size
        composite = np.broadcast_to(_BG.astype(np.uint8), batched.shape).copy()
        coverage = np.zeros(batched.shape[:2], int)
        for i, rep in enumerate(reps.tolist()):
            renderer.draw(np.array([rep]), EYE, FORWARD, UP, 0.1, 100.0, algorithms=algorithms[i : i + 1],
                          levels=levels[i : i + 1])
            image = renderer.read_image()
            mask = _drawn(image)
            assert mask.sum() > 50
            composite[mask] = image[mask]
            coverage += mask
        assert coverage.max() == 1  # the spheres do not overlap on screen
        np.testing.assert_array_equal(batched, composite)
        # The order of the reps does not matter either (grouping by algorithm reorders them anyway).
        order = np.random.default_rng(3).permutation(reps.size)
        renderer.draw(reps[order], EYE, FORWARD, UP, 0.1, 100.0, algorithms=algorithms[order], levels=levels[order])
        np.testing.assert_array_equal(renderer.read_image(), batched)


def test_each_algorithm_draws_its_own_look(renderer: Renderer) -> None:
    renderer.upload(1, _sphere(subdivisions=1), object_id=4)  # coarse: flat shows its facets, lit smooths them
    images = []
    for algorithm in range(len(ALGORITHMS)):
        stats = renderer.draw(np.array([1]), EYE, FORWARD, UP, 0.1, 100.0, algorithms=np.array([algorithm]))
        assert stats.terms.draws == [int(algorithm == k) for k in range(3)]
        images.append(renderer.read_image().astype(int))
        assert _drawn(images[-1]).sum() > 500  # not blank
    masks = [_drawn(im) for im in images]
    assert (masks[0] == masks[1]).all() and (masks[0] == masks[2]).all()  # same shape, other shading
    for a in range(3):
        for b in range(a + 1, 3):
            assert np.abs(images[a] - images[b]).max(axis=2)[masks[0]].mean() > 3, (a, b)
    # The shading's second differences: lit (Gouraud) is smooth, flat jumps at the facets, the bricks add edges.
    def roughness(image: np.ndarray) -> float:
        m = masks[0]
        inner = m[1:-1, 1:-1] & m[2:, 1:-1] & m[:-2, 1:-1] & m[1:-1, 2:] & m[1:-1, :-2]
        lap = image[1:-1, 2:] + image[1:-1, :-2] + image[2:, 1:-1] + image[:-2, 1:-1] - 4 * image[1:-1, 1:-1]
        return float(np.abs(lap).sum(axis=2)[inner].mean())

    assert 2 * roughness(images[1]) < roughness(images[0]) and 2 * roughness(images[0]) < roughness(images[2])


def test_mixed_algorithms_count_terms_exactly(renderer: Renderer) -> None:
    a, b, c = _sphere((-2.5, 0, 0), 1), _sphere((0, 0, 0), 2), _sphere((2.5, 0, 0), 3)
    fine, coarse, vmap = _pyramid()
    renderer.upload(1, a)
    renderer.upload(2, b)
    renderer.upload(3, c)
    renderer.upload(4, fine)
    renderer.set_morph_target(4, morph_targets(fine.positions, coarse.positions, vmap))
    reps = np.array([1, 2, 3, 4, 99, 2])
    stats = renderer.draw(reps, EYE, FORWARD, UP, 0.1, 100.0, weights=np.array([1.0, 1.0, 0.3, 0.4, 1.0, 1.0]),
                          algorithms=np.array([2, 0, 2, 1, 0, 1]), levels=np.array([0.0, 1, 2, 3, 4, 5]))
    t = stats.terms
    assert isinstance(t, FrameTerms)
    assert t.draws == [1, 2, 2]
    assert t.triangles == [b.faces, fine.faces + b.faces, a.faces + c.faces]
    assert t.vertices == [b.vertices, fine.vertices + b.vertices, a.vertices + c.vertices]
    assert (stats.draws, stats.triangles, stats.vertices) == (5, sum(t.triangles), sum(t.vertices))
    assert stats.morphs == 1 and renderer.missing == 1 and renderer.unmorphed == 1  # rep 3 has no target
    assert stats.pixels == sum(t.pixels) and t.pixels[0] > 0 and t.pixels[2] > 0
    assert 0 < stats.cpu_time <= stats.time and stats.splats == 0
    with pytest.raises(ValueError):
        renderer.draw(reps, EYE, FORWARD, UP, 0.1, 100.0, algorithms=np.array([0, 1, 2, 3, 0, 0]))
    with pytest.raises(ValueError):
        renderer.draw(reps, EYE, FORWARD, UP, 0.1, 100.0, algorithms=np.array([0, 1]))
    with pytest.raises(ValueError):
        renderer.draw(reps, EYE, FORWARD, UP, 0.1, 100.0, algorithms=np.full(6, 0.5))
    with pytest.raises(ValueError):
        renderer.draw(reps, EYE, FORWARD, UP, 0.1, 100.0, levels=np.zeros(5))
    with pytest.raises(ValueError):
        renderer.draw(reps, EYE, FORWARD, UP, 0.1, 100.0, levels=np.full(6, np.nan))
    assert renderer.missing == 1  # refused frames count nothing


def test_pixels_query_counts_covered_pixels(renderer: Renderer) -> None:
    # A square facing the camera: no overdraw, so samples passed = covered pixels.
    square = Geometry(np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float32),
                      np.array([[0, 1, 2], [0, 2, 3]], np.uint32))
    renderer.upload(1, square, object_id=2)
    for algorithm in range(3):
        stats = renderer.draw(np.array([1]), EYE, FORWARD, UP, 0.1, 100.0, algorithms=np.array([algorithm]))
        covered = _drawn(renderer.read_image()).sum()
        assert covered > 500 and abs(stats.pixels - covered) <= 0.01 * covered
        assert stats.terms.pixels[algorithm] == stats.pixels
    # A sphere, without back-face culling: its back faces may pass first, at most doubling the count.
    renderer.upload(2, _sphere(), object_id=2)
    stats = renderer.draw(np.array([2]), EYE, FORWARD, UP, 0.1, 100.0)
    covered = _drawn(renderer.read_image()).sum()
    assert 0.99 * covered <= stats.pixels <= 2 * covered
    # Two objects side by side: the per-algorithm terms split the pixels.
    renderer.draw(np.array([1]), EYE, FORWARD, UP, 0.1, 100.0)
    square_pixels = _drawn(renderer.read_image()).sum()
    renderer.upload(3, _sphere((2.5, 0, 0)), object_id=3)
    stats = renderer.draw(np.array([1, 3]), EYE, FORWARD, UP, 0.1, 100.0, algorithms=np.array([0, 2]))
    assert stats.terms.pixels[1] == 0 and stats.terms.pixels[2] > 0
    assert abs(stats.terms.pixels[0] - square_pixels) <= 0.01 * square_pixels
    assert renderer.draw(np.zeros(0, int), EYE, FORWARD, UP, 0.1, 100.0).pixels == 0


def test_false_colour_shows_levels_and_marks_morphs(renderer: Renderer) -> None:
    fine, coarse, vmap = _pyramid()
    renderer.upload(1, fine, object_id=3)
    renderer.set_morph_target(1, morph_targets(fine.positions, coarse.positions, vmap))
    normal = _image(renderer, 1)
    renderer.false_colour = True
    by_level = []
    for level in (0.0, 2.5, 5.0):
        renderer.draw(np.array([1]), EYE, FORWARD, UP, 0.1, 100.0, levels=np.array([level]))
        by_level.append(renderer.read_image().astype(int))
    mask = _drawn(normal)
    assert (_drawn(by_level[0]) == mask).all()  # the same shape
    for a, b in [(0, 1), (1, 2), (0, 2)]:
        assert np.abs(by_level[a] - by_level[b]).max(axis=2)[mask].mean() > 30
    assert np.abs(by_level[0] - normal).max(axis=2)[mask].mean() > 30
    coarse_end, fine_end = by_level[0][mask].mean(axis=0), by_level[2][mask].mean(axis=0)
    assert coarse_end[2] > coarse_end[0] and fine_end[0] > fine_end[2]  # blue for coarse, red for fine

    def magenta(image: np.ndarray) -> np.ndarray:
        r, g, b = image[..., 0], image[..., 1], image[..., 2]
        return (r > 40) & (b > 40) & (g < 0.1 * np.minimum(r, b))

    assert not magenta(by_level[1]).any()
    renderer.draw(np.array([1]), EYE, FORWARD, UP, 0.1, 100.0, weights=np.array([0.5]), levels=np.array([2.5]))
    morphing = renderer.read_image().astype(int)
    stripes = magenta(morphing)
    assert 0.3 < stripes[_drawn(morphing)].mean() < 0.7  # about half of it, in stripes
    # Lighting applies to the stripes too: the faces of the pyramid get different magentas.
    assert np.unique(morphing[stripes][:, 0]).size >= 2
    renderer.false_colour = False
    renderer.draw(np.array([1]), EYE, FORWARD, UP, 0.1, 100.0, weights=np.array([0.5]), levels=np.array([2.5]))
    assert not magenta(renderer.read_image().astype(int)).any()


def test_lit_morph_ends_match_their_levels(renderer: Renderer) -> None:
    """The lit algorithm morphs its normals too: w = 0 shades like the coarser level (normals rounded to bytes)."""
    from server.scene.lod import build_chain

    mesh = trimesh.creation.icosphere(3)
    chain = build_chain(mesh.vertices, mesh.faces, max_levels=3)
    k = len(chain) - 1
    (cp, cf), (fp, ff) = chain[k - 1], chain[k]
    coarse = Geometry(cp.astype(np.float32), cf.astype(np.uint32))
    fine = Geometry(fp.astype(np.float32), ff.astype(np.uint32))
    renderer.upload(1, coarse, object_id=9)
    renderer.upload(2, fine, object_id=9)
    targets = morph_targets(fine.positions, coarse.positions, chain.morph[k])
    renderer.set_morph_target(2, targets)
    lit = np.array([1])
    renderer.draw(np.array([1]), EYE, FORWARD, UP, 0.1, 100.0, algorithms=lit)
    image_coarse = renderer.read_image().astype(int)
    renderer.draw(np.array([2]), EYE, FORWARD, UP, 0.1, 100.0, weights=np.array([0.0]), algorithms=lit)
    at_zero = np.abs(renderer.read_image().astype(int) - image_coarse).max(axis=2)
    assert np.percentile(at_zero, 99) <= 3 and (at_zero > 6).sum() <= 10
    # The target normals are the coarse level's vertex normals, gathered through the map.
    expected = smooth_normals(coarse.positions, coarse.indices)[chain.morph[k]]
    got = target_normals(targets, fine.indices)
    assert np.einsum("ij,ij->i", expected, got).min() > 0.999
    # Merged by the morph map (no sort), the same normals.
    by_map = target_normals(targets, fine.indices, merge=chain.morph[k])
    assert np.einsum("ij,ij->i", expected, by_map).min() > 0.999
    with pytest.raises(ValueError):
        target_normals(targets, fine.indices, merge=chain.morph[k][:-1])


def test_smooth_normals_agree_with_the_neighbours_and_refuse_bad_indices() -> None:
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 0]], np.float32)
    fan = np.array([[4, 0, 1], [4, 1, 2], [4, 2, 3], [4, 3, 0]])
    normals = smooth_normals(square, fan)
    np.testing.assert_allclose(normals, np.tile([0.0, 0.0, 1.0], (5, 1)), atol=1e-6)
    # A face wound the other way is flipped to agree with its neighbours, not cancelled.
    np.testing.assert_allclose(smooth_normals(square, fan[:, [0, 2, 1]]), -normals, atol=1e-6)  # all reversed
    np.testing.assert_allclose(smooth_normals(square, np.vstack([fan[:3], fan[3, [0, 2, 1]]])), normals, atol=1e-6)
    assert smooth_normals(square, np.zeros((0, 3), int))[:, 2].min() == 1.0  # no faces: +z
    for bad in ([[0, 1, 5]], [[0, -1, 2]]):
        with pytest.raises(ValueError, match="indices"):
            smooth_normals(square, np.array(bad))


def test_layers_draw_inside_the_fence(renderer: Renderer) -> None:
    renderer.upload(1, _sphere(), object_id=1)

    class Layer:
        def __init__(self, splats: int, pause: float = 0.0) -> None:
            self.splats, self.pause, self.calls = splats, pause, []

        def render(self, view_projection, eye, viewport, fov_y):
            import time

            self.calls.append((np.array(view_projection), np.array(eye), viewport, fov_y,
                               renderer.ctx.fbo is renderer.fbo))
            renderer.fbo.clear(1.0, 0.0, 0.0, 1.0, viewport=(0, 0, 4, 4))  # draws into the frame's framebuffer
            time.sleep(self.pause)
            return self.splats

    a, b = Layer(120, pause=0.05), Layer(3)
    stats = renderer.draw(np.array([1]), EYE, FORWARD, UP, 0.1, 100.0, layers=[a, b])
    assert stats.splats == 123 and stats.time >= 0.05 and stats.cpu_time >= 0.05
    assert len(a.calls) == len(b.calls) == 1
    vp, eye, viewport, fov_y, bound = a.calls[0]
    assert vp.shape == (4, 4) and vp.dtype == np.float32 and bound
    assert viewport == (W, H) and fov_y == 60.0
    np.testing.assert_array_equal(eye, EYE)
    # Row-major, camera-relative: the sphere's centre (world origin) projects to the middle of the screen,
    # a point above it to the upper half.
    clip = vp @ np.array([*(np.zeros(3) - EYE), 1.0])
    np.testing.assert_allclose(clip[:2] / clip[3], 0.0, atol=1e-6)
    clip = vp @ np.array([*(np.array([0.0, 1.0, 0.0]) - EYE), 1.0])
    assert clip[1] / clip[3] > 0.2
    image = renderer.read_image()
    np.testing.assert_array_equal(image[H - 4 :, :4], np.broadcast_to([255, 0, 0], (4, 4, 3)))  # after the clear
    assert np.abs(image[H // 2, W // 2] - _BG).max() > 20  # and the meshes are still there
    assert renderer.draw(np.array([1]), EYE, FORWARD, UP, 0.1, 100.0).splats == 0


def test_gpu_time_rule() -> None:
    rule = Renderer.gpu_time_plausible
    assert rule(0.008, 0.010, 0.009)
    assert not rule(0.0, 0.010, 0.0)  # zero
    assert not rule(0.030, 0.010, 0.009)  # longer than the fence
    assert not rule(3e-6, 0.010, 0.009)  # a few µs while the fence waited 9 ms on the GPU
    assert rule(0.0005, 0.010, 0.0002)  # short GPU work after a long submission
    with Renderer(32, 32) as r:
        r.upload(1, _sphere())
        stats = r.draw(np.array([1]), EYE, FORWARD, UP, 0.1, 100.0)
        assert stats.gpu_time is None or 0 < stats.gpu_time <= stats.time * 1.1 + 1e-4


def test_rep_ids_outside_the_dense_table(renderer: Renderer) -> None:
    a, b = _sphere((-2, 0, 0), 1), _sphere((2, 0, 0), 2)
    renderer.upload(-7, a)
    renderer.upload((1 << 31) - 1, b)
    renderer.upload(3, a)
    stats = renderer.draw(np.array([-7, (1 << 31) - 1, 3, -8, 1 << 30]), EYE, FORWARD, UP, 0.1, 100.0)
    assert (stats.draws, stats.triangles) == (3, 2 * a.faces + b.faces) and renderer.missing == 2
    renderer.free(-7)
    assert renderer.draw(np.array([-7, (1 << 31) - 1]), EYE, FORWARD, UP, 0.1, 100.0).draws == 1
    assert renderer.draw([], EYE, FORWARD, UP, 0.1, 100.0).draws == 0


def test_empty_geometry_is_a_draw_of_nothing(renderer: Renderer) -> None:
    renderer.upload(1, Geometry(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint32)))
    renderer.upload(2, Geometry(np.zeros((3, 3), np.float32), np.zeros((0, 3), np.uint32)))
    renderer.set_morph_target(1, np.zeros((0, 3), np.float32))
    stats = renderer.draw(np.array([1, 2]), EYE, FORWARD, UP, 0.1, 100.0, weights=np.array([0.5, 1.0]))
    assert (stats.draws, stats.triangles, stats.vertices, stats.pixels) == (2, 0, 3, 0)
    with pytest.raises(ValueError):
        renderer.upload(3, Geometry(np.zeros((3, 3), np.float32), np.array([[0, 1, 3]], np.uint32)))
    assert 3 not in renderer.meshes


def test_arena_growth_and_compaction_keep_images() -> None:
    """Many uploads through tiny arenas (grown many times), frees (compacted), morphs: the frame stays the same."""
    fine, coarse, vmap = _pyramid()
    with Renderer(W, H) as reference:
        reps = _grid(reference)
        algorithms = np.arange(reps.size) % 3
        reference.upload(50, fine, object_id=7)
        reference.set_morph_target(50, morph_targets(fine.positions, coarse.positions, vmap))
        drawn = np.append(reps, 50)
        weights = np.append(np.ones(reps.size), 0.25)
        reference.draw(drawn, EYE, FORWARD, UP, 0.1, 100.0, weights=weights, algorithms=np.append(algorithms, 1))
        expected = reference.read_image()
    with Renderer(W, H, vertex_capacity=8, index_capacity=16) as r:
        r.vertex_arena.compact_min = r.index_arena.compact_min = 1
        rng = np.random.default_rng(7)
        junk = []
        for i in range(200):  # interleave junk uploads and frees with the real ones
            rep = 1000 + i
            r.upload(rep, _sphere((50, 50, 50), subdivisions=int(rng.integers(0, 3))))
            junk.append(rep)
            if i % 20 == 5:
                _grid(r)
                r.upload(50, fine, object_id=7)
                r.set_morph_target(50, morph_targets(fine.positions, coarse.positions, vmap))
            if rng.random() < 0.6:
                r.free(junk.pop(int(rng.integers(len(junk)))))
        for rep in junk:
            r.free(rep)
        assert r.vertex_arena.grows >= 3 and r.index_arena.grows >= 3
        assert r.vertex_arena.compactions >= 1 and r.index_arena.compactions >= 1
        stats = r.draw(drawn, EYE, FORWARD, UP, 0.1, 100.0, weights=weights, algorithms=np.append(algorithms, 1))
        assert stats.morphs == 1 and stats.draws == drawn.size
        np.testing.assert_array_equal(r.read_image(), expected)
        # Compaction of what is left moves the live blocks again; the frame does not change.
        r.free(reps[0])
        r.vertex_arena.compact()
        r.index_arena.compact()
        assert r.vertex_arena.holes == r.index_arena.holes == 0
        r.upload(reps[0], _sphere(_grid_centre(0), subdivisions=1), object_id=0)
        r.draw(drawn, EYE, FORWARD, UP, 0.1, 100.0, weights=weights, algorithms=np.append(algorithms, 1))
        np.testing.assert_array_equal(r.read_image(), expected)


def test_many_small_reps_in_one_frame() -> None:
    """Thousands of representations: one multi-draw per algorithm, exact counts, the Python side in milliseconds."""
    n = 3000
    ico = trimesh.creation.icosphere(0)
    rng = np.random.default_rng(2)
    centres = rng.uniform(-60, 60, (n, 3))
    with Renderer(W, H) as r:
        for i in range(n):
            r.upload(i, Geometry((ico.vertices * 0.5 + centres[i]).astype(np.float32), ico.faces.astype(np.uint32)))
        eye = np.array([0.0, 0.0, 120.0])
        reps = np.arange(n)
        algorithms = rng.integers(0, 3, n)
        r.cull = False  # every rep submitted: the counts are exact
        stats = r.draw(reps, eye, FORWARD, UP, 0.1, 500.0, weights=np.ones(n), algorithms=algorithms,
                       levels=np.zeros(n))
        assert (stats.draws, stats.triangles, stats.vertices) == (n, 20 * n, 12 * n)
        assert stats.terms.draws == np.bincount(algorithms, minlength=3).tolist()
        assert stats.pixels > 0 and _drawn(r.read_image()).sum() > 0


def test_external_context_is_kept() -> None:
    import moderngl

    ctx = moderngl.create_standalone_context(require=330, backend="egl")
    try:
        with Renderer(W, H, ctx=ctx) as r:
            assert r.ctx is ctx
            r.upload(1, _sphere())
            assert r.draw(np.array([1]), EYE, FORWARD, UP, 0.1, 100.0).draws == 1
        r.release()  # twice is harmless
        ctx.buffer(reserve=16).release()  # the context is still alive
    finally:
        ctx.release()


def test_frustum_culling_leaves_out_unseen_reps_without_changing_the_image() -> None:
    """Reps outside the view are not submitted (nor counted), and the picture is the same either way."""
    n = 400
    ico = trimesh.creation.icosphere(1)
    rng = np.random.default_rng(5)
    centres = rng.uniform(-80, 80, (n, 3))
    with Renderer(W, H) as r:
        for i in range(n):
            r.upload(i, Geometry((ico.vertices * 0.8 + centres[i]).astype(np.float32), ico.faces.astype(np.uint32)))
        eye = np.array([0.0, 0.0, 0.0])
        reps = np.arange(n)
        r.cull = False
        everything = r.draw(reps, eye, FORWARD, UP, 0.1, 500.0)
        expected = r.read_image()
        r.cull = True
        culled = r.draw(reps, eye, FORWARD, UP, 0.1, 500.0)
        np.testing.assert_array_equal(r.read_image(), expected)
        assert everything.culled == 0 and everything.draws == n
        # Looking along one axis from the middle of a cube of spheres, most of them are out of view.
        assert culled.culled > n // 2 and culled.draws == n - culled.culled
        assert culled.triangles == 80 * culled.draws and culled.pixels == everything.pixels
        # The governor's look ahead sees what the draw will: the same reps in view, the same vertices.
        seen, vertices = r.in_view(reps, eye, FORWARD, UP, 0.1, 500.0)
        assert int(seen.sum()) == culled.draws and int(vertices[seen].sum()) == culled.vertices
        assert culled.seen.tolist() == seen.tolist()


def test_culling_far_from_the_origin_keeps_every_rep_that_shows() -> None:
    """The sphere table is float32: 60 km out (St. Helens' extent), spheres grazing the frustum's edges
    still count as seen — the image with culling is the image without it."""
    ico = trimesh.creation.icosphere(1)
    base = np.array([60_000.0, 250.0, -60_000.0])
    rng = np.random.default_rng(11)
    # Spheres scattered across the view and just past its edges, 20–60 m ahead (looking along −z).
    offsets = np.column_stack([rng.uniform(-45, 45, 300), rng.uniform(-28, 28, 300), rng.uniform(-60, -20, 300)])
    with Renderer(W, H) as r:
        for i, off in enumerate(offsets):
            r.upload(i, Geometry((ico.vertices * 0.5 + base + off).astype(np.float32), ico.faces.astype(np.uint32)))
        reps = np.arange(len(offsets))
        r.cull = False
        everything = r.draw(reps, base, np.array([0.0, 0.0, -1.0]), np.array([0.0, 1.0, 0.0]), 0.1, 500.0)
        expected = r.read_image()
        r.cull = True
        culled = r.draw(reps, base, np.array([0.0, 0.0, -1.0]), np.array([0.0, 1.0, 0.0]), 0.1, 500.0)
        np.testing.assert_array_equal(r.read_image(), expected)
        assert 0 < culled.culled < len(offsets) and culled.pixels == everything.pixels
