"""The real renderer (EGL) keeps each textured representation's texture in a layer of its size class's array
and the textured algorithm samples it, in the same multi-draw as untextured ones; layers are freed and reused."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from client.renderer import Renderer
from client.textures import SIDES, Layers, size_class
from proto.geometry import Geometry

W, H = 160, 120
EYE, FORWARD, UP = np.zeros(3), np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])
RED, GREEN = (220, 30, 30), (30, 200, 40)
GREY = np.array([150, 150, 150], np.uint8)


def checker(side: int, cells: int) -> np.ndarray:
    tex = np.zeros((side, side, 3), np.uint8)
    odd = (np.indices((side, side)) // (side // cells)).sum(axis=0) % 2 == 1
    tex[~odd], tex[odd] = RED, GREEN
    return tex


def quad(x0: float, x1: float, texture: np.ndarray | None, y: float = 4.0) -> Geometry:
    """A wall facing the camera at distance y, from x0 to x1 and z −1..1, UVs over its face."""
    p = np.array([[x0, y, -1], [x1, y, -1], [x1, y, 1], [x0, y, 1]], np.float32)
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32) if texture is not None else None
    return Geometry(p, np.array([[0, 1, 2], [0, 2, 3]], np.uint32), np.tile(GREY, (4, 1)), uv, texture)


@pytest.fixture(scope="module")
def renderer():
    with Renderer(W, H, fov_y=60.0) as r:
        yield r


@pytest.fixture(autouse=True)
def _reset(renderer):
    yield
    for rep in list(renderer.meshes):
        renderer.free(rep)


def _kinds(row: np.ndarray) -> np.ndarray:
    """Per pixel of a row: 0 red-ish, 1 green-ish, -1 neither."""
    row = row.astype(int)
    red = (row[:, 0] > 1.8 * row[:, 1]) & (row[:, 0] > 1.8 * row[:, 2])
    green = (row[:, 1] > 1.8 * row[:, 0]) & (row[:, 1] > 1.8 * row[:, 2])
    return np.where(red, 0, np.where(green, 1, -1))


def _runs(kinds: np.ndarray) -> int:
    """How many times a row switches between red and green (other pixels skipped)."""
    k = kinds[kinds >= 0]
    return int(np.count_nonzero(np.diff(k)))


def test_textured_draws_the_texture_and_untextured_the_procedural_pattern_in_one_pass(renderer) -> None:
    renderer.upload(1, quad(-3.0, -0.2, checker(64, 8)))  # left half: textured
    renderer.upload(2, quad(0.2, 3.0, None))  # right half: no texture
    stats = renderer.draw(np.array([1, 2]), EYE, FORWARD, UP, 0.1, 100.0, algorithms=np.array([2, 2]))
    assert stats.terms.draws[2] == 2  # one algorithm group: both in the same multi-draw
    image = renderer.read_image()
    left, right = image[H // 2, : W // 2 - 8], image[H // 2, W // 2 + 8:]
    # the checker's 8 cells across the quad: both colours, alternating along the row
    kinds = _kinds(left)
    assert (kinds == 0).sum() > 10 and (kinds == 1).sum() > 10
    assert _runs(kinds) >= 5
    # the untextured wall: its grey under the procedural bricks, never the checker's colours
    assert (_kinds(right) < 0).all()
    assert np.ptp(right.astype(int).mean(axis=1)) > 5  # a pattern, not a flat colour


def test_flat_and_lit_draw_the_payload_colour_not_the_texture(renderer) -> None:
    renderer.upload(1, quad(-2.0, 2.0, checker(64, 8)))
    for algorithm in (0, 1):
        renderer.draw(np.array([1]), EYE, FORWARD, UP, 0.1, 100.0, algorithms=np.array([algorithm]))
        row = renderer.read_image()[H // 2, W // 4: 3 * W // 4].astype(int)
        assert (_kinds(row) < 0).all() and np.ptp(row, axis=1).max() < 30  # grey, no checker


def test_textures_of_several_sizes_and_a_freed_layer_reused(renderer) -> None:
    """Each texture lands in its size class (a non-square one resampled up to its class), freeing gives its
    layer back, and a rep uploaded after draws its own texture from the reused layer."""
    renderer.upload(1, quad(-3.0, -0.2, checker(16, 2)))
    renderer.upload(2, quad(0.2, 3.0, checker(64, 8)[:, :40]))  # 64 × 40: class of 64
    assert renderer.textures.layers[size_class(16, 16)].used == 1
    assert renderer.textures.layers[size_class(64, 64)].used == 1
    renderer.free(1)
    assert renderer.textures.layers[size_class(16, 16)].used == 0
    green = np.zeros((16, 16, 3), np.uint8)
    green[:] = GREEN
    renderer.upload(3, quad(-3.0, -0.2, green))  # takes rep 1's layer
    renderer.draw(np.array([3, 2]), EYE, FORWARD, UP, 0.1, 100.0, algorithms=np.array([2, 2]))
    image = renderer.read_image()
    assert (_kinds(image[H // 2, 8: W // 2 - 16]) == 1).all()
    assert _runs(_kinds(image[H // 2, W // 2 + 16:])) >= 3


def test_many_textures_grow_their_class_and_keep_their_pixels(renderer) -> None:
    """Past a class's first layers its array doubles; the layers written before keep their texture."""
    solid = []
    for i in range(9):
        t = np.zeros((8, 8, 3), np.uint8)
        t[:] = RED if i % 2 == 0 else GREEN
        solid.append(t)
        renderer.upload(10 + i, quad(-3.0 + 0.6 * i, -2.5 + 0.6 * i, t))
    assert renderer.textures.layers[0].capacity >= 9
    renderer.draw(np.arange(10, 19), EYE, FORWARD, UP, 0.1, 100.0, algorithms=np.full(9, 2))
    row = renderer.read_image()[H // 2]
    kinds = _kinds(row)
    assert _runs(kinds) >= 8  # nine walls alternating red, green, red...
    assert kinds[kinds >= 0][0] == 0


@given(st.integers(1, SIDES[-1]), st.integers(1, SIDES[-1]))
def test_a_size_class_holds_the_texture(h: int, w: int) -> None:
    k = size_class(h, w)
    assert SIDES[k] >= max(h, w) and (k == 0 or SIDES[k - 1] < max(h, w))


def test_layers_are_reused_and_double_when_full() -> None:
    layers = Layers(2)
    a, grew_a = layers.take()
    b, grew_b = layers.take()
    c, grew_c = layers.take()
    assert {a, b} == {0, 1} and not grew_a and not grew_b and grew_c and layers.capacity == 4 and c in (2, 3)
    layers.give(a)
    assert layers.take() == (a, False)
    with pytest.raises(ValueError, match="not in use"):
        layers.give(9)
