"""Texture images of CityGML (``ParameterizedTexture``) and CityJSON (``appearance.textures``): pixels and mean colour.

A textured surface is drawn with its image (``server.scene.importers.atlas`` packs an
object's images into one atlas), and its face colour — what the flat and lit
algorithms draw — is the image's mean colour: a façade photograph becomes the colour
one sees from across the street, which is what a city read from afar shows. Pixels are
weighted by their alpha, so the transparent padding of a texture atlas does not grey
the mean; the image handed out has its transparent pixels filled with that mean, for
the same reason.

Images are read at most ``IMAGE_SIDE`` pixels a side (a façade photograph is larger
than a level's texture ever is), and only the last few decoded ones are kept: a city
names thousands of images, each used by one or a few buildings, and a city's worth of
pixels would not fit in memory. Mean colours are kept for every image.

An image that is missing, remote or unreadable is not an error: the file still
builds and those surfaces keep their semantic colour. It is logged once per image
(``logging``, this module's logger), not once per surface that uses it.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from pathlib import Path
from urllib.parse import unquote, urlparse

import numpy as np
from PIL import Image, UnidentifiedImageError

__all__ = ["IMAGE_SIDE", "TextureImages", "mean_colour"]

log = logging.getLogger(__name__)

# Larger images are box-reduced to about this many pixels a side first: the mean barely
# moves, and a city's worth of façade photographs would otherwise be decoded at full size.
_SIDE = 256
#: The largest side of an image as it is handed to the atlas.
IMAGE_SIDE = 512
# Decoded images kept for reuse: an object's images are usually its own, so a few suffice.
_KEEP = 16


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


class TextureImages:
    """Image references of one source file → their pixels and mean colours, each image's colour read once.

    source : the file whose image references these are; relative ones are resolved against its folder
    """

    def __init__(self, source: Path) -> None:
        self.source = Path(source)
        self._colour: dict[str, tuple[int, int, int] | None] = {}
        self._pixels: OrderedDict[str, np.ndarray] = OrderedDict()

    def colour(self, uri: str) -> tuple[int, int, int] | None:
        """The mean RGB8 of the image ``uri`` names, or None (warned once) if it cannot be read."""
        if uri not in self._colour:
            self._load(uri)
        return self._colour[uri]

    def image(self, uri: str) -> np.ndarray | None:
        """The image ``uri`` names as (h, w, 3) uint8 rows top-down, at most ``IMAGE_SIDE`` a side, transparent
        pixels filled with its mean colour; None (warned once) if it cannot be read."""
        if uri in self._pixels:
            self._pixels.move_to_end(uri)
            return self._pixels[uri]
        if uri in self._colour and self._colour[uri] is None:
            return None
        return self._load(uri)

    def _load(self, uri: str) -> np.ndarray | None:
        read = self._read(uri)
        if read is None:
            self._colour[uri] = None
            return None
        self._colour[uri], pixels = read
        self._pixels[uri] = pixels
        while len(self._pixels) > _KEEP:
            self._pixels.popitem(last=False)
        return pixels

    def _read(self, uri: str) -> tuple[tuple[int, int, int], np.ndarray] | None:
        path = self._local(uri)
        if path is None:
            log.warning("%s: texture %r is not a local file; its surfaces keep their semantic colours",
                        self.source, uri)
            return None
        try:
            with Image.open(path) as image:
                image.draft("RGB", (IMAGE_SIDE, IMAGE_SIDE))  # a JPEG decodes at a reduced scale, cheaply
                image = image.convert("RGBA")
                image.thumbnail((IMAGE_SIDE, IMAGE_SIDE), Image.Resampling.BOX)
                colour = mean_colour(image)
                rgba = np.asarray(image, np.uint8)
                rgb = rgba[:, :, :3].copy()
                rgb[rgba[:, :, 3] == 0] = colour
                return colour, rgb
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
