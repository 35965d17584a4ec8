"""Base-colour textures as they travel inside a geometry payload: PNG bytes, checked before they are decoded.

A textured representation carries its own texture (``proto.geometry``'s ``tx``),
so a coarser level carries a smaller one and the byte gate, the store's byte
column and the client's cache budget count it with the geometry. PNG because it
is lossless (a checker's edges stay sharp at every level) and pillow reads and
writes it everywhere.

The payload declares the texture's size beside its bytes. The decoder reads the
PNG header first (pillow's ``Image.open`` reads only the header) and refuses an
image whose header disagrees with the declared size or exceeds
``MAX_TEXTURE_SIDE``, so a peer cannot make the client inflate more pixels than
the payload admits to.
"""

from __future__ import annotations

import io

import numpy as np

from .errors import ProtocolError

__all__ = ["MAX_TEXTURE_SIDE", "encode_texture", "decode_texture"]

#: Largest side a payload's texture may declare (and decode to), in pixels.
MAX_TEXTURE_SIDE = 4096


def encode_texture(rgb: np.ndarray) -> bytes:
    """(h, w, 3) uint8 RGB, rows top-down → PNG bytes. Raises ValueError on another shape or a side over the cap."""
    from PIL import Image

    a = np.asarray(rgb)
    if a.ndim != 3 or a.shape[2] != 3 or a.dtype != np.uint8 or min(a.shape[:2]) < 1:
        raise ValueError(f"texture must be (h, w, 3) uint8, got {a.dtype} {a.shape}")
    if max(a.shape[:2]) > MAX_TEXTURE_SIDE:
        raise ValueError(f"texture {a.shape[1]}×{a.shape[0]} has a side over {MAX_TEXTURE_SIDE} px")
    out = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(a), "RGB").save(out, format="PNG")
    return out.getvalue()


def decode_texture(png: bytes, width: int, height: int) -> np.ndarray:
    """PNG bytes declared ``width`` × ``height`` → (height, width, 3) uint8 RGB, rows top-down.

    Any defect — a declared side outside 1..``MAX_TEXTURE_SIDE``, bytes that are not a PNG, a header whose
    size is not the declared one, pixel data that does not decode (truncated, corrupt) — raises
    ``ProtocolError('bad_geometry', ...)``; no pixel is decoded before the header's size is checked.
    """
    from PIL import Image

    if not (1 <= width <= MAX_TEXTURE_SIDE and 1 <= height <= MAX_TEXTURE_SIDE):
        raise ProtocolError("bad_geometry", f"texture size {width}×{height} outside 1..{MAX_TEXTURE_SIDE} px a side")
    try:
        image = Image.open(io.BytesIO(png), formats=["PNG"])  # the header only
    except Exception as exc:  # pillow raises UnidentifiedImageError, SyntaxError, struct errors...
        raise ProtocolError("bad_geometry", f"texture is not a PNG ({type(exc).__name__}: {exc})") from None
    with image:
        if image.size != (width, height):
            raise ProtocolError("bad_geometry", f"texture declared {width}×{height} but its PNG is "
                                                f"{image.size[0]}×{image.size[1]}")
        try:
            image.load()
            rgb = np.asarray(image.convert("RGB"), np.uint8)
        except Exception as exc:  # truncated or corrupt pixel data
            raise ProtocolError("bad_geometry", f"texture PNG does not decode ({type(exc).__name__}: {exc})") from None
    return rgb.reshape(height, width, 3)
