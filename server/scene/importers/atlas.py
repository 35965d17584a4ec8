"""One texture per object: the images its surfaces use, packed into an atlas, and its faces' UVs remapped.

A ``Mesh`` carries one texture (``server.scene.source``), but a CityGML or CityJSON
building names an image per surface — a photograph per façade, another for the roof.
So each object gets one atlas image: its images, each at most ``IMAGE_SIDE`` pixels a
side (the reader already reduced them, ``server.scene.importers.textures``), are packed
by shelf packing (tallest first, left to right, a new shelf when a row is full) into an
atlas at most ``ATLAS_SIDE`` pixels a side — when they do not fit, all of them are
scaled down together until they do. Each image sits inside a ``GAP``-pixel border of
its own edge pixels, so a sample filtered at its edge does not reach the neighbour's.

**Repeating textures cannot repeat inside an atlas.** Texture coordinates outside
[0, 1] tile an image in the source; in an atlas they would run into the neighbours.
So each *group* of faces (a source polygon, whose triangles must stay in one piece) is
moved by its integer offset — the floor of its smallest u and of its smallest v — and
its UVs are then clamped to [0, 1]: a surface that tiles its image once, wherever in
UV space, is drawn exactly; one that tiles it several times shows one tile, stretched
where the clamp bites. Inside its rectangle a UV of 0 or 1 lands on the centre of the
image's edge texel, not its outer border, so no sample straddles two images.

**Surfaces without an image in a textured object** keep their face colour for the
flat and lit algorithms; for the textured one, each distinct colour gets a
``PATCH`` × ``PATCH`` pixel patch of that colour in the atlas, and every corner of such
a face the patch's centre. A patch, not one texel, because every coarser level's texture
is a reduction of the atlas (``server.scene.texcoords``), and a lone texel would be
averaged with its neighbours at once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from PIL import Image

from .textures import IMAGE_SIDE

__all__ = ["ATLAS_SIDE", "GAP", "IMAGE_SIDE", "PATCH", "Atlas", "atlas_uvs", "build_atlas", "object_texture",
           "shelf_pack", "split_by_uv"]

#: The largest side of an object's atlas.
ATLAS_SIDE = 2048
#: Pixels of edge-replicated border around each image in the atlas.
GAP = 2
#: The side of the patch a flat colour gets in the atlas.
PATCH = 4
# UVs closer than this are one UV when vertices are split; a tolerance for "integer" offsets.
_UV_STEP = 1.0 / (1 << 20)
_EPS = 1e-6


def shelf_pack(sizes: np.ndarray, width: int) -> tuple[np.ndarray, int]:
    """Shelf packing of rectangles into a strip ``width`` pixels wide.

    sizes : (k, 2) int (w, h) of each rectangle, each w ≤ width
    Returns (offsets (k, 2) int64 (x, y) of each rectangle's top-left corner, the strip's height used).
    Rectangles go tallest first, left to right along a shelf; a new shelf starts below when the next
    one does not fit beside the last.
    """
    sizes = np.asarray(sizes, np.int64).reshape(-1, 2)
    if sizes.size and sizes[:, 0].max() > width:
        raise ValueError(f"a rectangle {int(sizes[:, 0].max())} wide does not fit a strip {width} wide")
    offsets = np.zeros_like(sizes)
    x = y = shelf = 0
    for i in np.argsort(-sizes[:, 1], kind="stable").tolist():  # one step per image of one object
        w, h = int(sizes[i, 0]), int(sizes[i, 1])
        if x + w > width:
            y, x, shelf = y + shelf, 0, 0
        offsets[i] = (x, y)
        x += w
        shelf = max(shelf, h)
    return offsets, y + shelf


@dataclass
class Atlas:
    """image : (H, W, 3) uint8 rows top-down; rects : (k, 4) int64 (x, y, w, h) of each packed image in
    pixels, top-left origin, border excluded."""

    image: np.ndarray
    rects: np.ndarray


def _layout(sizes: np.ndarray, side: int) -> tuple[np.ndarray, np.ndarray, int, int] | None:
    """(inner sizes, offsets, width, height) packing ``sizes`` with their borders, or None if over ``side``."""
    padded = sizes + 2 * GAP
    if padded[:, 0].max() > side:
        return None
    width = int(min(side, max(padded[:, 0].max(), math.ceil(math.sqrt(float((padded.prod(axis=1)).sum()))))))
    offsets, height = shelf_pack(padded, width)
    if height > side:
        return None
    return sizes, offsets, width, height


def build_atlas(images: Sequence[np.ndarray], side: int = ATLAS_SIDE) -> Atlas:
    """Pack ``images`` ((h_i, w_i, 3) uint8 each) into one atlas at most ``side`` pixels a side.

    When they do not fit, every image is scaled by the same factor (box filter) until they do, so the
    texel density stays even across the object's surfaces; ``ValueError`` when even at one pixel each
    they do not.
    """
    if not images:
        raise ValueError("an atlas needs at least one image")
    full = np.array([(im.shape[1], im.shape[0]) for im in images], np.int64)
    scale = 1.0
    while True:
        sizes = np.maximum(1, np.floor(full * scale)).astype(np.int64)
        layout = _layout(sizes, side)
        if layout is not None:
            break
        if (sizes == 1).all():
            raise ValueError(f"{len(images)} images do not fit an atlas {side} px a side")
        scale *= 0.8
    sizes, offsets, width, height = layout
    atlas = np.zeros((height, width, 3), np.uint8)
    for im, (w, h), (x, y) in zip(images, sizes.tolist(), offsets.tolist()):
        if (w, h) != (im.shape[1], im.shape[0]):
            im = np.asarray(Image.fromarray(np.ascontiguousarray(im, np.uint8), "RGB")
                            .resize((w, h), Image.Resampling.BOX), np.uint8)
        atlas[y:y + h + 2 * GAP, x:x + w + 2 * GAP] = np.pad(im, ((GAP, GAP), (GAP, GAP), (0, 0)), mode="edge")
    rects = np.column_stack([offsets + GAP, sizes]).astype(np.int64)
    return Atlas(atlas, rects)


def atlas_uvs(uv: np.ndarray, item: np.ndarray, group: np.ndarray, atlas: Atlas) -> np.ndarray:
    """(m, 3, 2) float64: each face corner's UV in the atlas (OpenGL's: v = 0 at the atlas's bottom row).

    uv    : (m, 3, 2) float the corners' UVs in their own image (OpenGL's convention), any range
    item  : (m,) int the rectangle of ``atlas.rects`` each face's image went to
    group : (m,) int the faces wrapped together (a source polygon): each group is moved by the floor of
            its smallest u and v, then clamped to [0, 1] (module docstring)
    """
    uv = np.asarray(uv, np.float64).reshape(-1, 3, 2)
    item = np.asarray(item, np.int64).reshape(-1)
    _, group = np.unique(np.asarray(group, np.int64).reshape(-1), return_inverse=True)
    low = np.full((int(group.max(initial=-1)) + 1, 2), np.inf)
    np.minimum.at(low, group, uv.min(axis=1))
    offset = np.floor(low + _EPS)
    local = np.clip(uv - offset[group][:, None, :], 0.0, 1.0)
    x, y, w, h = (atlas.rects[item][:, k, None].astype(np.float64) for k in range(4))
    height, width = atlas.image.shape[:2]
    px = x + 0.5 + local[:, :, 0] * (w - 1)
    py = y + 0.5 + (1.0 - local[:, :, 1]) * (h - 1)  # pixel rows from the top
    return np.stack([px / width, 1.0 - py / height], axis=2)


def object_texture(face_image: np.ndarray, face_uv: np.ndarray, face_group: np.ndarray, face_colour: np.ndarray,
                   images: Sequence[np.ndarray | None]) -> tuple[np.ndarray, np.ndarray] | None:
    """One object's atlas and its faces' UVs in it; None when no face has a readable image.

    face_image  : (m,) int index into ``images`` of each face's image, −1 for none
    face_uv     : (m, 3, 2) float its corners' UVs in that image (NaN where the source gives none)
    face_group  : (m,) int the source polygon of each face (wrapped together, ``atlas_uvs``)
    face_colour : (m, 3) uint8 each face's colour: faces without an image are drawn in a patch of it
    images      : per image, (h, w, 3) uint8 or None where it could not be read
    Returns (atlas (H, W, 3) uint8, uv (m, 3, 2) float64).
    """
    face_image = np.asarray(face_image, np.int64).reshape(-1)
    face_uv = np.asarray(face_uv, np.float64).reshape(-1, 3, 2)
    readable = np.array([im is not None for im in images] + [False], bool)
    textured = readable[face_image] & np.isfinite(face_uv).all(axis=(1, 2))
    if not textured.any():
        return None
    used, item = np.unique(face_image[textured], return_inverse=True)
    colours, patch = np.unique(np.asarray(face_colour, np.uint8).reshape(-1, 3)[~textured], axis=0,
                               return_inverse=True)
    pictures = [images[i] for i in used.tolist()] + [np.broadcast_to(c, (PATCH, PATCH, 3)) for c in colours]
    try:
        atlas = build_atlas(pictures)
    except ValueError:  # more images than an atlas holds: the object keeps its colours
        return None
    items = np.empty(face_image.shape[0], np.int64)
    items[textured] = item
    items[~textured] = len(used) + patch.reshape(-1)
    uv = np.where(textured[:, None, None], face_uv, 0.5)
    # a patch face wraps alone: its 0.5 must not move the offset of a textured face of its polygon
    group = np.where(textured, np.asarray(face_group, np.int64).reshape(-1), -1 - items)
    return atlas.image, atlas_uvs(uv, items, group, atlas)


def split_by_uv(vertex: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-vertex UVs from per-corner ones: a vertex whose corners take different UVs is split.

    vertex : (m, 3) int the vertex of each face corner; uv : (m, 3, 2) float their UVs
    Returns (source (n,) int64 the vertex each new vertex copies, faces (m, 3) int64, uv (n, 2) float64).
    """
    vertex = np.asarray(vertex, np.int64).reshape(-1)
    flat = np.asarray(uv, np.float64).reshape(-1, 2)
    key = np.column_stack([vertex, np.rint(flat / _UV_STEP).astype(np.int64)])
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return vertex[first], inverse.reshape(-1, 3).astype(np.int64), flat[first]
