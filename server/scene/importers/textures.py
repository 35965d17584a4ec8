"""Texture images as one colour each: the mean of the image's pixels, until textures are drawn.

The payload carries one colour per face (``server.scene.colours``), so a textured
surface of CityGML (``ParameterizedTexture``) or CityJSON (``appearance.textures``)
is drawn in its image's mean colour — a façade photograph becomes the colour one
sees from across the street, which is what a city read from afar shows. Pixels are
weighted by their alpha, so the transparent padding of a texture atlas does not
grey the mean.

An image that is missing, remote or unreadable is not an error: the file still
builds and those surfaces keep their semantic colour. It is logged once per image
(``logging``, this module's logger), not once per surface that uses it.
"""

from __future__ import annotations

import logging
from pathlib import Path
from urllib.parse import unquote, urlparse

import numpy as np
from PIL import Image, UnidentifiedImageError

__all__ = ["TextureColours", "mean_colour"]

log = logging.getLogger(__name__)

# Larger images are box-reduced to about this many pixels a side first: the mean barely
# moves, and a city's worth of façade photographs would otherwise be decoded at full size.
_SIDE = 256


def mean_colour(image: Image.Image) -> tuple[int, int, int]:
    """The alpha-weighted mean RGB8 of ``image`` (plain mean where every pixel is transparent)."""
    if image.mode == "P" or image.mode not in ("RGB", "RGBA"):
        image = image.convert("RGBA")
    factor = max(image.size) // _SIDE
    if factor > 1:
        image = image.reduce(factor)
    pixels = np.asarray(image, np.float64).reshape(-1, len(image.getbands()))
    rgb = pixels[:, :3]
    alpha = pixels[:, 3] if pixels.shape[1] == 4 else None
    if alpha is not None and alpha.sum() > 0:
        mean = (rgb * alpha[:, None]).sum(axis=0) / alpha.sum()
    else:
        mean = rgb.mean(axis=0)
    r, g, b = np.clip(np.rint(mean), 0, 255).astype(int).tolist()
    return r, g, b


class TextureColours:
    """Image references of one source file → their mean colours, each image read once.

    source : the file whose image references these are; relative ones are resolved against its folder
    """

    def __init__(self, source: Path) -> None:
        self.source = Path(source)
        self._colour: dict[str, tuple[int, int, int] | None] = {}

    def colour(self, uri: str) -> tuple[int, int, int] | None:
        """The mean RGB8 of the image ``uri`` names, or None (warned once) if it cannot be read."""
        if uri not in self._colour:
            self._colour[uri] = self._read(uri)
        return self._colour[uri]

    def _read(self, uri: str) -> tuple[int, int, int] | None:
        path = self._local(uri)
        if path is None:
            log.warning("%s: texture %r is not a local file; its surfaces keep their semantic colours",
                        self.source, uri)
            return None
        try:
            with Image.open(path) as image:
                image.draft("RGB", (_SIDE, _SIDE))  # a JPEG decodes at a reduced scale, cheaply
                return mean_colour(image)
        except FileNotFoundError:
            reason = "no such file"
        except (OSError, UnidentifiedImageError, ValueError, Image.DecompressionBombError) as exc:
            reason = str(exc) or type(exc).__name__
        log.warning("%s: texture %r (%s) cannot be read: %s; its surfaces keep their semantic colours",
                    self.source, uri, path, reason)
        return None

    def _local(self, uri: str) -> Path | None:
        """The file ``uri`` names: a path relative to the source's folder, an absolute path or a
        ``file:`` URI; None for anything remote (the build reads no network)."""
        text = uri.strip()
        parsed = urlparse(text)
        if parsed.scheme == "file":
            return Path(unquote(parsed.path))
        if len(parsed.scheme) > 1:  # http:, https:, …; a one-letter scheme is a Windows drive
            return None
        path = self.source.parent / text
        if not path.exists() and "\\" in text:  # written on Windows
            path = self.source.parent / text.replace("\\", "/")
        return path
