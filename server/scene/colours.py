"""Colours carried from the source through LOD levels, proxies and geomorphs.

**Transfer.** Every level of an object — a decimation step, a ladder proxy
(pruned shells, block model, oriented box, hull), a level the source gave, an
HLOD proxy merged from many objects — takes its colours from a coloured
reference surface, the object's full-detail source mesh (``Appearance``):

- *face colours* (semantic surfaces, materials): each face takes the colour of
  the reference face nearest its centroid (libigl's AABB tree, as
  ``server.scene.lod`` measures errors with);
- *vertex colours* (painted meshes, scans): each vertex takes the reference
  colour at its closest surface point, interpolated in that face.

One rule for every way a level is made: the ladder's proxies and the HLOD's
merged ones have no collapse history an attribute could ride along, and a
simplifier that keeps attributes would pin every colour border. A block
model's top, made at the mean roof height, lands nearest the roof and is drawn
as one; its walls nearest the walls. All levels of an object take their colours
from the same reference, so a coarser level's colours agree with the finer
one's wherever their surfaces agree, which is what keeps a geomorph from
popping in colour.

**Split where colours meet.** The payload carries colours per vertex
(``proto.geometry``), so a face-coloured level has each vertex that faces of
different colours share split into one vertex per colour. A per-vertex colour
is then a per-face colour exactly, and the lit algorithm's smooth normals get a
crease where a roof meets a wall. The split costs vertices (a box building's 8
become 16), and the byte and vertex counts the cost model sees are the split
ones.

**Geomorphs.** Splits renumber vertices, so the morph maps are rewritten: a
fine vertex morphs to the copy of its target that has its own colour when the
coarser level has one, else to any copy. The client blends colours with
positions (``client.shading``): at weight 0 a morphing level shows the coarser
level's colours too.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import igl
import numpy as np

from proto.geometry import order_for_gpu

from .source import Mesh

__all__ = ["Appearance", "transfer", "split_by_colour", "coloured_levels", "coloured_mesh", "constant",
           "rewrite_morphs"]

Level = tuple[np.ndarray, np.ndarray]


@dataclass
class Appearance:
    """A coloured reference surface: positions (n, 3) float64, faces (m, 3) int64, and either
    face_colours (m, 3) uint8 or vertex_colours (n, 3) uint8."""

    positions: np.ndarray
    faces: np.ndarray
    face_colours: np.ndarray | None = None
    vertex_colours: np.ndarray | None = None

    @classmethod
    def of(cls, mesh: Mesh, origin: np.ndarray | None = None) -> "Appearance | None":
        """A source mesh's appearance (moved by −origin, as the builder recentres), None if it has no colours."""
        if not mesh.coloured or mesh.n_faces == 0:
            return None
        p = mesh.positions if origin is None else mesh.positions - np.asarray(origin, np.float64)
        return cls(p, mesh.faces, mesh.face_colours, mesh.vertex_colours)

    @classmethod
    def of_level(cls, positions: np.ndarray, faces: np.ndarray, colours: np.ndarray, by_face: bool) -> "Appearance":
        """A coloured level (``coloured_levels``' output) as a reference: by_face — its colours are per face
        (split), so each face takes its first corner's."""
        faces = np.asarray(faces, np.int64)
        if by_face:
            return cls(positions, faces, face_colours=colours[faces[:, 0]])
        return cls(positions, faces, vertex_colours=colours)

    @property
    def by_face(self) -> bool:
        return self.face_colours is not None

    @staticmethod
    def merge(parts: Sequence["Appearance"]) -> "Appearance | None":
        """One reference from several (an HLOD node's objects); per face unless some part is per vertex."""
        parts = [a for a in parts if a is not None]
        if not parts:
            return None
        offsets = np.cumsum([0] + [a.positions.shape[0] for a in parts])[:-1]
        p = np.concatenate([a.positions for a in parts])
        f = np.concatenate([a.faces + o for a, o in zip(parts, offsets)])
        if all(a.by_face for a in parts):
            return Appearance(p, f, face_colours=np.concatenate([a.face_colours for a in parts]))
        vc = []
        for a in parts:  # a per-face part lends each vertex the colour of a face that uses it
            if a.by_face:
                c = np.zeros((a.positions.shape[0], 3), np.uint8)
                c[a.faces.ravel()] = np.repeat(a.face_colours, 3, axis=0)
                vc.append(c)
            else:
                vc.append(a.vertex_colours)
        return Appearance(p, f, vertex_colours=np.concatenate(vc))


def constant(n_faces: int, rgb: Sequence[int]) -> np.ndarray:
    """(n_faces, 3) uint8 of one colour."""
    return np.tile(np.asarray(rgb, np.uint8).reshape(1, 3), (int(n_faces), 1))


def _closest(ref: Appearance, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(face index (k,) int64, closest point (k, 3)) on the reference surface for each point."""
    _, face, closest = igl.point_mesh_squared_distance(
        np.ascontiguousarray(points, np.float64), np.ascontiguousarray(ref.positions, np.float64),
        np.ascontiguousarray(ref.faces, np.int64))
    return np.asarray(face, np.int64).reshape(-1), np.asarray(closest, np.float64).reshape(-1, 3)


def transfer(ref: Appearance, positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Colours for a mesh from the reference: (m, 3) uint8 per face if the reference is per face,
    else (n, 3) uint8 per vertex (see the module docstring).

    positions : (n, 3) float; faces : (m, 3) int
    """
    p = np.asarray(positions, np.float64)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    if ref.by_face:
        if f.shape[0] == 0:
            return np.zeros((0, 3), np.uint8)
        face, _ = _closest(ref, p[f].mean(axis=1))
        return ref.face_colours[face]
    face, c = _closest(ref, p)
    tri = ref.positions[ref.faces[face]]  # (n, 3 corners, 3)
    w = _barycentric(c, tri)
    colours = (w[:, :, None] * ref.vertex_colours[ref.faces[face]].astype(np.float64)).sum(axis=1)
    return np.clip(np.rint(colours), 0, 255).astype(np.uint8)


def _barycentric(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(k, 3) barycentric weights of points p (k, 3) in triangles tri (k, 3, 3); degenerate ones: a corner."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    v0, v1, v2 = b - a, c - a, p - a
    d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
    d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
    den = d00 * d11 - d01 * d01
    ok = np.abs(den) > 1e-30
    den = np.where(ok, den, 1.0)
    v = np.where(ok, (d11 * d20 - d01 * d21) / den, 0.0)
    w = np.where(ok, (d00 * d21 - d01 * d20) / den, 0.0)
    out = np.column_stack([1.0 - v - w, v, w])
    return np.clip(out, 0.0, 1.0) / np.maximum(np.clip(out, 0.0, 1.0).sum(1, keepdims=True), 1e-30)


def _packed(rgb: np.ndarray) -> np.ndarray:
    rgb = np.asarray(rgb, np.int64)
    return (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]


def split_by_colour(positions: np.ndarray, faces: np.ndarray, face_colours: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Split the vertices that faces of different colours share: one copy per (vertex, colour).

    positions : (n, 3); faces : (m, 3) int; face_colours : (m, 3) uint8
    Returns (positions (n', 3), faces (m, 3) int64, colours (n', 3) uint8, source (n',) int64: the
    vertex each copy was made from). Copies come in (vertex, colour) order.
    """
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    key = f * (1 << 24) + _packed(face_colours)[:, None]
    unique, inverse = np.unique(key.ravel(), return_inverse=True)
    source = unique >> 24
    rgb = unique & 0xFFFFFF
    colours = np.column_stack([(rgb >> 16) & 255, (rgb >> 8) & 255, rgb & 255]).astype(np.uint8)
    return np.asarray(positions)[source], inverse.reshape(-1, 3).astype(np.int64), colours, source


def coloured_levels(ref: Appearance, levels: Sequence[Level], morphs: Sequence[np.ndarray | None]
                    ) -> tuple[list[Level], list[np.ndarray | None], list[np.ndarray]]:
    """An object's chain with colours: (levels, morph maps, per-vertex colours (n_k, 3) uint8).

    levels : [(positions (n_k, 3), faces (m_k, 3)), ...] coarsest → finest in GPU order, as
             ``server.scene.lod.Chain`` keeps them; morphs: ``Chain.morph`` (None entries stay None)
    A per-vertex reference leaves levels and maps as they are; a per-face one splits each level
    where colours meet and returns it in GPU order with its maps rewritten (module docstring).
    """
    if not ref.by_face:
        return list(levels), list(morphs), [transfer(ref, p, f) for p, f in levels]
    out_levels: list[Level] = []
    colours: list[np.ndarray] = []
    sources: list[np.ndarray] = []
    for p, f in levels:
        sp, sf, sc, src = split_by_colour(p, f, transfer(ref, p, f))
        gp, gf, new_of_old = order_for_gpu(sp, sf)
        old_of_new = np.empty(gp.shape[0], np.int64)
        old_of_new[new_of_old] = np.arange(new_of_old.size)  # a split mesh uses every vertex
        out_levels.append((gp, gf))
        colours.append(sc[old_of_new])
        sources.append(src[old_of_new])
    return out_levels, rewrite_morphs(morphs, sources, colours), colours


def rewrite_morphs(morphs: Sequence[np.ndarray | None], sources: Sequence[np.ndarray],
                   colours: Sequence[np.ndarray]) -> list[np.ndarray | None]:
    """Morph maps onto split levels: a fine vertex morphs to the copy of its target that has its own colour
    when the coarser level has one, else to the target's first copy.

    morphs  : per level, None or the (n_k,) map onto level k−1's vertices before either was split
    sources : per level, (n'_k,) int64 — the unsplit vertex each split vertex was made from
    colours : per level, (n'_k, 3) uint8 per split vertex
    Returns per level None or the (n'_k,) map onto level k−1's split vertices.
    """
    out_morphs: list[np.ndarray | None] = [None] * len(sources)
    for k in range(1, len(sources)):
        m = morphs[k]
        if m is None:
            continue
        target = np.asarray(m, np.int64)[sources[k]]  # the coarser level's vertex, before its split
        coarse_key = sources[k - 1] * (1 << 24) + _packed(colours[k - 1])
        order = np.argsort(coarse_key, kind="stable")
        sorted_key = coarse_key[order]
        want = target * (1 << 24) + _packed(colours[k])
        at = np.minimum(np.searchsorted(sorted_key, want), sorted_key.size - 1)
        same = sorted_key[at] == want
        first = np.searchsorted(sorted_key, target * (1 << 24))  # the first copy of the target
        out_morphs[k] = order[np.where(same, at, first)]
    return out_morphs


def coloured_mesh(ref: Appearance, positions: np.ndarray, faces: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One mesh with colours from the reference (an HLOD proxy): (positions, faces, (n', 3) uint8 per vertex),
    split where colours meet when the reference is per face."""
    if not ref.by_face:
        return np.asarray(positions), np.asarray(faces), transfer(ref, positions, faces)
    p, f, c, _ = split_by_colour(positions, faces, transfer(ref, positions, faces))
    return p, f, c
