"""What the mesh shaders read that the CPU works out: vertex records, normals, tints, the key light.

A representation's vertices are stored once, at upload, as ``VERTEX`` records:
its position, its morph target (the position on the next coarser level; the
position itself until one is set), the smooth normals at both, so the lit
algorithm morphs its shading along with the shape, and the colours at both
(the payload's, ``proto.geometry``), so a morph blends colours too, and its texture
coordinates (zero where the representation has no texture). Normals are packed in
bytes (n·½+½, the shader's normalised ``4f1``); a colour's fourth byte says whether
the vertex has one (255) or takes its object's tint (0). Everything here works on
whole meshes (numpy, and one compiled kernel for the normals), no GL: the renderer writes the
results into its arenas.
"""

from __future__ import annotations

import colorsys

import numba
import numpy as np

from proto.camera import cross3

__all__ = ["VERTEX", "vertex_records", "pack_colours", "smooth_normals", "target_normals", "pack_normals",
           "object_tint", "packed_tint", "key_light", "morph_targets"]

#: Vertex record: world position, morph target (= position until set), smooth normal and the target's normal
#: (n·½+½ in normalised bytes, 4th byte padding), colour and the target's colour (RGB, 4th byte 255 when the
#: vertex has a colour, 0 when it takes the object's tint), texture coordinates (u, v; v up, float: a texture
#: may repeat). 48 bytes. A morphing vertex keeps its own UV: every level's UVs come from the same source map
#: (``server.scene.texcoords``), so the coarser level's agree with them where the surfaces agree.
VERTEX = np.dtype([("position", "<f4", 3), ("target", "<f4", 3), ("normal", "u1", 4), ("target_normal", "u1", 4),
                   ("colour", "u1", 4), ("target_colour", "u1", 4), ("uv", "<f4", 2)])


def pack_colours(colours: np.ndarray | None, n: int) -> np.ndarray:
    """(n, 4) uint8: RGB colours with 255 in the fourth byte, or all zero (the object's tint) for None.

    colours : (n, 3) uint8 or None. Raises ValueError on another shape.
    """
    packed = np.zeros((n, 4), np.uint8)
    if colours is not None:
        c = np.asarray(colours)
        if c.shape != (n, 3):
            raise ValueError(f"colours must be ({n}, 3), got {c.shape}")
        packed[:, :3] = c
        packed[:, 3] = 255
    return packed


def vertex_records(positions: np.ndarray, indices: np.ndarray, colours: np.ndarray | None = None,
                   uv: np.ndarray | None = None) -> np.ndarray:
    """(nv,) ``VERTEX`` records of a mesh without a morph target (the target is the position itself).

    positions : (nv, 3) float32; indices : (nf, 3) uint32, every entry < nv
    colours   : (nv, 3) uint8 per vertex, or None (drawn in the object's tint)
    uv        : (nv, 2) float texture coordinates, or None (no texture: zeros)
    """
    records = np.empty(positions.shape[0], VERTEX)
    records["position"] = positions
    records["target"] = positions
    records["normal"] = pack_normals(smooth_normals(positions, indices))
    records["target_normal"] = records["normal"]
    records["colour"] = pack_colours(colours, positions.shape[0])
    records["target_colour"] = records["colour"]
    if uv is None:
        records["uv"] = 0.0
    else:
        uv = np.asarray(uv)
        if uv.shape != (positions.shape[0], 2):
            raise ValueError(f"uv must be ({positions.shape[0]}, 2), got {uv.shape}")
        records["uv"] = uv
    return records


def morph_targets(fine_positions: np.ndarray, coarse_positions: np.ndarray, vertex_map: np.ndarray) -> np.ndarray:
    """Where each vertex of a level morphs to: ``coarse_positions[vertex_map]``.

    fine_positions   : (n, 3) float — level k (only its vertex count is used)
    coarse_positions : (n', 3) float — level k − 1
    vertex_map       : (n,) int, every entry in 0..n'−1 (``proto.morph.decode_morph``)
    Returns (n, 3) float32, the argument of ``Renderer.set_morph_target``.
    Raises ValueError on mismatched shapes or entries out of range.
    """
    fine = np.asarray(fine_positions)
    coarse = np.asarray(coarse_positions, np.float32)
    m = np.asarray(vertex_map)
    if fine.ndim != 2 or fine.shape[1] != 3 or coarse.ndim != 2 or coarse.shape[1] != 3:
        raise ValueError(f"positions must be (n, 3), got {fine.shape} and {coarse.shape}")
    if m.shape != (fine.shape[0],) or not np.issubdtype(m.dtype, np.integer):
        raise ValueError(f"the morph map must be ({fine.shape[0]},) integers, got {m.dtype} {m.shape}")
    if m.size and (int(m.min()) < 0 or int(m.max()) >= coarse.shape[0]):
        raise ValueError(f"morph map entries must lie in 0..{coarse.shape[0] - 1}")
    return np.ascontiguousarray(coarse[m.astype(np.intp, copy=False)], np.float32).reshape(-1, 3)


def object_tint(object_id: int) -> tuple[float, float, float]:
    """A muted colour that is stable per object id (integer hash → hue)."""
    h = (int(object_id) * 0x9E3779B1 + 0x7F4A7C15) & 0xFFFFFFFF
    h ^= h >> 16
    h = (h * 0x85EBCA6B) & 0xFFFFFFFF
    h ^= h >> 13
    hue = (h & 0xFFFF) / 65536.0
    value = 0.75 + 0.2 * ((h >> 16) & 0xFF) / 255.0
    r, g, b = colorsys.hsv_to_rgb(hue, 0.35, value)
    return (r, g, b)


def packed_tint(object_id: int) -> int:
    r, g, b = (round(255 * c) for c in object_tint(object_id))
    return r | (g << 8) | (b << 16) | (255 << 24)


def smooth_normals(positions: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """(nv, 3) float32 unit vertex normals: area-weighted face normals summed per vertex.

    Simplified meshes do not keep a consistent winding, so a second pass flips
    each face normal to agree with the first pass's sum at its corners before
    summing again: a minority of flipped faces no longer cancels its
    neighbours. Vertices without (non-degenerate) faces get +z. Raises
    ValueError on an index outside 0..nv−1.
    """
    p = np.ascontiguousarray(positions, np.float64).reshape(-1, 3)
    f = np.ascontiguousarray(indices, np.intp).reshape(-1, 3)
    if f.size and (int(f.min()) < 0 or int(f.max()) >= p.shape[0]):
        raise ValueError(f"indices must lie in 0..{p.shape[0] - 1}")
    return _smooth_normals(p, f)


def _jit(fn):
    """numba's ``njit``, cached beside the module (compiled in memory where there is nowhere to keep it); the
    server's kernels have their own (``server.select.kernels.jit``), which the client may not import.

    Normals are made for every representation a delta adds, between two frames: compiled, the two
    scatter passes run without the temporaries a numpy scatter needs, which is what kept the frame
    loop waiting while a large delta was applied."""
    try:
        return numba.njit(cache=True, error_model="numpy")(fn)
    except RuntimeError:  # no cache locator (a read-only install)
        return numba.njit(cache=False, error_model="numpy")(fn)


@_jit
def _smooth_normals(p: np.ndarray, f: np.ndarray) -> np.ndarray:
    nv, nf = p.shape[0], f.shape[0]
    face = np.empty((nf, 3))
    first = np.zeros((nv, 3))
    for i in range(nf):
        a, b, c = f[i, 0], f[i, 1], f[i, 2]
        e1x, e1y, e1z = p[b, 0] - p[a, 0], p[b, 1] - p[a, 1], p[b, 2] - p[a, 2]
        e2x, e2y, e2z = p[c, 0] - p[a, 0], p[c, 1] - p[a, 1], p[c, 2] - p[a, 2]
        face[i, 0] = e1y * e2z - e1z * e2y
        face[i, 1] = e1z * e2x - e1x * e2z
        face[i, 2] = e1x * e2y - e1y * e2x
        for k in range(3):
            v = f[i, k]
            for j in range(3):
                first[v, j] += face[i, j]
    total = np.zeros((nv, 3))
    for i in range(nf):
        agree = 0.0
        for k in range(3):
            v = f[i, k]
            agree += face[i, 0] * first[v, 0] + face[i, 1] * first[v, 1] + face[i, 2] * first[v, 2]
        sign = -1.0 if agree < 0.0 else 1.0
        for k in range(3):
            v = f[i, k]
            for j in range(3):
                total[v, j] += sign * face[i, j]
    out = np.empty((nv, 3), np.float32)
    for v in range(nv):
        norm = np.sqrt(total[v, 0] ** 2 + total[v, 1] ** 2 + total[v, 2] ** 2)
        if norm <= 1e-30:
            out[v, 0], out[v, 1], out[v, 2] = 0.0, 0.0, 1.0
        else:
            for j in range(3):
                out[v, j] = total[v, j] / norm
    return out


def target_normals(targets: np.ndarray, indices: np.ndarray, merge: np.ndarray | None = None) -> np.ndarray:
    """(nv, 3) float32 normals for a level's vertices at their morph targets: the coarser level's smooth normals.

    At w = 0 a level's triangles collapse onto the coarser level's: those whose
    corners meet degenerate (zero area, no weight) and the rest are the coarser
    triangles. So the smooth normals of the collapsed mesh, with the vertices
    that share a target merged into one, are the coarser level's normals (up to
    summation order), and the lit algorithm morphs its shading along with the
    shape instead of popping at the switch. ``merge`` (nv,) non-negative ints
    says which vertices share a target — the morph map, whose entries are the
    coarser level's vertices — and is the fast way (no sort); without it the
    vertices at equal target positions are merged (``np.unique``).
    """
    t = np.asarray(targets, np.float32).reshape(-1, 3)
    if t.shape[0] == 0:
        return np.zeros((0, 3), np.float32)
    if merge is None:
        unique, inverse = np.unique(t, axis=0, return_inverse=True)
    else:
        inverse = np.asarray(merge, np.intp)
        if inverse.shape != (t.shape[0],) or int(inverse.min()) < 0:
            raise ValueError(f"merge must be ({t.shape[0]},) non-negative ints, got {inverse.shape}")
        unique = np.zeros((int(inverse.max()) + 1, 3), np.float32)
        unique[inverse] = t
    inverse = inverse.ravel()
    return smooth_normals(unique, inverse[np.asarray(indices, np.intp).reshape(-1, 3)])[inverse]


def pack_normals(normals: np.ndarray) -> np.ndarray:
    """(nv, 4) uint8: unit normals as n·½+½ in bytes (the shader's normalised 4f1), padding 255."""
    packed = np.full((normals.shape[0], 4), 255, np.uint8)
    packed[:, :3] = normals * 127.5 + 128.0  # in [0.5, 255.5) for unit vectors: truncation rounds to nearest
    return packed


def key_light(forward: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Unit direction (3,) towards a light carried above, behind and right of the camera.

    A camera-borne key light lights every visible face (no black backs in a
    walkthrough) while the angle still separates the faces of a shape.
    """
    f = forward / np.linalg.norm(forward)
    s = cross3(f, up)
    s /= np.linalg.norm(s)
    u = cross3(s, f)
    light = -f + 0.6 * u + 0.35 * s
    return light / np.linalg.norm(light)
