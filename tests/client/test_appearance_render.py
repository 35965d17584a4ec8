"""The real renderer (EGL) draws payload colours, blends them in a morph, lights by the sun, paints a sky."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from client.renderer import BACKGROUND, Renderer
from client.shading import object_tint
from client.sky import BELOW, HORIZON, ZENITH
from proto.geometry import Geometry

W, H = 160, 120
EYE, FORWARD, UP = np.zeros(3), np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])
RED, BLUE = np.array([220, 40, 30], np.uint8), np.array([30, 60, 220], np.uint8)


@pytest.fixture(scope="module")
def renderer():
    with Renderer(W, H, fov_y=60.0) as r:
        yield r


@pytest.fixture(autouse=True)
def _reset(renderer):
    yield
    for rep in list(renderer.meshes):
        renderer.free(rep)
    renderer.colours, renderer.sun, renderer.false_colour = "data", None, False
    if renderer.sky is not None:
        renderer.sky.release()
        renderer.sky = None


def _sphere(colour: np.ndarray | None, centre=(0.0, 5.0, 0.0)) -> Geometry:
    m = trimesh.creation.icosphere(3)
    p = np.asarray(m.vertices, np.float32) + np.float32(centre)
    c = None if colour is None else np.tile(colour, (p.shape[0], 1))
    return Geometry(p, np.asarray(m.faces, np.uint32), c)


def _hue(pixel: np.ndarray) -> np.ndarray:
    p = pixel.astype(float)
    return p / max(p.sum(), 1.0)


@pytest.mark.parametrize("algorithm", [0, 1, 2])
def test_every_algorithm_draws_the_payload_colour(renderer, algorithm) -> None:
    renderer.upload(1, _sphere(RED))
    renderer.draw(np.array([1]), EYE, FORWARD, UP, 0.1, 100.0, algorithms=np.array([algorithm]))
    centre = renderer.read_image()[H // 2 - 3 : H // 2 + 4, W // 2 - 3 : W // 2 + 4].reshape(-1, 3).mean(axis=0)
    assert centre[0] > 2 * centre[1] and centre[0] > 2 * centre[2]  # red, lit (textured: under its pattern)


def test_objects_mode_and_colourless_payloads_draw_the_tint(renderer) -> None:
    renderer.upload(1, _sphere(RED), object_id=7)
    renderer.upload(2, _sphere(None), object_id=7)
    tint = np.array(object_tint(7))
    images = {}
    for mode, rep in (("objects", 1), ("data", 2), ("data", 1)):
        renderer.colours = mode
        renderer.draw(np.array([rep]), EYE, FORWARD, UP, 0.1, 100.0)
        images[mode, rep] = renderer.read_image()[H // 2, W // 2]
    np.testing.assert_array_equal(images["objects", 1], images["data", 2])  # the tint either way
    np.testing.assert_allclose(_hue(images["data", 2]), tint / tint.sum(), atol=0.02)
    assert np.abs(images["data", 1].astype(int) - images["data", 2]).max() > 40


def test_a_morph_blends_toward_the_target_colours(renderer) -> None:
    fine = _sphere(RED)
    renderer.upload(1, fine)
    renderer.set_morph_target(1, fine.positions, np.tile(BLUE, (fine.vertices, 1)))
    pixels = []
    for w in (1.0, 0.5, 0.0):
        renderer.draw(np.array([1]), EYE, FORWARD, UP, 0.1, 100.0, weights=np.array([w]))
        pixels.append(renderer.read_image()[H // 2, W // 2].astype(int))
    full, half, target = pixels
    assert full[0] > full[2] and target[2] > target[0]  # red at weight 1, blue at 0
    assert target[0] < half[0] < full[0] and full[2] < half[2] < target[2]  # blended between


def test_the_sun_lights_the_side_it_faces(renderer) -> None:
    renderer.upload(1, _sphere(np.array([200, 200, 200], np.uint8)))
    sides = {}
    for sun in ((1.0, 0.0, 0.0), (-1.0, 0.0, 0.0)):
        renderer.sun = np.array(sun)
        renderer.draw(np.array([1]), EYE, FORWARD, UP, 0.1, 100.0, algorithms=np.array([1]))
        row = renderer.read_image()[H // 2].astype(int).sum(axis=1)
        sides[sun[0]] = (row[W // 2 + 15], row[W // 2 - 15])  # right and left of the sphere's centre
    assert sides[1.0][0] > sides[1.0][1] + 60  # the sun in +x (right) lights the right side
    assert sides[-1.0][1] > sides[-1.0][0] + 60


def test_the_sky_runs_from_zenith_to_horizon_with_haze_below(renderer) -> None:
    renderer.draw(np.zeros(0, np.int64), EYE, FORWARD, UP, 0.1, 100.0)
    cleared = renderer.read_image()
    assert (cleared == np.round(np.array(BACKGROUND) * 255)).all()  # without a sky: the clear colour
    renderer.enable_sky()
    pitched = np.array([0.0, np.cos(0.3), np.sin(0.3)])  # looking 17° up: the horizon below the centre
    renderer.draw(np.zeros(0, np.int64), EYE, pitched, UP, 0.1, 100.0)
    image = renderer.read_image().astype(float) / 255
    top, bottom = image[0, W // 2], image[-1, W // 2]
    horizon_row = int(round(H / 2 + np.tan(0.3) / np.tan(np.radians(30)) * H / 2))
    assert horizon_row < H - 5
    assert np.abs(top - ZENITH).max() < np.abs(top - HORIZON).max()  # the top is nearer the zenith's blue
    assert top[2] > top[0] + 0.2
    np.testing.assert_allclose(bottom, BELOW, atol=0.02)  # the haze below the horizon
    np.testing.assert_allclose(image[horizon_row - 2, W // 2], HORIZON, atol=0.06)
    # Drawn meshes cover the sky: the frame's depth was cleared, its colour kept.
    renderer.upload(1, _sphere(RED, centre=(0.0, 5.0 * np.cos(0.3), 5.0 * np.sin(0.3))))
    stats = renderer.draw(np.array([1]), EYE, pitched, UP, 0.1, 100.0)
    centre = renderer.read_image()[H // 2, W // 2]
    assert stats.pixels > 0 and centre[0] > 2 * centre[2]
