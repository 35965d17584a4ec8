"""Texture coordinates and base-colour textures carried from the source through every LOD level.

**UVs.** Every level of a textured object (a decimation step, a ladder proxy,
a level the source gave) takes its UVs from the object's full-detail source
mesh (``UVReference``), as its colours are taken (``server.scene.colours``):
each face of the level finds the reference face nearest its centroid (libigl's
AABB tree) and its three corners take the UVs of that face's affine map,
extended over the face's plane (barycentric weights, not clamped). Per face,
not per vertex: a vertex where UV charts meet (a box's edge, an atlas seam) has
one UV in each chart, and interpolating one UV per vertex would smear the whole
atlas across the faces that straddle the seam. A planar chart with an affine
map (a wall, a floor) gives every corner the same UV from whichever of its
faces it is reached, so the seam splits only where charts really meet.

**Split where UVs or colours meet.** The payload carries UVs per vertex
(``proto.geometry``), so a vertex whose corners take different UVs or colours
is split into one vertex per (UV, colour); the morph maps are rewritten as for
colours (``server.scene.colours.rewrite_morphs``). UVs are compared at 2⁻¹⁶,
finer than a texel of the largest texture a level carries.

**Textures per level.** Each level carries its own texture (``level_textures``):
a square power-of-two side, the finest level's the image's larger side rounded
to the nearest power of two and at most ``FINEST_SIDE``, each coarser level half
the side of the next finer and never below ``COARSEST_SIDE``. Square, so the
client keeps every texture of one side in one texture array (``client.textures``);
the UVs are normalised, so the image's aspect comes back on the surface. A
coarser level, drawn smaller on screen, sends fewer bytes, which its cost and
the byte gate count (the texture is inside its payload).

HLOD proxies merged from many objects carry colours only: their objects'
textures would need an atlas, and a proxy is drawn where a texel is smaller
than a pixel anyway.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import igl
import numpy as np

from proto.geometry import order_for_gpu

from .colours import Appearance, _barycentric, rewrite_morphs, transfer
from .source import Mesh

__all__ = ["UVReference", "FINEST_SIDE", "COARSEST_SIDE", "corner_uvs", "level_sides", "level_textures",
           "textured_levels"]

#: Largest texture side any level carries (the finest level's, at most).
FINEST_SIDE = 1024
#: Smallest texture side a level carries: below it a texture says no more than a colour.
COARSEST_SIDE = 8
#: UVs closer than this are one UV when a level's vertices are split.
_UV_STEP = 1.0 / 65536.0

Level = tuple[np.ndarray, np.ndarray]


@dataclass
class UVReference:
    """A textured reference surface: positions (n, 3) float64, faces (m, 3) int64, uv (n, 2) float64 and the
    source's texture (h, w, 3) uint8 rows top-down."""

    positions: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    texture: np.ndarray

    @classmethod
    def of(cls, mesh: Mesh, origin: np.ndarray | None = None) -> "UVReference | None":
        """A source mesh's UVs and texture (moved by −origin, as the builder recentres); None if it has none."""
        if not mesh.textured or mesh.n_faces == 0:
            return None
        p = mesh.positions if origin is None else mesh.positions - np.asarray(origin, np.float64)
        return cls(p, mesh.faces, mesh.uv, mesh.texture)


def _affine_weights(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(k, 3) barycentric weights of points p (k, 3) projected on the planes of triangles tri (k, 3, 3), not
    clamped (a point outside the triangle extends its affine map); degenerate triangles: clamped weights."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    v0, v1, v2 = b - a, c - a, p - a
    d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
    d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
    den = d00 * d11 - d01 * d01
    ok = np.abs(den) > 1e-12 * np.maximum(d00 * d11, 1e-300)
    safe = np.where(ok, den, 1.0)
    v = (d11 * d20 - d01 * d21) / safe
    w = (d00 * d21 - d01 * d20) / safe
    out = np.column_stack([1.0 - v - w, v, w])
    if not ok.all():
        out[~ok] = _barycentric(p[~ok], tri[~ok])
    return out


def corner_uvs(ref: UVReference, positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(m, 3, 2) float64: the UV of each face corner, from the reference face nearest the face's centroid.

    positions : (n, 3) float; faces : (m, 3) int
    """
    p = np.asarray(positions, np.float64)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    if f.shape[0] == 0:
        return np.zeros((0, 3, 2))
    _, near, _ = igl.point_mesh_squared_distance(np.ascontiguousarray(p[f].mean(axis=1)),
                                                 np.ascontiguousarray(ref.positions, np.float64),
                                                 np.ascontiguousarray(ref.faces, np.int64))
    near = np.asarray(near, np.int64).reshape(-1)
    tri = ref.positions[ref.faces[near]]  # (m, 3, 3)
    corners = p[f].reshape(-1, 3)  # (3m, 3): face i's corners at 3i..3i+2
    w = _affine_weights(corners, np.repeat(tri, 3, axis=0))  # (3m, 3)
    uv = (w[:, :, None] * np.repeat(ref.uv[ref.faces[near]], 3, axis=0)).sum(axis=1)
    return uv.reshape(-1, 3, 2)


def level_sides(texture_shape: Sequence[int], n_levels: int) -> list[int]:
    """The texture side of each of ``n_levels`` levels, coarsest first (module docstring).

    texture_shape : the source texture's (h, w, ...)
    """
    larger = max(int(texture_shape[0]), int(texture_shape[1]), 1)
    finest = 1 << max(0, round(math.log2(larger)))
    finest = min(FINEST_SIDE, max(COARSEST_SIDE, finest))
    return [max(COARSEST_SIDE, finest >> (n_levels - 1 - k)) for k in range(n_levels)]


def level_textures(texture: np.ndarray, n_levels: int) -> list[np.ndarray]:
    """Each level's texture, coarsest first: (s_k, s_k, 3) uint8 rows top-down, s_k from ``level_sides``.

    Each is resampled from the source image (box filter where it shrinks, which averages whole texels;
    Lanczos where an axis grows), so no level inherits another's rounding.
    """
    from PIL import Image

    image = Image.fromarray(np.ascontiguousarray(texture, np.uint8), "RGB")
    out: list[np.ndarray] = []
    made: dict[int, np.ndarray] = {}
    for side in level_sides(texture.shape, n_levels):
        if side not in made:
            shrinks = side <= min(image.size)
            made[side] = np.asarray(image.resize((side, side), Image.Resampling.BOX if shrinks
                                                 else Image.Resampling.LANCZOS), np.uint8)
        out.append(made[side])
    return out


def _packed(rgb: np.ndarray) -> np.ndarray:
    rgb = np.asarray(rgb, np.int64)
    return (rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]


def textured_levels(ref: Appearance | None, uvref: UVReference, levels: Sequence[Level],
                    morphs: Sequence[np.ndarray | None]
                    ) -> tuple[list[Level], list[np.ndarray | None], list[np.ndarray] | None, list[np.ndarray],
                               list[np.ndarray]]:
    """An object's chain with UVs, textures and (when ``ref`` is given) colours.

    levels : [(positions (n_k, 3), faces (m_k, 3)), ...] coarsest → finest in GPU order
             (``server.scene.lod.Chain``); morphs: ``Chain.morph``
    Returns (levels split where UVs or colours meet, in GPU order; their morph maps; per-vertex colours
    (n'_k, 3) uint8 per level, or None without ``ref``; per-vertex UVs (n'_k, 2) float64; textures
    (s_k, s_k, 3) uint8), every list coarsest first.
    """
    out_levels: list[Level] = []
    colours: list[np.ndarray] = []
    uvs: list[np.ndarray] = []
    sources: list[np.ndarray] = []
    for p, f in levels:
        f = np.asarray(f, np.int64).reshape(-1, 3)
        uv = corner_uvs(uvref, p, f)  # (m, 3, 2)
        if ref is None:
            rgb = np.zeros((f.shape[0], 3, 3), np.uint8)
        elif ref.by_face:
            rgb = np.repeat(transfer(ref, p, f)[:, None, :], 3, axis=1)
        else:
            rgb = transfer(ref, p, f)[f]
        key = np.column_stack([f.reshape(-1), _packed(rgb).reshape(-1),
                               np.rint(uv.reshape(-1, 2) / _UV_STEP).astype(np.int64)])
        _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
        src = f.reshape(-1)[first]
        sp, sf = np.asarray(p)[src], inverse.reshape(-1, 3).astype(np.int64)
        gp, gf, new_of_old = order_for_gpu(sp, sf)
        old_of_new = np.empty(gp.shape[0], np.int64)
        old_of_new[new_of_old] = np.arange(new_of_old.size)  # a split mesh uses every vertex
        out_levels.append((gp, gf))
        colours.append(rgb.reshape(-1, 3)[first][old_of_new])
        uvs.append(uv.reshape(-1, 2)[first][old_of_new])
        sources.append(src[old_of_new])
    textures = level_textures(uvref.texture, len(levels))
    return (out_levels, rewrite_morphs(morphs, sources, colours), colours if ref is not None else None, uvs,
            textures)
