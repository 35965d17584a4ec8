"""Headless moderngl renderer: resident geometry in arenas, one multi-draw per algorithm, fenced frames.

The frame time this module measures is what the server's cost model is fitted
to, so the fence holds drawing only: clear, the mesh draws, the layers (point
splats) and ``ctx.finish()``. Uploads, frees and arena compaction happen
between frames, outside it.

Layout (issue 6). Resident geometry lives in two ``Arena`` s: a vertex arena of
``VERTEX`` records (position, morph target and their smooth normals; 32 bytes) and an
index arena of uint32 indices, stored as uploaded (local to their
representation; the draw's baseVertex offsets them). A representation is a
*slot* in numpy tables (its indirect command template, vertex and triangle
counts, tint, whether it has a morph target); rep ids map to slots through a
dense int32 table indexed by rep id, so ``draw`` looks up all its reps at once.

A frame builds, with numpy only, one DrawElementsIndirectCommand per drawn rep
(count, 1, firstIndex, baseVertex, baseInstance = its row) and a per-draw row
(``DRAW``: morph weight, level, tint, flags) read by the vertex shader as
instanced attributes with divisor 1 — baseInstance selects the row, so no
per-draw uniform (on llvmpipe a uniform change between draws cost as much as
the draw). Draws are grouped by rendering algorithm (flat, lit, textured:
separate programs over the same vertex layout) and each group is one
``render_indirect``. No back-face culling: simplified meshes do not keep a
consistent winding; flat and textured take their normal from screen-space
derivatives and lit flips its normal towards the viewer.

Geomorphing (Zach 2002, 3.4): a vertex's morph target is the position it morphs
to on the next coarser level (``morph_targets``); until ``set_morph_target``
sets it, it is the position itself. Every draw blends w · fine + (1 − w) · target
with its row's weight: 1 for static draws (bit-exact: the target term is 0) and
for reps without a target, max(w, 0) for the morphing ones. A morph costs the
finer level's triangles and vertices, and is counted so.

Matrix convention handed to layers (``draw(layers=...)``): ``view_projection``
is the (4, 4) float32 row-major matrix M = projection @ view-rotation of
``proto.camera`` (the view without its translation), applied as
clip = M @ [world − eye, 1] — camera-relative, like ``mesh.vert.glsl``, which
receives M.T's bytes (GLSL reads column-major), so a layer uploads
``M.T.tobytes()``.
"""

from __future__ import annotations

import colorsys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol, Sequence

import moderngl
import numpy as np

from proto.camera import cross3, projection_matrix, view_matrix
from proto.geometry import Geometry
from proto.messages import ALGORITHMS

from .arena import Arena, Relocation

__all__ = ["FrameStats", "FrameTerms", "Renderer", "RendererError", "BACKGROUND", "VERTEX", "DRAW",
           "Layer", "object_tint", "morph_targets", "smooth_normals", "target_normals"]

#: Clear colour (sky), RGB in [0, 1].
BACKGROUND = (0.62, 0.74, 0.86)
_FRAGMENT = ("mesh.frag.glsl", "mesh_lit.frag.glsl", "mesh_textured.frag.glsl")
_SHADERS = Path(__file__).with_name("shaders")
_EGL_HINT = (
    "walkstream's client renders headless through EGL and needs Mesa's EGL "
    "(apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri)"
)
_NEEDS = ("GL_ARB_multi_draw_indirect", "GL_ARB_base_instance")
#: Rep ids below this live in the dense lookup table (≤ 64 MiB); others (and negatives) in a sorted overflow.
_DENSE_LIMIT = 1 << 24
_TEXTURE_PERIOD = 64.0  # metres, mesh_textured.frag.glsl's PERIOD
_AXES = np.arange(3)

#: Vertex record: world position, morph target (= position until set), smooth normal and the target's normal
#: (n·½+½ in normalised bytes, 4th byte padding). 32 bytes.
VERTEX = np.dtype([("position", "<f4", 3), ("target", "<f4", 3), ("normal", "u1", 4), ("target_normal", "u1", 4)])
#: Per-draw row (instanced attribute, divisor 1): weight, continuous level, tint (RGBA8 packed little-endian), flags.
DRAW = np.dtype([("weight", "<f4"), ("level", "<f4"), ("tint", "<u4"), ("flags", "<u4")])
_FLAG_MORPH = 1
_VERTEX_FORMAT = ("3f 3f 4f1 4f1", "in_pos", "in_target", "in_normal", "in_target_normal")
_DRAW_FORMAT = ("1f 1f 4f1 1u4 /i", "in_weight", "in_level", "in_tint", "in_flags")


class RendererError(RuntimeError):
    """The GL context could not be created (or lacks what the renderer needs)."""


@dataclass(frozen=True)
class FrameTerms:
    """A frame's work per rendering algorithm (index into ``ALGORITHMS``), as ``proto.messages.AlgorithmTerms``.

    Each field is a list of 3 ints; ``pixels`` are samples that passed the depth test.
    """

    triangles: list[int]
    vertices: list[int]
    pixels: list[int]
    draws: list[int]


@dataclass(frozen=True)
class FrameStats:
    """One drawn frame: fenced wall time (s) and what was drawn.

    A morphing representation counts its own (the finer level's) triangles and
    vertices; ``morphs`` is how many of the ``draws`` were morphing (weight < 1).
    ``pixels``: samples that passed the depth test in the mesh draws (occlusion
    query; overdraw counts). ``gpu_time``: the timer query's GL_TIME_ELAPSED
    over the fenced frame (s), or None when not plausible (``Renderer.gpu_time_plausible``).
    ``cpu_time``: seconds ``draw`` spent on the CPU before the final wait on the
    GPU (preparation and submission; on llvmpipe submission includes the vertex
    processing its draw module does in the calling thread). ``prepare_time``:
    the part of it that is the renderer's own work (looking up the reps,
    building the multi-draw commands and per-draw rows, uploading them), which
    is what grows with the number of drawn representations. ``culled``: reps
    asked for but outside the view frustum, not drawn (nor counted in the
    other figures: the cost model is fitted to what was drawn). ``splats``: what
    the layers drew. ``terms``: the same work split by rendering algorithm.
    """

    time: float
    triangles: int
    vertices: int
    draws: int
    morphs: int = 0
    pixels: int = 0
    gpu_time: float | None = None
    cpu_time: float = 0.0
    splats: int = 0
    terms: FrameTerms | None = None
    prepare_time: float = 0.0
    culled: int = 0


class Layer(Protocol):
    """Something drawn inside the fence after the meshes (the point-splat layer).

    ``render`` gets the row-major camera-relative ``view_projection`` (see the
    module docstring), the eye (3,) float64, the viewport (width, height) and the
    vertical fov in degrees; it draws into the bound framebuffer (depth test on)
    and returns how many splats it drew. It must not begin a GL_TIME_ELAPSED
    query (the frame's is active).
    """

    def render(self, view_projection: np.ndarray, eye: np.ndarray, viewport: tuple[int, int],
               fov_y: float) -> int: ...


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


def _packed_tint(object_id: int) -> int:
    r, g, b = (round(255 * c) for c in object_tint(object_id))
    return r | (g << 8) | (b << 16) | (255 << 24)


def smooth_normals(positions: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """(nv, 3) float32 unit vertex normals: area-weighted face normals summed per vertex (vectorised).

    Simplified meshes do not keep a consistent winding, so a second pass flips
    each face normal to agree with the first pass's sum at its corners before
    summing again: a minority of flipped faces no longer cancels its
    neighbours. Vertices without (non-degenerate) faces get +z.
    """
    p = np.asarray(positions, np.float64).reshape(-1, 3)
    f = np.asarray(indices, np.intp).reshape(-1, 3)
    nv = p.shape[0]
    if not f.size:
        out = np.zeros((nv, 3), np.float32)
        out[:, 2] = 1.0
        return out
    tri = p[f]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    face = e1[:, [1, 2, 0]] * e2[:, [2, 0, 1]] - e1[:, [2, 0, 1]] * e2[:, [1, 2, 0]]  # cross, cheaper than np.cross
    slots = ((f * 3)[:, :, None] + _AXES).ravel()  # (face, corner, axis) → vertex·3 + axis
    first = np.bincount(slots, weights=np.repeat(face, 3, axis=0).ravel(), minlength=3 * nv).reshape(nv, 3)
    face[np.einsum("ij,ikj->i", face, first[f]) < 0] *= -1.0
    out = np.bincount(slots, weights=np.repeat(face, 3, axis=0).ravel(), minlength=3 * nv).reshape(nv, 3)
    norm = np.sqrt(np.einsum("ij,ij->i", out, out))
    bad = norm <= 1e-30
    norm[bad] = 1.0
    out /= norm[:, None]
    out[bad] = (0.0, 0.0, 1.0)
    return out.astype(np.float32)


def target_normals(targets: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """(nv, 3) float32 normals for a level's vertices at their morph targets: the coarser level's smooth normals.

    At w = 0 a level's triangles collapse onto the coarser level's: those whose
    corners meet degenerate (zero area, no weight) and the rest are the coarser
    triangles. So the smooth normals of the collapsed mesh, with the vertices
    that share a target position merged into one, are the coarser level's
    normals (up to summation order), and the lit algorithm morphs its shading
    along with the shape instead of popping at the switch.
    """
    t = np.asarray(targets, np.float32).reshape(-1, 3)
    if t.shape[0] == 0:
        return np.zeros((0, 3), np.float32)
    unique, inverse = np.unique(t, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    return smooth_normals(unique, inverse[np.asarray(indices, np.intp).reshape(-1, 3)])[inverse]


def _pack_normals(normals: np.ndarray) -> np.ndarray:
    """(nv, 4) uint8: unit normals as n·½+½ in bytes (the shader's normalised 4f1), padding 255."""
    packed = np.full((normals.shape[0], 4), 255, np.uint8)
    packed[:, :3] = normals * 127.5 + 128.0  # in [0.5, 255.5) for unit vectors: truncation rounds to nearest
    return packed


def _sphere(centre: np.ndarray, half: np.ndarray) -> tuple[float, float, float, float]:
    """A box's bounding sphere for the float32 table: the radius grows by more than float32 rounds the centre
    (2⁻²⁴ relative), so the rounded sphere still holds the box."""
    r = float(np.linalg.norm(half))
    return (*map(float, centre), r + 1e-6 * (float(np.abs(centre).max()) + r))


def _key_light(forward: np.ndarray, up: np.ndarray) -> np.ndarray:
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


def _source(name: str, defines: str, common: str) -> str:
    """A stage's source with the defines and ``mesh_common.glsl`` inserted after its #version line."""
    head, _, body = (_SHADERS / name).read_text().partition("\n")
    return f"{head}\n{defines}{common}\n#line 2\n{body}"


@dataclass
class _Slots:
    """Per-slot tables (numpy, grown geometrically); a slot is one resident representation."""

    command: np.ndarray = field(default_factory=lambda: np.zeros((0, 5), np.uint32))  # count, 1, first, base, 0
    vertices: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    faces: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    tint: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint32))
    target: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    vblock: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # vertex arena offset, -1: none
    iblock: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # index arena offset, -1: none
    centre: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float64))  # box over fine and target
    half: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float64))
    # bounding sphere x, y, z, r in float32 (half the bytes a frame gathers), r padded over float32's rounding
    sphere: np.ndarray = field(default_factory=lambda: np.zeros((0, 4), np.float32))

    def grow(self, capacity: int) -> None:
        old = self.vertices.size
        for name in ("command", "vertices", "faces", "tint", "target", "vblock", "iblock", "centre", "half", "sphere"):
            a = getattr(self, name)
            b = np.zeros((capacity,) + a.shape[1:], a.dtype)
            b[:old] = a
            setattr(self, name, b)
        self.vblock[old:] = -1
        self.iblock[old:] = -1


class Renderer:
    """An offscreen framebuffer (colour + depth) and the representations resident on the GPU.

    width, height : framebuffer size in pixels
    fov_y : vertical field of view in degrees (the ``Hello`` value)
    backend : moderngl standalone backend; "egl" for headless, None for the platform default
    ctx : an existing context (a window's) to draw in instead; never released here
    vertex_capacity, index_capacity : the arenas' initial sizes (vertices, indices); they grow as needed

    Set ``false_colour`` to shade by level (``false_colour_levels``: the level
    shown in the ramp's finest colour). ``vertex_arena`` / ``index_arena`` are
    the arenas, ``meshes`` maps resident rep ids to slots.
    """

    morph_targets = staticmethod(morph_targets)

    def __init__(self, width: int, height: int, *, fov_y: float = 60.0, backend: str | None = "egl",
                 ctx: moderngl.Context | None = None, vertex_capacity: int = 1 << 16,
                 index_capacity: int = 1 << 18) -> None:
        self._own_ctx = ctx is None
        if ctx is not None:
            self.ctx = ctx  # a window's context (``client.window``): drawn offscreen, then blitted
        else:
            try:
                kwargs = {"backend": backend} if backend else {}
                self.ctx = moderngl.create_standalone_context(require=330, **kwargs)
            except Exception as exc:
                raise RendererError(f"cannot create a GL context ({exc}); {_EGL_HINT}") from exc
        lacking = [e for e in _NEEDS if e not in self.ctx.extensions] if self.ctx.version_code < 430 else []
        if lacking:
            if self._own_ctx:
                self.ctx.release()
            raise RendererError(f"the GL context ({self.ctx.info.get('GL_VERSION')}) lacks {', '.join(lacking)}; "
                                f"the renderer needs GL 4.3 or those extensions (Mesa's llvmpipe has them)")
        self.width, self.height, self.fov_y = int(width), int(height), float(fov_y)
        self._color = self.ctx.renderbuffer((self.width, self.height))
        self._depth = self.ctx.depth_renderbuffer((self.width, self.height))
        self.fbo = self.ctx.framebuffer(color_attachments=[self._color], depth_attachment=self._depth)

        self.false_colour = False
        """Shade each draw by its level (``levels``), morphing draws striped magenta."""
        self.cull = True
        """Leave out reps whose bounding sphere is outside the view frustum (``FrameStats.culled``)."""
        self.false_colour_levels = 5.0
        """The level drawn in the false-colour ramp's finest colour (red); 0 is the coarsest (blue)."""
        common = (_SHADERS / "mesh_common.glsl").read_text()
        self.programs = tuple(
            self.ctx.program(
                vertex_shader=_source("mesh.vert.glsl", f"#define ALGORITHM {k}\n#define STAGE_VERTEX\n", common),
                fragment_shader=_source(_FRAGMENT[k], f"#define ALGORITHM {k}\n#define STAGE_FRAGMENT\n", common))
            for k in range(len(ALGORITHMS))
        )
        self._uniforms = [
            {name: prog.get(name, None) for name in ("u_view_projection", "u_eye", "u_up", "u_sun", "u_false_colour",
                                                     "u_level_scale", "u_eye_wrap")}
            for prog in self.programs
        ]

        self.vertex_arena = Arena(self.ctx, VERTEX.itemsize, vertex_capacity)
        self.index_arena = Arena(self.ctx, 4, index_capacity, compact_min=1 << 16)
        self.vertex_arena.listeners.append(self._vertices_moved)
        self.index_arena.listeners.append(self._indices_moved)
        self._draw_capacity = 1024
        self._draw_rows = self.ctx.buffer(reserve=self._draw_capacity * DRAW.itemsize)
        self._commands = self.ctx.buffer(reserve=self._draw_capacity * 20)
        self._vaos: list[moderngl.VertexArray] = []
        self._vaos_stale = True

        self._slots = _Slots()
        self._slots.grow(256)
        self._free_slots: list[int] = list(range(255, -1, -1))
        self._table = np.full(1024, -1, np.int32)
        self._overflow: dict[int, int] = {}
        self._overflow_keys = np.zeros(0, np.int64)
        self._overflow_slots = np.zeros(0, np.int32)
        self.meshes: dict[int, int] = {}
        """Resident representations: rep id → slot in the tables (read-only for callers)."""

        self._time_query = self.ctx.query(time=True)
        self._sample_queries = [self.ctx.query(samples=True) for _ in ALGORITHMS]
        self.missing = 0
        """Draw requests for reps not uploaded, in total (skipped, never drawn)."""
        self.unmorphed = 0
        """Draw requests with weight < 1 for reps without a morph target, in total (drawn at full detail)."""
        self._warm_up()

    def _warm_up(self) -> None:
        """Draw a triangle with every algorithm, static and morphing, false-coloured or not.

        llvmpipe compiles shaders at their first draw (~25 ms each): not in frame 0's time.
        """
        tri = Geometry(np.array([[-1, -1, -5], [1, -1, -5], [0, 1, -5]], np.float32), np.array([[0, 1, 2]], np.uint32))
        self.upload(-1, tri)
        self.set_morph_target(-1, tri.positions[[0, 0, 2]])
        n = len(ALGORITHMS)
        for false_colour in (True, False):
            self.false_colour = false_colour
            self.draw(np.full(2 * n, -1), np.zeros(3), np.array([0.0, 0.0, -1.0]), np.array([0.0, 1.0, 0.0]), 0.1,
                      10.0, weights=np.repeat([1.0, 0.5], n), algorithms=np.tile(np.arange(n), 2))
        self.free(-1)
        self.missing = self.unmorphed = 0

    # ----------------------------------------------------------------- resident geometry

    def upload(self, rep: int, geometry: Geometry, object_id: int | None = None) -> None:
        """Put one representation on the GPU (replacing any with the same id).

        geometry.positions : (nv, 3) float32; geometry.indices : (nf, 3) uint32, every entry < nv.
        object_id picks the tint, so all levels of one object share a colour. GPU memory:
        32 bytes per vertex (``VERTEX``) and 12 per triangle, in the arenas.
        Raises ValueError on an index out of range.
        """
        rep = int(rep)
        positions = np.ascontiguousarray(geometry.positions, np.float32).reshape(-1, 3)
        indices = np.ascontiguousarray(geometry.indices, np.uint32).reshape(-1, 3)
        nv, nf = positions.shape[0], indices.shape[0]
        if nf and int(indices.max()) >= nv:
            raise ValueError(f"representation {rep} has indices beyond its {nv} vertices")
        self.free(rep)
        records = np.empty(nv, VERTEX)
        records["position"] = positions
        records["target"] = positions
        records["normal"] = _pack_normals(smooth_normals(positions, indices))
        records["target_normal"] = records["normal"]
        vblock = iblock = -1
        if nv:
            vblock = self.vertex_arena.alloc(nv)
            self.vertex_arena.write(vblock, records)
        if nf:
            iblock = self.index_arena.alloc(3 * nf)
            self.index_arena.write(iblock, indices)
        slot = self._new_slot()
        s = self._slots
        s.command[slot] = (3 * nf, 1, max(iblock, 0), max(vblock, 0), 0)
        s.vertices[slot], s.faces[slot] = nv, nf
        s.tint[slot] = _packed_tint(rep if object_id is None else object_id)
        s.target[slot] = False
        s.vblock[slot], s.iblock[slot] = vblock, iblock
        lo, hi = (positions.min(axis=0), positions.max(axis=0)) if nv else (np.zeros(3), np.zeros(3))
        s.centre[slot], s.half[slot] = (lo + hi) / 2.0, (hi - lo) / 2.0
        s.sphere[slot] = _sphere(s.centre[slot], s.half[slot])
        self._bind(rep, slot)

    def set_morph_target(self, rep: int, targets: np.ndarray) -> None:
        """Give an uploaded representation its morph target (replacing any it had).

        targets : (nv, 3) float — the position each of ``rep``'s nv vertices morphs
            to, on the next coarser level (``morph_targets``). Stored in the vertex
            records with the coarser level's normals (``target_normals``, from the
            rep's own triangles): read back, patched, written — between frames
            nothing is in flight, so the read does not stall. Dropped with the representation
            (``free``, or ``upload`` over it). Raises KeyError if ``rep`` is not
            uploaded, ValueError on a wrong shape or non-finite targets.
        """
        slot = self.meshes.get(int(rep))
        if slot is None:
            raise KeyError(f"representation {rep} is not uploaded")
        nv = int(self._slots.vertices[slot])
        t = np.asarray(targets)
        if t.shape != (nv, 3):
            raise ValueError(f"morph target of representation {rep} must be ({nv}, 3), got {t.shape}")
        t = np.ascontiguousarray(t, np.float32)
        if not np.isfinite(t).all():
            raise ValueError(f"morph target of representation {rep} is not finite")
        if nv:
            block = int(self._slots.vblock[slot])
            records = np.frombuffer(self.vertex_arena.read(block), VERTEX).copy()
            records["target"] = t
            if self._slots.faces[slot]:
                indices = np.frombuffer(self.index_arena.read(int(self._slots.iblock[slot])), np.uint32)
                records["target_normal"] = _pack_normals(target_normals(t, indices.reshape(-1, 3)))
            self.vertex_arena.write(block, records)
            # A morphing vertex travels between its two positions: the box covers both ends.
            c, h = self._slots.centre[slot], self._slots.half[slot]
            lo, hi = np.minimum(c - h, t.min(axis=0)), np.maximum(c + h, t.max(axis=0))
            self._slots.centre[slot], self._slots.half[slot] = (lo + hi) / 2.0, (hi - lo) / 2.0
            self._slots.sphere[slot] = _sphere(self._slots.centre[slot], self._slots.half[slot])
        self._slots.target[slot] = True

    def has_morph_target(self, rep: int) -> bool:
        """Whether ``rep`` is uploaded with a morph target."""
        slot = self.meshes.get(int(rep))
        return slot is not None and bool(self._slots.target[slot])

    def free(self, rep: int) -> None:
        """Drop a representation (its morph target too); unknown ids are ignored.

        An arena left too sparse (``Arena.fragmented``) is compacted here, between frames.
        """
        rep = int(rep)
        slot = self.meshes.pop(rep, None)
        if slot is None:
            return
        if 0 <= rep < _DENSE_LIMIT:
            self._table[rep] = -1
        else:
            del self._overflow[rep]
            self._overflow_keys = None  # rebuilt at the next lookup
        s = self._slots
        if s.vblock[slot] >= 0:
            self.vertex_arena.free(int(s.vblock[slot]))
        if s.iblock[slot] >= 0:
            self.index_arena.free(int(s.iblock[slot]))
        s.command[slot] = 0
        s.vertices[slot] = s.faces[slot] = 0
        s.target[slot] = False
        s.vblock[slot] = s.iblock[slot] = -1
        self._free_slots.append(slot)
        self.vertex_arena.maybe_compact()
        self.index_arena.maybe_compact()

    def _new_slot(self) -> int:
        if not self._free_slots:
            old = self._slots.vertices.size
            self._slots.grow(2 * old)
            self._free_slots = list(range(2 * old - 1, old - 1, -1))
        return self._free_slots.pop()

    def _bind(self, rep: int, slot: int) -> None:
        self.meshes[rep] = slot
        if 0 <= rep < _DENSE_LIMIT:
            if rep >= self._table.size:
                table = np.full(1 << int(rep).bit_length(), -1, np.int32)
                table[: self._table.size] = self._table
                self._table = table
            self._table[rep] = slot
        else:
            self._overflow[rep] = slot
            self._overflow_keys = None

    def _lookup(self, reps: np.ndarray) -> np.ndarray:
        """Slots (s,) int of ``reps`` (s,) int64, −1 where not resident; vectorised."""
        table = self._table
        if reps.size == 0:
            return np.zeros(0, np.int32)
        if reps.min() >= 0 and reps.max() < table.size:
            return table[reps]
        slots = np.full(reps.size, -1, np.int32)
        inside = (reps >= 0) & (reps < table.size)
        slots[inside] = table[reps[inside]]
        if self._overflow:
            if self._overflow_keys is None:
                keys = np.fromiter(self._overflow.keys(), np.int64, len(self._overflow))
                order = np.argsort(keys)
                self._overflow_keys = keys[order]
                self._overflow_slots = np.fromiter(self._overflow.values(), np.int32, len(self._overflow))[order]
            out = np.flatnonzero(~inside)
            i = np.minimum(np.searchsorted(self._overflow_keys, reps[out]), self._overflow_keys.size - 1)
            slots[out] = np.where(self._overflow_keys[i] == reps[out], self._overflow_slots[i], -1)
        return slots

    # ----------------------------------------------------------------- arenas moved

    def _vertices_moved(self, arena: Arena, moved: Relocation | None) -> None:
        self._vaos_stale = True
        if moved is not None:
            s = self._slots
            live = np.flatnonzero(s.vblock >= 0)
            s.vblock[live] = moved.map(s.vblock[live])
            s.command[live, 3] = s.vblock[live]

    def _indices_moved(self, arena: Arena, moved: Relocation | None) -> None:
        self._vaos_stale = True
        if moved is not None:
            s = self._slots
            live = np.flatnonzero(s.iblock >= 0)
            s.iblock[live] = moved.map(s.iblock[live])
            s.command[live, 2] = s.iblock[live]

    def _build_vaos(self) -> None:
        """One VAO per program over the arenas' current buffers and the per-draw rows."""
        for vao in self._vaos:
            vao.release()
        self._vaos = [
            self.ctx.vertex_array(
                prog,
                [(self.vertex_arena.buffer, *_VERTEX_FORMAT), (self._draw_rows, *_DRAW_FORMAT)],
                index_buffer=self.index_arena.buffer,
                index_element_size=4,
                skip_errors=True,  # flat and textured do not read the normal
            )
            for prog in self.programs
        ]
        self._vaos_stale = False

    # ----------------------------------------------------------------- drawing

    def draw(
        self,
        reps: np.ndarray,
        eye: np.ndarray,
        forward: np.ndarray,
        up: np.ndarray,
        near: float,
        far: float,
        weights: np.ndarray | None = None,
        algorithms: np.ndarray | None = None,
        levels: np.ndarray | None = None,
        layers: Sequence[Layer] = (),
    ) -> FrameStats:
        """Draw ``reps`` (s,) int from the pose (eye, forward, up: (3,) float) and time it.

        weights : (s,) float aligned with ``reps``, the morph weight of each (None:
            all 1). A rep with weight ≥ 1 is drawn as it is; one with weight < 1
            and a morph target is drawn blended toward its coarser level (below 0
            counts as 0); one with weight < 1 and no target is drawn as it is and
            counted in ``unmorphed``.
        algorithms : (s,) int in 0..2, index into ``ALGORITHMS`` (None: all flat).
        levels : (s,) float, the continuous level shown by ``false_colour`` (None: 0).
        layers : drawn after the meshes, inside the fence (``Layer``); their returns are ``splats``.
        Reps not resident are skipped and counted in ``missing``.
        Returns the fenced wall time of clear + draws + layers + ``ctx.finish()``
        and what was drawn (``FrameStats``). Raises ValueError on misaligned or
        non-finite arguments or algorithms out of range.
        """
        c0 = time.perf_counter()
        reps = np.asarray(reps).ravel()
        reps = reps.astype(np.int64, copy=False) if reps.dtype.kind in "iu" else reps.astype(np.int64)
        s = reps.size
        w = self._aligned(weights, s, np.float64, "weights")
        alg = self._aligned(algorithms, s, np.int64, "algorithms")
        lev = self._aligned(levels, s, np.float32, "levels")
        if w is not None and not np.isfinite(w).all():
            raise ValueError("morph weights must be finite")
        if alg is not None and s and (alg.min() < 0 or alg.max() >= len(ALGORITHMS)):
            raise ValueError(f"algorithms must lie in 0..{len(ALGORITHMS) - 1}")
        if lev is not None and not np.isfinite(lev).all():
            raise ValueError("levels must be finite")

        slots = self._lookup(reps)
        here = slots >= 0
        n = int(np.count_nonzero(here))
        if n < s:
            self.missing += s - n
            slots = slots[here]
            w = None if w is None else w[here]
            alg = None if alg is None else alg[here]
            lev = None if lev is None else lev[here]
        tables = self._slots
        eye = np.asarray(eye, np.float64)
        up = np.asarray(up, np.float64)
        forward = np.asarray(forward, np.float64)
        rotation = view_matrix(np.zeros(3), forward, up)
        vp64 = projection_matrix(self.fov_y, self.width / self.height, near, far) @ rotation
        culled = 0
        if self.cull and n:
            # Frustum culling by bounding sphere (Gribb–Hartmann planes of the view-projection, normalised):
            # the selection includes a margin around the view for where the camera is going, and on
            # llvmpipe every submitted vertex is processed on the CPU, seen or not. One (6, 4) @ (4, s)
            # product gives each centre's signed distance to each plane plus its radius; planes as rows, so
            # the test reduces over contiguous rows (a reduction along the short axis of (s, 6) cost 4× more:
            # 1.7 ms of the 3.8 ms a frame of 10k reps took to prepare).
            planes = np.stack([vp64[3] + vp64[0], vp64[3] - vp64[0], vp64[3] + vp64[1], vp64[3] - vp64[1],
                               vp64[3] + vp64[2], vp64[3] - vp64[2]])
            planes /= np.linalg.norm(planes[:, :3], axis=1, keepdims=True)
            m = np.hstack([planes[:, :3], np.ones((6, 1))]).astype(np.float32)
            d = m @ tables.sphere[slots].T
            d += (planes[:, 3] - planes[:, :3] @ eye)[:, None]
            seen = np.logical_and.reduce(d >= 0.0, axis=0)
            culled = n - int(np.count_nonzero(seen))
            if culled:
                slots = slots[seen]
                w = None if w is None else w[seen]
                alg = None if alg is None else alg[seen]
                lev = None if lev is None else lev[seen]
                n -= culled
        if alg is not None and n:  # group by algorithm, keeping the caller's order within each
            masks = [alg == k for k in range(len(ALGORITHMS))]
            order = np.concatenate([np.flatnonzero(m) for m in masks])  # three passes beat a sort
            slots, alg = slots[order], alg[order]
            w = None if w is None else w[order]
            lev = None if lev is None else lev[order]
            per_alg = np.array([np.count_nonzero(m) for m in masks])
        else:
            per_alg = np.array([n, 0, 0])

        rows = np.empty(n, DRAW)
        morphs = 0
        if w is None:
            rows["weight"] = 1.0
            rows["flags"] = 0
        else:
            static = w >= 1.0
            has_target = tables.target[slots]
            morphing = ~static & has_target
            morphs = int(np.count_nonzero(morphing))
            self.unmorphed += int(np.count_nonzero(~static & ~has_target))
            rows["weight"] = np.where(morphing, np.maximum(w, 0.0), 1.0)
            rows["flags"] = morphing * np.uint32(_FLAG_MORPH)
        rows["level"] = 0.0 if lev is None else lev
        rows["tint"] = tables.tint[slots]
        commands = tables.command[slots]
        commands[:, 4] = np.arange(n, dtype=np.uint32)

        faces, vertices = tables.faces[slots], tables.vertices[slots]
        if alg is None or not n:
            tri_alg = np.array([faces.sum(), 0, 0], np.int64)
            vert_alg = np.array([vertices.sum(), 0, 0], np.int64)
        else:
            tri_alg = np.bincount(alg, weights=faces, minlength=len(ALGORITHMS)).astype(np.int64)
            vert_alg = np.bincount(alg, weights=vertices, minlength=len(ALGORITHMS)).astype(np.int64)

        if n > self._draw_capacity:  # orphaning keeps the buffers' names, so the VAOs stay valid
            while self._draw_capacity < n:
                self._draw_capacity *= 2
            self._draw_rows.orphan(self._draw_capacity * DRAW.itemsize)
            self._commands.orphan(self._draw_capacity * 20)
        if n:
            self._draw_rows.write(rows)
            self._commands.write(commands)
        if self._vaos_stale:
            self._build_vaos()

        vp = vp64.astype(np.float32)
        vp_bytes = vp.T.tobytes()
        values = {
            "u_eye": tuple(eye),
            "u_up": tuple(up / np.linalg.norm(up)),
            "u_sun": tuple(_key_light(forward, up)),
            "u_false_colour": bool(self.false_colour),
            "u_level_scale": float(self.false_colour_levels),
            "u_eye_wrap": tuple(eye - _TEXTURE_PERIOD * np.floor(eye / _TEXTURE_PERIOD)),
        }
        for k in np.flatnonzero(per_alg).tolist():
            uniforms = self._uniforms[k]
            uniforms["u_view_projection"].write(vp_bytes)
            for name, value in values.items():
                if uniforms[name] is not None:
                    uniforms[name].value = value

        c1 = time.perf_counter()
        self.ctx.finish()  # uploads still in flight belong to no frame: finish them outside the fence
        t0 = time.perf_counter()
        splats = 0
        with self._time_query:
            self.fbo.use()
            self.ctx.enable_only(moderngl.DEPTH_TEST)
            self.fbo.clear(*BACKGROUND, 1.0, depth=1.0)
            first = 0
            for k, count in enumerate(per_alg.tolist()):
                if count:
                    with self._sample_queries[k]:
                        self._vaos[k].render_indirect(self._commands, moderngl.TRIANGLES, count=count, first=first)
                    first += count
            for layer in layers:
                splats += int(layer.render(vp, eye, (self.width, self.height), self.fov_y))
        t1 = time.perf_counter()
        self.ctx.finish()
        t2 = time.perf_counter()
        elapsed = t2 - t0

        pixels = [self._sample_queries[k].samples if count else 0 for k, count in enumerate(per_alg.tolist())]
        gpu = self._time_query.elapsed * 1e-9
        terms = FrameTerms(triangles=tri_alg.tolist(), vertices=vert_alg.tolist(), pixels=pixels,
                           draws=per_alg.astype(np.int64).tolist())
        return FrameStats(
            time=elapsed,
            triangles=int(tri_alg.sum()),
            vertices=int(vert_alg.sum()),
            draws=n,
            morphs=morphs,
            pixels=int(sum(pixels)),
            gpu_time=gpu if self.gpu_time_plausible(gpu, elapsed, t2 - t1) else None,
            cpu_time=(c1 - c0) + (t1 - t0),
            prepare_time=c1 - c0,
            culled=culled,
            splats=splats,
            terms=terms,
        )

    @staticmethod
    def gpu_time_plausible(gpu_time: float, wall_time: float, wait_time: float = 0.0) -> bool:
        """Whether a timer query's GL_TIME_ELAPSED (s) can be believed, given the frame's fenced times (s).

        wall_time : the fenced wall time (``FrameStats.time``)
        wait_time : the part of it spent in the final ``ctx.finish()``, waiting for the GPU
        llvmpipe's timer queries are not trustworthy (zero, or a few µs for frames
        whose fence waited milliseconds on its rasterizer threads), so a value is
        kept only if it is positive, no longer than the fence (plus 10 % and
        0.1 ms) and at least half the final wait less 0.2 ms: the GPU finished
        the queried work during that wait, and could not have started it before
        the fence, so the query spans at least most of the wait.
        """
        return 0.0 < gpu_time <= wall_time * 1.1 + 1e-4 and gpu_time >= 0.5 * wait_time - 2e-4

    @staticmethod
    def _aligned(values: object, s: int, dtype: type, what: str) -> np.ndarray | None:
        if values is None:
            return None
        a = np.asarray(values)
        if a.shape != (s,):
            raise ValueError(f"{what} must be aligned with reps ({s},), got {a.shape}")
        if dtype is np.int64 and s and a.dtype.kind not in "iu":
            if a.dtype.kind != "f" or not np.array_equal(a, np.round(a)):
                raise ValueError(f"{what} must be integers")
        return a.astype(dtype, copy=False)

    # ----------------------------------------------------------------- output

    def read_image(self) -> np.ndarray:
        """The last frame as (height, width, 3) uint8, rows top-down."""
        data = self.fbo.read(components=3, alignment=1)
        return np.frombuffer(data, np.uint8).reshape(self.height, self.width, 3)[::-1].copy()

    def save_png(self, path: str | Path) -> None:
        """Write the last frame as a PNG (PIL if present, else matplotlib)."""
        image = self.read_image()
        try:
            from PIL import Image
        except ImportError:
            import matplotlib.pyplot as plt

            plt.imsave(str(path), image)
        else:
            Image.fromarray(image).save(str(path))

    def release(self) -> None:
        """Release every GL object, and the context if the renderer created it."""
        if self.programs is None:
            return
        for vao in self._vaos:
            vao.release()
        self._vaos = []
        self.meshes.clear()
        self.vertex_arena.release()
        self.index_arena.release()
        self._draw_rows.release()
        self._commands.release()
        for prog in self.programs:
            prog.release()
        self.programs = None
        self.fbo.release()
        self._color.release()
        self._depth.release()
        if self._own_ctx:
            self.ctx.release()

    def __enter__(self) -> "Renderer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()
