"""The selection draws a textured representation with its texture (F&S's Accuracy over algorithms, R):
drawing it in its mean colour loses the texture's detail, an error the image shows; an untextured
representation is chosen exactly as before."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from server.scene.store import SceneStore
from server.scene.writer import SceneWriter, encode_levels
from server.select import kernels, options
from server.select.benefit import UNTEXTURED_ACCURACY, BenefitFactors, benefit_matrix, texture_accuracy
from server.select.camera import View
from server.select.cost import CostModel
from server.select.selection import Levels, Scene, _textured, select

BOUNDS = np.array([[-200.0, -10.0, -10.0], [200.0, 400.0, 10.0]])
ALL = (0, 1, 2)  # flat, lit, textured: what the normal client offers
FLAT, LIT, TEXTURED = ALL


def _view():
    return View.of_pose([0, 0, 0], [0, 1, 0], [0, 0, 1], 60.0, (640, 360), BOUNDS)


def _row(n: int, levels: int = 3, textured=None) -> Levels:
    """n boxes in a row ahead of the camera, ``levels`` levels each growing 4× in faces; ``textured``: (n,) bool
    objects whose every level carries a texture (None: none does)."""
    lo = np.stack([np.zeros(n), 8.0 + 6.0 * np.arange(n), np.zeros(n) - 1.0], axis=1)
    faces = np.tile(100 * 4 ** np.arange(levels), n)
    rep_textured = None if textured is None else np.repeat(np.asarray(textured, bool), levels)
    return Levels(lo, lo + 2.0, np.arange(n) * levels, np.full(n, levels), faces, faces // 2,
                  rep_textured=rep_textured)


@pytest.mark.parametrize("accuracy", ["fs", "sse", "zach"])
def test_with_time_to_spare_a_textured_object_is_drawn_textured_an_untextured_one_as_before(accuracy):
    n = 12
    textured = np.arange(n) % 2 == 0
    base = _row(n)
    if accuracy == "sse":  # errors falling with level, as a store's
        base = dataclasses.replace(base, rep_error=np.tile([0.4, 0.1, 0.0], n))
    lv = dataclasses.replace(base, rep_textured=np.repeat(textured, 3))
    model, factors = CostModel(c_vertex=1e-7), BenefitFactors(accuracy=accuracy)
    choice = select(lv, _view(), model, 10.0, "greedy", 0.0, algorithms=ALL, factors=factors)
    before = select(base, _view(), model, 10.0, "greedy", 0.0, algorithms=ALL, factors=factors)
    assert choice.reps.size == n  # every box drawn
    obj = choice.reps // 3
    assert (choice.algorithm[textured[obj]] == TEXTURED).all()
    # untextured boxes: the same algorithm as when nothing in the scene is textured (lit, under F&S's m = 2)
    same = dict(zip((before.reps // 3).tolist(), before.algorithm.tolist()))
    assert [same[o] for o in obj[~textured[obj]]] == choice.algorithm[~textured[obj]].tolist()
    assert TEXTURED not in choice.algorithm[~textured[obj]]
    if accuracy == "fs":
        assert (choice.algorithm[~textured[obj]] == LIT).all()


def test_a_tight_budget_still_settles_for_a_cheaper_algorithm():
    """One textured box of one level: a budget that fits it lit but not textured draws it lit, not nothing."""
    lv = _row(1, levels=1, textured=[True])
    model = CostModel(c_vertex=1e-6)
    lit, textured = (model.vertex_coefficients()[a] * lv.rep_vertices[0] for a in (LIT, TEXTURED))
    assert lit < textured
    roomy = select(lv, _view(), model, 1.01 * textured, "greedy", 0.0, algorithms=ALL)
    assert roomy.algorithm.tolist() == [TEXTURED]
    tight = select(lv, _view(), model, 0.5 * (lit + textured), "greedy", 0.0, algorithms=ALL)
    assert tight.reps.tolist() == [0] and tight.algorithm.tolist() == [LIT]


def test_the_untextured_algorithms_lose_accuracy_only_on_a_texture():
    textured = np.array([[True] * 6, [False] * 6])
    got = texture_accuracy(textured, 3, ("flat", "lit", "textured"))
    u = UNTEXTURED_ACCURACY
    np.testing.assert_array_equal(got, [[u, u, 1, u, u, 1], [1] * 6])
    # offered lit and textured only: option k is drawn with names[k % 2]
    np.testing.assert_array_equal(texture_accuracy(textured[:, :4], 2, ("lit", "textured"))[0], [u, 1, u, 1])
    assert 0 < u < 1


def test_an_index_without_textures_gives_a_view_without_them():
    class Index:
        rep_texels = np.array([0, 0, 64, 0])

    assert _textured(Index()).tolist() == [False, False, True, False]
    Index.rep_texels = np.zeros(4, np.int32)  # an older store: nothing is textured, the benefit is unchanged
    assert _textured(Index()) is None


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 60), levels=st.integers(1, 4), r=st.integers(1, 3),
       accuracy=st.sampled_from(["fs", "zach", "off", "sse"]), hysteresis=st.booleans())
def test_the_compiled_benefit_counts_the_texture_as_numpy_does(seed, n, levels, r, accuracy, hysteresis):
    kernels.use_kernels(True)
    try:
        kern = kernels.compiled().view
        rng = np.random.default_rng(seed)
        cams, k = int(rng.integers(1, 4)), levels * r
        faces = np.sort(rng.integers(1, 20_000, (n, levels)), axis=1).repeat(r, axis=1).astype(np.int32)
        vertices = (faces * rng.uniform(0.5, 1.5, faces.shape)).astype(np.int32)
        valid = np.arange(k)[None, :] < (rng.integers(1, levels + 1, n) * r)[:, None]
        textured = rng.random((n, levels)).repeat(r, axis=1) < 0.5
        error = np.sort(rng.uniform(0, 2, (n, levels)), axis=1)[:, ::-1].repeat(r, axis=1).copy()
        extent = rng.uniform(1, 30, n)
        size = rng.choice([0.0, 3.0, 400.0, 2e5], (cams, n)) * rng.uniform(0.5, 1.5, (cams, n))
        offset = rng.uniform(0, 1.2, (cams, n))
        speed = [rng.uniform(0, 3000, n) if j % 2 else None for j in range(cams)]
        weight = rng.uniform(0.05, 1.0, cams)
        previous = rng.integers(-1, k + 1, n)
        factors = BenefitFactors(accuracy=accuracy, hysteresis=hysteresis,
                                 algorithm_names=("flat", "lit", "textured")[:r])
        want = np.zeros((n, k))
        for j in range(cams):
            want += weight[j] * benefit_matrix(size[j], faces, algorithms=r, factors=factors, vertices=vertices,
                                               offset=offset[j], speed=speed[j], previous=previous, error=error,
                                               extent=extent, textured=textured)
        want = np.where(valid, want, 0.0)
        got = options.benefit_kernel(kern, size, offset, speed, weight, faces, vertices, valid, r, factors, None,
                                     None, previous, None, error, extent, textured)
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
        plain = options.benefit_kernel(kern, size, offset, speed, weight, faces, vertices, valid, r, factors, None,
                                       None, previous, None, error, extent)
        loses = textured & valid & (np.arange(k) % r != 2)[None, :] & (got > 0)
        if accuracy != "off" and not hysteresis:
            np.testing.assert_allclose(got[loses], UNTEXTURED_ACCURACY * plain[loses], rtol=1e-12)
    finally:
        kernels.use_kernels(None)


def test_a_scene_of_an_index_carries_its_textured_reps(tmp_path):
    """From the writer through the store's index to the solvers' view: one textured box, one plain."""
    box = trimesh.creation.box((2.0, 2.0, 2.0))
    uv = np.asarray(box.vertices)[:, :2] / 2.0 + 0.5
    tex = np.zeros((8, 8, 3), np.uint8)
    tex[::2] = 200
    with SceneWriter(tmp_path / "t.db", walkable=False) as w:
        lv = [(np.asarray(box.vertices), np.asarray(box.faces))]
        lo, hi, blobs, _ = encode_levels(lv, reorder=False, uvs=[uv], textures=[tex])
        w.add_encoded("textured", "box", lo, hi, [0.0], blobs)
        lo, hi, blobs, _ = encode_levels([(np.asarray(box.vertices) + 5.0, np.asarray(box.faces))])
        w.add_encoded("plain", "box", lo, hi, [0.0], blobs)
    with SceneStore.open(tmp_path / "t.db") as store:
        assert store.index.rep_texels.tolist() == [64, 0]
        scene = Scene.of(store.index)
        assert scene.flat.rep_textured.tolist() == [True, False]
