"""Tree splats on real EGL (llvmpipe): where they land, exact counts at every x, partial groups, residency."""

from __future__ import annotations

import math

import moderngl
import numpy as np
import pytest

from client.splats import SplatLayer
from proto.camera import projection_matrix, view_matrix
from proto.points import Instances, Points, decode_instances, decode_points, encode_instances, encode_points
from server.scene.points import point_model
from server.scene.vegetation import broadleaf, conifer

W, H, FOV = 160, 120, 60.0
NEAR, FAR = 0.5, 2000.0
BACKGROUND = np.array([0.62, 0.74, 0.86])
BG8 = np.round(BACKGROUND * 255)
# Far from the origin on purpose: the layer draws camera-relative.
ORIGIN = np.array([5000.0, -3000.0, 120.0])


@pytest.fixture(scope="module")
def models() -> dict[int, Points]:
    """Two tree models through the wire format, with point counts that make rounding matter."""
    return {
        0: decode_points(encode_points(point_model(conifer(3), n_points=1000, seed=1))),
        1: decode_points(encode_points(point_model(broadleaf(4), n_points=701, seed=2))),
    }


@pytest.fixture(scope="module")
def gl():
    ctx = moderngl.create_standalone_context(backend="egl", require=430)
    color = ctx.renderbuffer((W, H))
    depth = ctx.depth_renderbuffer((W, H))
    fbo = ctx.framebuffer(color_attachments=[color], depth_attachment=depth)
    yield ctx, fbo
    fbo.release()
    color.release()
    depth.release()
    ctx.release()


@pytest.fixture
def layer(gl, models) -> SplatLayer:
    s = SplatLayer(gl[0])
    for m, p in models.items():
        s.add_model(m, p)
    yield s
    s.release()


def _group(ids, xy, z: float = 0.0, yaw_seed: int = 0, scale: float = 1.0) -> Instances:
    """Trees with model ``ids`` at ground points ``xy`` (k, 2) around ORIGIN, through the wire format."""
    ids = np.asarray(ids)
    k = ids.size
    yaw = np.random.default_rng(yaw_seed).uniform(0, 2 * np.pi, k)
    m = np.zeros((k, 4, 4))
    c, s = np.cos(yaw) * scale, np.sin(yaw) * scale
    m[:, 0, 0], m[:, 0, 1], m[:, 1, 0], m[:, 1, 1], m[:, 2, 2] = c, -s, s, c, scale
    m[:, :3, 3] = ORIGIN + np.column_stack([np.asarray(xy, float), np.full(k, z)])
    m[:, 3, 3] = 1
    return decode_instances(encode_instances(ids, m))


def _frame(layer: SplatLayer, fbo, eye, forward, up=(0.0, 0.0, 1.0), clear_depth: float = 1.0):
    """Render the layer's current groups; returns (splats drawn, image (H, W, 3) top-down, vp).

    The count ``render`` returns is checked against the GPU's own (GL_PRIMITIVES_GENERATED).
    """
    eye = np.asarray(eye, float)
    vp = projection_matrix(FOV, W / H, NEAR, FAR) @ view_matrix(np.zeros(3), np.asarray(forward, float), np.asarray(up))
    ctx = layer.ctx
    fbo.use()
    ctx.enable_only(moderngl.DEPTH_TEST)
    fbo.clear(*BACKGROUND, 1.0, depth=clear_depth)
    query = ctx.query(primitives=True)
    with query:
        drawn = layer.render(vp, eye, (W, H), FOV)
    ctx.finish()
    assert query.primitives == drawn
    image = np.frombuffer(fbo.read(components=3, alignment=1), np.uint8).reshape(H, W, 3)[::-1]
    return drawn, image, vp


def _pixel(vp: np.ndarray, eye: np.ndarray, world: np.ndarray) -> tuple[int, int]:
    c = vp @ np.r_[world - eye, 1.0]
    ndc = c[:3] / c[3]
    return int((ndc[0] + 1) / 2 * W), int((1 - ndc[1]) / 2 * H)


def _foreground(image: np.ndarray) -> np.ndarray:
    return np.abs(image.astype(float) - BG8).max(axis=2) > 12


def _expected(models: dict[int, Points], inst: Instances, x: float) -> tuple[int, int]:
    """The documented rule, tree by tree: (splats, trees)."""
    sizes = [len(models[int(m)]) for m in inst.model]
    total = sum(sizes)
    if x == 0:
        return 0, 0
    if x * total < len(sizes):  # partial group: one splat for each of the trees the budget pays for
        t = max(1, math.floor(x * total))
        return t, t
    return sum(min(max(math.floor(x * n + 0.5), 1), n) for n in sizes), len(sizes)


def test_a_tree_is_drawn_where_it_stands(layer, gl) -> None:
    inst = _group([0], [[0.0, 0.0]])
    layer.add_group(7, inst)
    layer.set_resolutions(np.array([7]), np.array([1.0]))
    height = float(layer._models[0][0]["position"][:, 2].max())
    centre = ORIGIN + [0.0, 0.0, height / 2]
    eye = centre + [0.0, -60.0, 0.0]
    drawn, image, vp = _frame(layer, gl[1], eye, (0.0, 1.0, 0.0))
    assert drawn == 1000
    px, py = _pixel(vp, eye, centre)
    assert abs(px - W // 2) <= 1 and abs(py - H // 2) <= 1
    fg = _foreground(image)
    assert fg[py - 3 : py + 4, px - 3 : px + 4].mean() > 0.8
    # Foliage is green, not sky; the corners stay background.
    patch = image[py - 3 : py + 4, px - 3 : px + 4].reshape(-1, 3).astype(float).mean(axis=0)
    assert patch[1] > patch[2] and patch[1] > patch[0]
    assert not fg[:5, :5].any() and not fg[:5, -5:].any()
    # The tree's top and base project onto the rows where the splats end (±a splat).
    _, top = _pixel(vp, eye, ORIGIN + [0.0, 0.0, height])
    _, base = _pixel(vp, eye, ORIGIN)
    rows = np.flatnonzero(fg.any(axis=1))
    assert abs(rows.min() - top) <= 4 and abs(rows.max() - base) <= 4


def test_every_command_of_a_multi_draw_lands(layer, gl) -> None:
    """Groups of mixed models, side by side: each (group, model) run is one indirect command."""
    layer.add_group(1, _group([1, 0], [[-33, 0], [-27, 0]]))
    layer.add_group(2, _group([0, 1, 1], [[-3, 0], [3, 0], [0, 9]]))
    layer.add_group(3, _group([0, 1], [[27, 0], [33, 0]]))
    layer.set_resolutions(np.array([1, 2, 3]), np.array([1.0, 0.5, 0.25]))
    eye = ORIGIN + [0.0, -90.0, 8.0]
    drawn, image, vp = _frame(layer, gl[1], eye, (0.0, 1.0, 0.0))
    assert layer._draws == 6
    fg = _foreground(image)
    for dx in (-30.0, 0.0, 30.0):
        px, py = _pixel(vp, eye, ORIGIN + [dx, 0.0, 6.0])
        assert fg[py - 4 : py + 5, px - 4 : px + 5].mean() > 0.5, dx
    assert not fg[:, :8].any() and not fg[:, -8:].any()


def test_depth_test_hides_splats_behind_nearer_geometry(layer, gl) -> None:
    layer.add_group(7, _group([0], [[0.0, 0.0]]))
    layer.set_resolutions(np.array([7]), np.array([1.0]))
    eye = ORIGIN + [0.0, -60.0, 10.0]
    drawn, image, _ = _frame(layer, gl[1], eye, (0.0, 1.0, 0.0), clear_depth=0.0)
    assert drawn == 1000 and not _foreground(image).any()


def test_counts_agree_with_the_payloads_at_every_x(layer, gl, models) -> None:
    rng = np.random.default_rng(5)
    groups = {
        1: _group(rng.integers(0, 2, 64), rng.uniform(-50, 50, (64, 2))),
        2: _group(rng.integers(0, 2, 10), rng.uniform(-50, 50, (10, 2))),
        3: _group([1, 1, 1, 0, 1], rng.uniform(-50, 50, (5, 2))),
    }
    for rep, inst in groups.items():
        layer.add_group(rep, inst)
    eye = ORIGIN + [0.0, -150.0, 30.0]
    for x in (1.0, 0.7, 0.5, 0.25, 0.1, 0.013, 0.001, 1e-4, 1e-5, 0.0):
        reps = np.array(sorted(groups))
        xs = np.full(reps.size, x)
        want = [_expected(models, groups[r], x) for r in reps]
        splats, trees = sum(w[0] for w in want), sum(w[1] for w in want)
        assert layer.counts(reps, xs) == (splats, trees), x
        layer.set_resolutions(reps, xs)
        drawn, image, _ = _frame(layer, gl[1], eye, (0.0, 1.0, 0.0))
        assert drawn == splats
        assert _foreground(image).any() == (splats > 0)
    # x = 1 draws every point of every tree; mixed x per group add up.
    assert layer.counts(np.array([1]), np.array([1.0]))[0] == sum(len(models[int(m)]) for m in groups[1].model)
    xs = np.array([1.0, 0.3, 0.002])
    want = [_expected(models, groups[r], x) for r, x in zip((1, 2, 3), xs)]
    assert layer.counts(np.array([1, 2, 3]), xs) == (sum(w[0] for w in want), sum(w[1] for w in want))


def test_fewer_points_draw_proportionally_fewer_splats(layer, models) -> None:
    inst = _group(np.arange(64) % 2, np.random.default_rng(1).uniform(-40, 40, (64, 2)))
    layer.add_group(1, inst)
    full = layer.counts(np.array([1]), np.array([1.0]))[0]
    for x in (0.5, 0.25, 0.1):
        assert abs(layer.counts(np.array([1]), np.array([x]))[0] / full - x) < 0.01


def test_partial_group_draws_one_splat_for_some_trees_spread_over_the_group(layer, gl, models) -> None:
    k = 64
    xy = np.column_stack([np.linspace(-300, 300, k), np.zeros(k)])  # a row of trees along x
    inst = _group(np.arange(k) % 2, xy)
    layer.add_group(4, inst)
    total = sum(len(models[int(m)]) for m in inst.model)
    x = 8.5 / total  # budget for 8 splats: 8 of the 64 trees draw one each
    assert layer.counts(np.array([4]), np.array([x])) == (8, 8)
    assert layer.counts(np.array([4]), np.array([0.2 / total])) == (1, 1)  # kept groups draw ≥ 1 tree
    assert layer.counts(np.array([4]), np.array([0.0])) == (0, 0)
    assert layer.counts(np.array([4]), np.array([64.0 / total])) == (64, 64)  # one splat for every tree
    layer.set_resolutions(np.array([4]), np.array([x]))
    eye = ORIGIN + [0.0, -1000.0, 10.0]
    drawn, image, vp = _frame(layer, gl[1], eye, (0.0, 1.0, 0.0))
    assert drawn == 8
    fg = _foreground(image)
    cols = np.flatnonzero(fg.any(axis=0))
    left, _ = _pixel(vp, eye, ORIGIN + [-300.0, 0.0, 0.0])
    right, _ = _pixel(vp, eye, ORIGIN + [300.0, 0.0, 0.0])
    # Eight blobs, not one corner: the drawn trees span most of the row.
    assert cols.max() - cols.min() > 0.7 * (right - left)
    runs = np.count_nonzero(np.diff(np.r_[0, fg.any(axis=0).astype(int)]) == 1)
    assert runs >= 5


def test_coverage_holds_when_fewer_larger_splats_are_drawn(layer, gl) -> None:
    rng = np.random.default_rng(2)
    layer.add_group(1, _group(rng.integers(0, 2, 16), rng.uniform(-30, 30, (16, 2)), yaw_seed=3))
    eye = ORIGIN + [0.0, -70.0, 15.0]
    covered = {}
    for x in (1.0, 0.25, 0.05):
        layer.set_resolutions(np.array([1]), np.array([x]))
        _, image, _ = _frame(layer, gl[1], eye, (0.0, 1.0, 0.0))
        covered[x] = _foreground(image).sum()
    assert covered[1.0] > 1000
    assert 0.7 < covered[0.25] / covered[1.0] < 1.5  # measured 1.09
    assert 0.6 < covered[0.05] / covered[1.0] < 2.0  # measured 1.29


def test_instance_scale_grows_the_tree_and_its_splats(layer, gl) -> None:
    eye = ORIGIN + [0.0, -150.0, 15.0]
    covered = []
    for scale in (1.0, 2.0):
        layer.add_group(1, _group([0], [[0.0, 0.0]], scale=scale))
        layer.set_resolutions(np.array([1]), np.array([0.25]))
        _, image, _ = _frame(layer, gl[1], eye, (0.0, 1.0, 0.0))
        covered.append(_foreground(image).sum())
    assert 3.0 < covered[1] / covered[0] < 5.0  # area ∝ scale²


def test_replacing_and_freeing_groups_and_models(layer, gl, models) -> None:
    layer.add_group(5, _group([0, 0, 0], [[0, 0], [10, 0], [20, 0]]))
    assert layer.counts(np.array([5]), np.array([1.0])) == (3000, 3)
    layer.add_group(5, _group([1], [[0, 0]]))
    assert layer.counts(np.array([5]), np.array([1.0])) == (701, 1)
    layer.add_group(6, _group([0], [[30, 0]]))
    assert layer.counts(np.array([5, 6]), np.array([1.0, 1.0])) == (1701, 2)
    # Stale commands: set_resolutions, then the group changes before render — render re-plans.
    layer.set_resolutions(np.array([5, 6]), np.array([1.0, 1.0]))
    layer.add_group(6, _group([0, 0], [[30, 0], [40, 0]]))
    eye = ORIGIN + [20.0, -150.0, 10.0]
    assert _frame(layer, gl[1], eye, (0.0, 1.0, 0.0))[0] == 2701
    # A replaced model changes every group that uses it.
    layer.add_model(1, Points(models[1].positions[:100], models[1].normals[:100], models[1].colors[:100],
                              models[1].radius[:100]))
    assert layer.counts(np.array([5]), np.array([1.0])) == (100, 1)
    layer.free_group(6)
    layer.free_group(12345)  # unknown: ignored
    assert layer.counts(np.array([5, 6]), np.array([1.0, 1.0])) == (100, 1)
    layer.free_group(5)
    missing = layer.missing
    layer.set_resolutions(np.array([5, 6]), np.array([1.0, 1.0]))
    assert layer.missing == missing + 2
    drawn, image, _ = _frame(layer, gl[1], eye, (0.0, 1.0, 0.0))
    assert drawn == 0 and not _foreground(image).any()


def test_missing_groups_are_counted_and_skipped(layer, gl) -> None:
    layer.add_group(1, _group([0], [[0, 0]]))
    assert layer.missing == 0
    layer.set_resolutions(np.array([3, 1, 9]), np.array([1.0, 1.0, 0.5]))
    assert layer.missing == 2
    assert layer.counts(np.array([3, 1, 9]), np.array([1.0, 1.0, 0.5])) == (1000, 1)
    layer.set_resolutions(np.array([], np.int64), np.array([]))
    assert layer.missing == 2
    assert _frame(layer, gl[1], ORIGIN + [0, -60, 10], (0, 1, 0))[0] == 0


def test_bad_input_is_refused(layer, gl, models) -> None:
    with pytest.raises(ValueError, match=r"\[2, 9\]"):
        layer.add_group(1, _group([0, 9, 2, 9], np.zeros((4, 2))))
    assert layer.has_model(1) and not layer.has_model(2)
    layer.add_group(1, _group([0], [[0, 0]]))
    for x in (1.5, -0.1, np.nan, np.inf):
        with pytest.raises(ValueError, match="x"):
            layer.set_resolutions(np.array([1]), np.array([x]))
        with pytest.raises(ValueError):
            layer.counts(np.array([1]), np.array([x]))
    with pytest.raises(ValueError):
        layer.set_resolutions(np.array([1, 2]), np.array([1.0]))
    with pytest.raises(ValueError):
        layer.render(np.eye(3), np.zeros(3), (W, H), FOV)
    with pytest.raises(ValueError):
        layer.add_model(-1, models[0])
