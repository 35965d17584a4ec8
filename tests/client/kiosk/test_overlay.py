"""The overlay: touch targets big enough and hit where they are drawn; captions reach the frame's pixels."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from client.kiosk.compositor import Compositor
from client.kiosk.config import DEFAULT_FONT
from client.kiosk.overlay import BUTTONS, MIN_TARGET, Layout, Overlay, OverlayState, wrap
from client.renderer import BACKGROUND, Renderer


@settings(max_examples=200, deadline=None)
@given(st.integers(320, 3840), st.integers(180, 2160), st.floats(0, 1), st.floats(0, 1))
def test_buttons_are_large_apart_and_hit_where_they_are(width, height, u, v):
    lay = Layout(width, height)
    buttons = lay.buttons("en")
    assert [b.name for b in buttons] == [name for name, _ in BUTTONS]
    for b in buttons:
        assert b.w >= MIN_TARGET and b.h >= MIN_TARGET
        assert 0 <= b.x and b.x + b.w <= width and 0 <= b.y and b.y + b.h <= height
        assert lay.hit(b.x + u * (b.w - 1), b.y + v * (b.h - 1)) == b.name
    for a, b in zip(buttons, buttons[1:]):
        assert a.x + a.w <= b.x  # side by side, never overlapping
    assert lay.hit(width / 2, height / 3) is None  # the scene


def test_captions_wrap_to_the_band():
    from PIL import ImageFont

    font = ImageFont.truetype(DEFAULT_FONT, 40)
    lines = wrap("The auditorium: 440 chairs facing the stage, twenty rows rising to the back", font, 500)
    assert len(lines) >= 2 and all(font.getlength(line) <= 500 for line in lines)
    assert " ".join(lines) == "The auditorium: 440 chairs facing the stage, twenty rows rising to the back"


def test_the_overlay_is_rasterised_only_when_it_changes():
    ov = Overlay(320, 180, font=DEFAULT_FONT, caption_px=20)
    a = OverlayState(caption="The grand piano", language="en")
    image, changed = ov.image(a)
    assert changed and image.shape == (180, 320, 4) and ov.rasterised == 1
    assert ov.image(OverlayState(caption="The grand piano", language="en"))[1] is False and ov.rasterised == 1
    assert ov.image(OverlayState(caption="Der Flügel", language="de"))[1] is True and ov.rasterised == 2
    counting = ov.image(OverlayState(countdown=12))[0]
    assert counting[..., 3].max() == 255 and not np.array_equal(counting, image)


@pytest.fixture
def renderer():
    r = Renderer(320, 180)
    yield r
    r.release()


def _text_mask(ov: Overlay, state: OverlayState) -> np.ndarray:
    """(h, w) bool: the caption band's fully opaque white pixels (the glyphs' cores)."""
    image, _ = ov.image(state)
    mask = (image[..., 3] == 255) & (image[..., :3] == 255).all(axis=2)
    mask[ov.layout.caption_bottom:] = False  # not the buttons' labels
    return mask


def test_a_caption_reaches_the_rendered_frame(renderer):
    from proto.geometry import Geometry

    tri = Geometry(np.array([[-50, 10, -20], [50, 10, -20], [0, 10, 40]], np.float32), np.array([[0, 1, 2]], np.uint32))
    renderer.upload(0, tri, object_id=3)
    eye, forward, up = np.zeros(3), np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])
    stats = renderer.draw(np.array([0]), eye, forward, up, 0.1, 100.0)
    assert stats.triangles == 1
    plain = renderer.read_image()
    ov = Overlay(320, 180, font=DEFAULT_FONT, caption_px=20)
    state = OverlayState(caption="The grand piano")
    comp = Compositor(renderer)
    comp.draw(*ov.image(state))
    shown = renderer.read_image()
    mask = _text_mask(ov, state)
    assert mask.sum() > 100
    assert np.all(shown[mask] == 255)  # every glyph core is white in the frame
    assert np.any(plain[mask] != 255)  # ... and was not before
    band = (ov.image(state)[0][..., 3] > 0)
    assert np.array_equal(shown[~band], plain[~band])  # outside the overlay the frame is untouched
    # The next frame's draw clears and redraws: the overlay is never timed, never left behind.
    renderer.draw(np.array([0]), eye, forward, up, 0.1, 100.0)
    assert np.array_equal(renderer.read_image(), plain)
    comp.draw(*ov.image(state))  # unchanged: no upload, the same pixels
    assert comp.uploads == 1 and np.array_equal(renderer.read_image(), shown)
    comp.release()


def test_dimming_darkens_the_whole_frame(renderer):
    renderer.draw(np.zeros(0, np.int64), np.zeros(3), np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0]), 0.1, 10.0)
    comp = Compositor(renderer)
    ov = Overlay(320, 180, font=DEFAULT_FONT)
    comp.draw(*ov.image(OverlayState(buttons=False, dim=1.0)))
    assert renderer.read_image().max() == 0  # "black" outside the open hours
    renderer.draw(np.zeros(0, np.int64), np.zeros(3), np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0]), 0.1, 10.0)
    comp.draw(*ov.image(OverlayState(buttons=False, dim=0.6)))
    sky = np.round(np.asarray(BACKGROUND) * 255)
    assert np.all(np.abs(renderer.read_image()[90, 160] - 0.4 * sky) <= 2)
    comp.release()
