"""What the kiosk draws over the scene: the caption, the touch buttons, the countdown, the reconnecting mark.

Two parts. ``Layout`` is pure geometry in window pixels (x right, y down): where the buttons are — each at
least ``MIN_TARGET`` px square (WCAG 2.5.5's 44 × 44 CSS px) — and which one a tap hits. ``Overlay``
rasterises the visible parts with Pillow's FreeType text into one RGBA image the size of the frame: the
caption word-wrapped in large type on a translucent band above the buttons, the countdown ("Touch to
continue" and the seconds left) in the middle, and a small "reconnecting…" in a corner while the server is
lost. It re-rasterises only when what it shows changes (``OverlayState`` is the key), so a frame that
shows what the last one did costs nothing here; ``client.kiosk.compositor`` blends the image over the
frame after the timed draw.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from PIL import Image, ImageDraw, ImageFont

__all__ = ["Layout", "Button", "Overlay", "OverlayState", "BUTTONS", "MIN_TARGET", "wrap"]

#: The smallest touch target, px (WCAG 2.5.5).
MIN_TARGET = 44
#: The buttons, left to right: name and label (the language button shows the language instead).
BUTTONS = (("home", "⌂"), ("language", ""), ("previous", "◀"), ("next", "▶"))

_BAND = (0, 0, 0, 150)  # the caption band: black, translucent
_TEXT = (255, 255, 255, 255)
_BUTTON = (20, 20, 20, 170)
_EDGE = (255, 255, 255, 200)


@dataclass(frozen=True)
class Button:
    name: str
    label: str
    x: int
    y: int
    w: int
    h: int

    def contains(self, x: float, y: float) -> bool:
        return self.x <= x < self.x + self.w and self.y <= y < self.y + self.h


@dataclass(frozen=True)
class Layout:
    """Where things go in a ``width`` × ``height`` frame (pixels, y down)."""

    width: int
    height: int

    @property
    def size(self) -> int:
        """A button's height: ≥ ``MIN_TARGET``, growing with the frame (four buttons and their gaps take 7 sizes
        of its width: a frame narrower than 7 × 44 px crowds them)."""
        return max(MIN_TARGET, min(round(self.height * 0.09), self.width // 7))

    @property
    def margin(self) -> int:
        return max(6, self.size // 4)

    def buttons(self, language: str = "") -> list[Button]:
        """The buttons along the bottom: home and language at the left, previous and next at the right."""
        s, m = self.size, self.margin
        w = 3 * s // 2  # four of these and their gaps: at most 7 sizes, within the width
        y = self.height - m - s
        xs = {"home": m, "language": 2 * m + w, "previous": self.width - 2 * (m + w), "next": self.width - m - w}
        return [Button(name, label or language.upper(), xs[name], y, w, s) for name, label in BUTTONS]

    def hit(self, x: float, y: float) -> str | None:
        """The button at window pixel (x, y), or None (the scene: a tap there is input, nothing more)."""
        for b in self.buttons():
            if b.contains(x, y):
                return b.name
        return None

    @property
    def caption_bottom(self) -> int:
        """The caption band's lower edge: above the buttons."""
        return self.height - 2 * self.margin - self.size


@dataclass(frozen=True)
class OverlayState:
    """Everything the overlay shows; equal states give the same image."""

    caption: str = ""
    language: str = "en"
    countdown: int | None = None
    reconnecting: bool = False
    buttons: bool = True
    #: Darken the scene by this much (0: not at all, 1: black) — outside the open hours.
    dim: float = 0.0


@lru_cache(maxsize=16)
def _font(path: str, px: int) -> ImageFont.FreeTypeFont:
    return ImageFont.truetype(path, px)


def wrap(text: str, font: ImageFont.FreeTypeFont, width: float) -> list[str]:
    """``text`` broken into lines no wider than ``width`` px (a word longer than that gets a line of its own)."""
    lines: list[str] = []
    for paragraph in text.splitlines() or [""]:
        line = ""
        for word in paragraph.split():
            trial = f"{line} {word}" if line else word
            if line and font.getlength(trial) > width:
                lines.append(line)
                line = word
            else:
                line = trial
        lines.append(line)
    return [ln for ln in lines if ln]


class Overlay:
    """Rasterises an ``OverlayState`` into an RGBA frame-sized image (rows top-down), cached by state."""

    def __init__(self, width: int, height: int, *, font: str, caption_px: int = 40) -> None:
        self.layout = Layout(int(width), int(height))
        self.font_path, self.caption_px = str(font), int(caption_px)
        _font(self.font_path, self.caption_px)  # a bad font fails here, at start, not at the first caption
        self._state: OverlayState | None = None
        self._image: np.ndarray | None = None
        self.rasterised = 0
        """Images made so far (a changed state each)."""

    def image(self, state: OverlayState) -> tuple[np.ndarray, bool]:
        """(the (height, width, 4) uint8 image for ``state``, whether it changed since the last call)."""
        if state == self._state and self._image is not None:
            return self._image, False
        self._state, self._image = state, self._draw(state)
        self.rasterised += 1
        return self._image, True

    def _draw(self, state: OverlayState) -> np.ndarray:
        lay = self.layout
        img = Image.new("RGBA", (lay.width, lay.height), (0, 0, 0, round(255 * min(max(state.dim, 0.0), 1.0))))
        d = ImageDraw.Draw(img)
        m = lay.margin
        if state.caption:
            font = _font(self.font_path, self.caption_px)
            lines = wrap(state.caption, font, lay.width - 4 * m)[:4]
            step = round(self.caption_px * 1.25)
            h = step * len(lines) + 2 * m
            top = lay.caption_bottom - h
            d.rounded_rectangle((m, top, lay.width - m, lay.caption_bottom), radius=m, fill=_BAND)
            for i, line in enumerate(lines):
                d.text((lay.width / 2, top + m + i * step), line, font=font, fill=_TEXT, anchor="ma")
        if state.buttons:
            font = _font(self.font_path, max(16, lay.size // 2))
            for b in lay.buttons(state.language):
                d.rounded_rectangle((b.x, b.y, b.x + b.w - 1, b.y + b.h - 1), radius=m, fill=_BUTTON, outline=_EDGE,
                                    width=2)
                d.text((b.x + b.w / 2, b.y + b.h / 2), b.label, font=font, fill=_TEXT, anchor="mm")
        if state.countdown is not None:
            big = _font(self.font_path, max(24, round(self.caption_px * 1.4)))
            small = _font(self.font_path, self.caption_px)
            w, h = min(lay.width - 2 * m, round(big.size * 12)), round(big.size * 3.2)
            x0, y0 = (lay.width - w) / 2, (lay.height - h) / 2 - lay.size
            d.rounded_rectangle((x0, y0, x0 + w, y0 + h), radius=m, fill=(0, 0, 0, 190), outline=_EDGE, width=2)
            d.text((lay.width / 2, y0 + h * 0.32), "Touch to continue", font=big, fill=_TEXT, anchor="mm")
            d.text((lay.width / 2, y0 + h * 0.72), f"{state.countdown} s", font=small, fill=_TEXT, anchor="mm")
        if state.reconnecting:
            font = _font(self.font_path, max(14, self.caption_px // 2))
            d.text((lay.width - m, m), "reconnecting…", font=font, fill=_TEXT, anchor="ra", stroke_width=2,
                   stroke_fill=(0, 0, 0, 120))
        return np.asarray(img, np.uint8)
