"""The kiosk draws the sky the walkstream client draws, unless its config says a plain background."""

from __future__ import annotations

import numpy as np

from client.kiosk.run import kiosk_renderer
from client.renderer import BACKGROUND
from client.sky import ZENITH


def _empty_frame(sky: bool) -> np.ndarray:
    renderer = kiosk_renderer((64, 48), None, sky)
    try:
        renderer.draw(np.zeros(0, np.int64), np.zeros(3), np.array([0.0, 1.0, 0.3]), np.array([0.0, 0.0, 1.0]),
                      0.1, 10.0)
        return renderer.read_image()
    finally:
        renderer.release()


def test_the_kiosk_draws_the_sky_by_default_and_a_plain_background_when_told():
    sky, plain = _empty_frame(True), _empty_frame(False)
    background = np.round(np.asarray(BACKGROUND) * 255)
    assert np.abs(plain.astype(float) - background).max() <= 1  # one colour
    top, bottom = sky[0].astype(float).mean(axis=0), sky[-1].astype(float).mean(axis=0)
    assert np.abs(top - np.asarray(ZENITH) * 255).max() < np.abs(bottom - np.asarray(ZENITH) * 255).max()
    assert np.abs(sky[0].astype(float) - background).max() > 10  # not the plain background


def test_the_example_config_asks_for_the_sky():
    import tomllib

    from client.kiosk.example import EXAMPLE

    assert tomllib.loads(EXAMPLE)["kiosk"]["sky"] is True
