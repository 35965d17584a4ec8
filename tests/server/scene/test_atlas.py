"""The per-object texture atlas: shelf packing, every image inside it and none overlapping, UVs inside their
image's rectangle (repeating ones wrapped per polygon), colour patches, vertices split where UVs differ."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from server.scene.importers.atlas import (ATLAS_SIDE, GAP, PATCH, atlas_uvs, build_atlas, object_texture,
                                          shelf_pack, split_by_uv)

sizes = st.lists(st.tuples(st.integers(1, 512), st.integers(1, 512)), min_size=1, max_size=24)


def _overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether rectangles (x, y, w, h) a and b share a pixel."""
    return bool(a[0] < b[0] + b[2] and b[0] < a[0] + a[2] and a[1] < b[1] + b[3] and b[1] < a[1] + a[3])


@settings(max_examples=60, deadline=None)
@given(sizes, st.integers(512, 2048))
def test_shelf_pack_keeps_every_rectangle_inside_the_strip_and_apart(wh, width) -> None:
    s = np.array(wh, np.int64)
    offsets, height = shelf_pack(s, width)
    rects = np.column_stack([offsets, s])
    assert (offsets >= 0).all() and (offsets[:, 0] + s[:, 0] <= width).all() and (offsets[:, 1] + s[:, 1] <= height).all()
    for i in range(len(rects)):
        for j in range(i):
            assert not _overlap(rects[i], rects[j])


def _image(w: int, h: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


@settings(max_examples=30, deadline=None)
@given(sizes, st.integers(0, 2 ** 16), st.integers(64, 2048), st.data())
def test_every_image_lands_in_the_atlas_and_uvs_stay_in_their_rectangle(wh, seed, side, data) -> None:
    images = [_image(w, h, seed + k) for k, (w, h) in enumerate(wh)]
    atlas = build_atlas(images, side=side)
    H, W = atlas.image.shape[:2]
    assert H <= side and W <= side
    r = atlas.rects
    padded = r + np.array([-GAP, -GAP, 2 * GAP, 2 * GAP])
    assert (padded[:, :2] >= 0).all() and (padded[:, 0] + padded[:, 2] <= W).all()
    assert (padded[:, 1] + padded[:, 3] <= H).all()
    for i in range(len(r)):
        for j in range(i):
            assert not _overlap(padded[i], padded[j])  # borders included
    # At full scale each image sits in its rectangle unchanged.
    for im, (x, y, w, h) in zip(images, r.tolist()):
        if (w, h) == (im.shape[1], im.shape[0]):
            assert np.array_equal(atlas.image[y:y + h, x:x + w], im)
    # Faces with UVs anywhere (repeating textures) map inside their image's rectangle.
    m = data.draw(st.integers(1, 20))
    item = np.array(data.draw(st.lists(st.integers(0, len(images) - 1), min_size=m, max_size=m)))
    uv = np.array(data.draw(st.lists(st.floats(-5, 5), min_size=6 * m, max_size=6 * m))).reshape(m, 3, 2)
    out = atlas_uvs(uv, item, np.arange(m), atlas)
    px, py = out[:, :, 0] * W, (1.0 - out[:, :, 1]) * H  # pixels, rows from the top
    x, y, w, h = (r[item][:, k, None] for k in range(4))
    eps = 1e-6
    assert ((px >= x - eps) & (px <= x + w + eps) & (py >= y - eps) & (py <= y + h + eps)).all()


def test_a_polygon_is_wrapped_by_its_integer_offset_in_one_piece() -> None:
    """A quad mapped onto [2, 3] × [-1, 0] is its image's [0, 1] × [0, 1]; its two triangles move together."""
    image = _image(10, 20, 1)
    atlas = build_atlas([image])
    quad = np.array([[[2, -1], [3, -1], [3, 0]], [[2, -1], [3, 0], [2, 0]]], float)
    got = atlas_uvs(quad, np.zeros(2, int), np.zeros(2, int), atlas)
    want = atlas_uvs(quad - [2, -1], np.zeros(2, int), np.zeros(2, int), atlas)
    np.testing.assert_allclose(got, want)
    # (0, 0) is the bottom-left texel's centre, (1, 1) the top-right one's.
    x, y, w, h = atlas.rects[0]
    H, W = atlas.image.shape[:2]
    np.testing.assert_allclose(want[0, 0], [(x + 0.5) / W, 1 - (y + h - 0.5) / H])
    np.testing.assert_allclose(want[0, 2], [(x + w - 0.5) / W, 1 - (y + 0.5) / H])


def test_too_many_images_are_scaled_down_together_to_fit() -> None:
    images = [_image(512, 512, k) for k in range(24)]
    atlas = build_atlas(images)
    assert max(atlas.image.shape[:2]) <= ATLAS_SIDE
    assert len({(int(w), int(h)) for w, h in atlas.rects[:, 2:]}) == 1 and atlas.rects[0, 2] < 512


def test_images_that_cannot_fit_even_at_one_pixel_are_refused() -> None:
    with pytest.raises(ValueError, match="do not fit"):
        build_atlas([_image(8, 8, k) for k in range(4)], side=2 * GAP + 1)


def test_faces_without_an_image_point_at_a_patch_of_their_colour() -> None:
    red = np.zeros((8, 8, 3), np.uint8)
    red[:] = (255, 0, 0)
    face_image = np.array([0, -1, 1])  # image 1 could not be read: that face is a colour face too
    uv = np.array([[[0, 0], [1, 0], [1, 1]], [[np.nan, np.nan]] * 3, [[0, 0], [1, 0], [1, 1]]], float)
    colours = np.array([[9, 9, 9], [0, 0, 200], [0, 120, 0]], np.uint8)
    texture, out = object_texture(face_image, uv, np.arange(3), colours, [red, None])
    H, W = texture.shape[:2]
    rows = np.floor((1 - out[:, :, 1]) * H).astype(int)
    cols = np.floor(out[:, :, 0] * W).astype(int)
    sampled = texture[rows, cols]  # (3, 3, 3) the texel under each corner
    assert (sampled[0] == (255, 0, 0)).all()
    assert (sampled[1] == (0, 0, 200)).all() and (sampled[2] == (0, 120, 0)).all()
    assert (out[1] == out[1, 0]).all()  # every corner at the patch's centre
    patch = texture[rows[1, 0] - PATCH // 2 + 1: rows[1, 0] + PATCH // 2, cols[1, 0] - PATCH // 2 + 1: cols[1, 0] + PATCH // 2]
    assert (patch == (0, 0, 200)).all()
    assert object_texture(np.array([-1]), uv[1:2], np.zeros(1), colours[:1], []) is None


def test_a_vertex_is_split_where_its_corners_uvs_differ() -> None:
    vertex = np.array([[0, 1, 2], [0, 2, 3]])
    uv = np.array([[[0, 0], [1, 0], [1, 1]], [[0.5, 0.5], [1, 1], [0, 1]]], float)
    source, faces, vuv = split_by_uv(vertex, uv)
    assert len(source) == 5  # vertex 0 twice, vertex 2 once (same UV from both faces)
    np.testing.assert_array_equal(source[faces], vertex)
    np.testing.assert_allclose(vuv[faces], uv)
