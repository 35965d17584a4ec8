"""Headless moderngl renderer: resident geometry in arenas, one multi-draw per algorithm, fenced frames.

The frame time this module measures is what the server's cost model is fitted
to, so the fence holds drawing only: clear, the mesh draws, the layers (point
splats) and ``ctx.finish()``. Uploads, frees and arena compaction happen
between frames, outside it.

Layout. Resident geometry lives in two ``Arena`` s: a vertex arena of
``VERTEX`` records (position, morph target, their smooth normals and colours, texture
coordinates; 48 bytes, ``client.shading``) and an index arena of uint32 indices, stored as uploaded
(local to their representation; the draw's baseVertex offsets them). A
representation is a *slot* in numpy tables (``client.slots``: its indirect
command template, vertex and triangle counts, tint, bounding sphere, whether it
has a morph target), so a frame looks up all its reps at once.

A frame is planned with numpy only (``client.frame_plan``): one
DrawElementsIndirectCommand per drawn rep (count, 1, firstIndex, baseVertex,
baseInstance = its row) and a per-draw row (``DRAW``: morph weight, level,
tint, flags, texture class and layer) read by the vertex shader as instanced attributes with divisor 1 —
baseInstance selects the row, so no per-draw uniform (on a software
rasterizer a uniform change between draws costs as much as the draw). Draws
are grouped by rendering algorithm (flat, lit, textured: separate programs
over the same vertex layout) and each group is one ``render_indirect``. No
back-face culling: simplified meshes do not keep a consistent winding; flat
and textured take their normal from screen-space derivatives and lit flips its
normal towards the viewer.

Geomorphing (Zach 2002, 3.4): a vertex's morph target is the position it morphs
to on the next coarser level (``morph_targets``); until ``set_morph_target``
sets it, it is the position itself. Every draw blends w · fine + (1 − w) · target
with its row's weight: 1 for static draws (bit-exact: the target term is 0) and
for reps without a target, max(w, 0) for the morphing ones. A morph costs the
finer level's triangles and vertices, and is counted so.

Textures. A representation whose payload brings a texture keeps it in a layer
of its size class's texture array (``client.textures``) while it is resident;
the textured algorithm samples it where the draw's row names one and draws its
procedural pattern where it does not, so textured and untextured objects share
one multi-draw. Flat and lit draw the payload's colours (a texture's mean).

Appearance. Each vertex carries the colour its payload gives (``proto.geometry``)
and its morph target's, blended with the position; a payload without colours is
drawn in its object's tint, and ``colours = "objects"`` draws every object in its
tint (a debugging view). ``sun``, when set, is the world direction every
algorithm is lit from (the scene's, ``proto.messages.Welcome.sun``); unset, a
light carried with the camera (``client.shading.key_light``). ``sky``, when set,
paints a sky gradient (``client.sky``) before the fence instead of clearing to
``BACKGROUND`` inside it: it is the same full-screen pass every frame whatever
the selection, so the frame the cost model is fitted to keeps measuring the
selection's work (the fence then clears depth only).

Matrix convention handed to layers (``draw(layers=...)``): ``view_projection``
is the (4, 4) float32 row-major matrix M = projection @ view-rotation of
``proto.camera`` (the view without its translation), applied as
clip = M @ [world − eye, 1] — camera-relative, like ``mesh.vert.glsl``, which
receives M.T's bytes (GLSL reads column-major), so a layer uploads
``M.T.tobytes()``.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Sequence

import moderngl
import numpy as np

from proto.camera import projection_matrix, view_matrix
from proto.geometry import Geometry
from proto.messages import ALGORITHMS

from .arena import Arena, Relocation
from .frame_stats import FrameStats, FrameTerms, Layer
from .frame_plan import DRAW, in_frustum, plan_frame
from .llvmpipe import raster_threads
from .shading import (VERTEX, key_light, morph_targets, pack_colours, pack_normals, packed_tint, target_normals,
                      vertex_records)
from .sky import Sky
from .slots import SlotTable
from .textures import SIDES, TextureStore

__all__ = ["FrameStats", "FrameTerms", "Renderer", "RendererError", "BACKGROUND", "COLOURS", "Layer",
           "morph_targets"]

#: Clear colour without a sky (``Renderer.sky``), RGB in [0, 1].
BACKGROUND = (0.62, 0.74, 0.86)
#: What a surface is drawn in (``Renderer.colours``): its data's colours (the object's tint where its payload
#: has none), or every object in its own tint (a debugging view).
COLOURS = ("data", "objects")
_FRAGMENT = ("mesh.frag.glsl", "mesh_lit.frag.glsl", "mesh_textured.frag.glsl")
_SHADERS = Path(__file__).with_name("shaders")
_EGL_HINT = (
    "walkstream's client renders headless through EGL and needs Mesa's EGL "
    "(apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri)"
)
_NEEDS = ("GL_ARB_multi_draw_indirect", "GL_ARB_base_instance")
_TEXTURE_PERIOD = 64.0  # metres, mesh_textured.frag.glsl's PERIOD

_VERTEX_FORMAT = ("3f 3f 4f1 4f1 4f1 4f1 2f", "in_pos", "in_target", "in_normal", "in_target_normal", "in_colour",
                  "in_target_colour", "in_uv")
_DRAW_FORMAT = ("1f 1f 4f1 1u4 1i 1f /i", "in_weight", "in_level", "in_tint", "in_flags", "in_tex_class",
                "in_tex_layer")
_TEXTURED = ALGORITHMS.index("textured")


class RendererError(RuntimeError):
    """The GL context could not be created (or lacks what the renderer needs)."""


def _source(name: str, defines: str, common: str) -> str:
    """A stage's source with the defines and ``mesh_common.glsl`` inserted after its #version line."""
    head, _, body = (_SHADERS / name).read_text().partition("\n")
    return f"{head}\n{defines}{common}\n#line 2\n{body}"


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
                with raster_threads():
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
        self.colours = "data"
        """What surfaces are drawn in, one of ``COLOURS`` (``false_colour`` overrides both)."""
        self.sun: np.ndarray | None = None
        """(3,) unit world direction towards the sun, or None: a light carried with the camera."""
        self.sky: Sky | None = None
        """The sky painted behind the scene (``enable_sky``), or None: cleared to ``BACKGROUND``."""
        common = (_SHADERS / "mesh_common.glsl").read_text()
        self.programs = tuple(
            self.ctx.program(
                vertex_shader=_source("mesh.vert.glsl", f"#define ALGORITHM {k}\n#define STAGE_VERTEX\n", common),
                fragment_shader=_source(_FRAGMENT[k], f"#define ALGORITHM {k}\n#define STAGE_FRAGMENT\n", common))
            for k in range(len(ALGORITHMS))
        )
        self._uniforms = [
            {name: prog.get(name, None) for name in ("u_view_projection", "u_eye", "u_up", "u_sun", "u_false_colour",
                                                     "u_level_scale", "u_eye_wrap", "u_object_colours",
                                                     "u_light_mix")}
            for prog in self.programs
        ]
        self.textures = TextureStore(self.ctx)
        """Resident representations' textures (``client.textures``), bound to units 0.. for the textured algorithm."""
        for k in range(len(SIDES)):  # class k's array is bound to texture unit k
            sampler = self.programs[_TEXTURED].get(f"u_texture{k}", None)
            if sampler is not None:
                sampler.value = k

        self.vertex_arena = Arena(self.ctx, VERTEX.itemsize, vertex_capacity)
        self.index_arena = Arena(self.ctx, 4, index_capacity, compact_min=1 << 16)
        self.vertex_arena.listeners.append(self._vertices_moved)
        self.index_arena.listeners.append(self._indices_moved)
        self._draw_capacity = 1024
        self._draw_rows = self.ctx.buffer(reserve=self._draw_capacity * DRAW.itemsize)
        self._commands = self.ctx.buffer(reserve=self._draw_capacity * 20)
        self._vaos: list[moderngl.VertexArray] = []
        self._vaos_stale = True

        self._slots = SlotTable()
        self.meshes = self._slots.meshes
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

        A software rasterizer (llvmpipe) compiles a shader at its first draw: not in frame 0's time.
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
        geometry.colours : (nv, 3) uint8 or None (then the object's tint). object_id picks the tint, so
        all levels of one object share a colour. geometry.uv (nv, 2) and geometry.texture (h, w, 3) uint8,
        or None: the texture goes into a texture array layer (``client.textures``) until the rep is freed.
        GPU memory: 48 bytes per vertex (``VERTEX``) and 12 per triangle, in the arenas, and the texture's
        layer. Raises ValueError on an index out of range.
        """
        rep = int(rep)
        positions = np.ascontiguousarray(geometry.positions, np.float32).reshape(-1, 3)
        indices = np.ascontiguousarray(geometry.indices, np.uint32).reshape(-1, 3)
        nv, nf = positions.shape[0], indices.shape[0]
        if nf and int(indices.max()) >= nv:
            raise ValueError(f"representation {rep} has indices beyond its {nv} vertices")
        self.free(rep)
        texture = getattr(geometry, "texture", None)
        uv = getattr(geometry, "uv", None) if texture is not None else None
        records = vertex_records(positions, indices, getattr(geometry, "colours", None), uv)
        vblock = iblock = -1
        if nv:
            vblock = self.vertex_arena.alloc(nv)
            self.vertex_arena.write(vblock, records)
        if nf:
            iblock = self.index_arena.alloc(3 * nf)
            self.index_arena.write(iblock, indices)
        s = self._slots
        slot = s.new()
        s.command[slot] = (3 * nf, 1, max(iblock, 0), max(vblock, 0), 0)
        s.vertices[slot], s.faces[slot] = nv, nf
        s.tint[slot] = packed_tint(rep if object_id is None else object_id)
        s.target[slot] = False
        s.vblock[slot], s.iblock[slot] = vblock, iblock
        if texture is not None:
            s.tex_class[slot], s.tex_layer[slot] = self.textures.add(texture)
        lo, hi = (positions.min(axis=0), positions.max(axis=0)) if nv else (np.zeros(3), np.zeros(3))
        s.bound(slot, lo, hi)
        s.bind(rep, slot)

    def reserve(self, vertices: int, indices: int) -> None:
        """Room in the arenas for a batch of uploads of this many vertices and indices (``Arena.reserve``)."""
        self.vertex_arena.reserve(vertices)
        self.index_arena.reserve(indices)

    def set_morph_target(self, rep: int, targets: np.ndarray, colours: np.ndarray | None = None,
                         merge: np.ndarray | None = None) -> None:
        """Give an uploaded representation its morph target (replacing any it had).

        targets : (nv, 3) float — the position each of ``rep``'s nv vertices morphs
            to, on the next coarser level (``morph_targets``). Stored in the vertex
            records with the coarser level's normals (``target_normals``, from the
            rep's own triangles): read back, patched, written — between frames
            nothing is in flight, so the read does not stall. ``colours``: (nv, 3) uint8, the
            targets' colours (None: each vertex keeps its own). ``merge``: the morph map, which
            says which vertices share a target (``target_normals``; None: those at equal
            positions). Dropped with the representation (``free``, or ``upload`` over it).
            Raises KeyError if ``rep`` is not uploaded, ValueError on a wrong shape or
            non-finite targets.
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
            records["target_colour"] = records["colour"] if colours is None else pack_colours(colours, nv)
            if self._slots.faces[slot]:
                indices = np.frombuffer(self.index_arena.read(int(self._slots.iblock[slot])), np.uint32)
                records["target_normal"] = pack_normals(target_normals(t, indices.reshape(-1, 3), merge))
            self.vertex_arena.write(block, records)
            # A morphing vertex travels between its two positions: the box covers both ends.
            c, h = self._slots.centre[slot], self._slots.half[slot]
            lo, hi = np.minimum(c - h, t.min(axis=0)), np.maximum(c + h, t.max(axis=0))
            self._slots.bound(slot, lo, hi)
        self._slots.target[slot] = True

    def enable_sky(self) -> None:
        """Paint the sky gradient behind the scene from now on (``client.sky``)."""
        if self.sky is None:
            self.sky = Sky(self.ctx)

    def have_morph_targets(self, reps: np.ndarray) -> np.ndarray:
        """(s,) bool — which of ``reps`` are uploaded with a morph target (vectorised: the per-frame check)."""
        slots = self._slots.lookup(np.asarray(reps, np.int64))
        return (slots >= 0) & self._slots.target[np.maximum(slots, 0)] if slots.size else np.zeros(0, bool)

    def has_morph_target(self, rep: int) -> bool:
        """Whether ``rep`` is uploaded with a morph target."""
        slot = self.meshes.get(int(rep))
        return slot is not None and bool(self._slots.target[slot])

    def free(self, rep: int) -> None:
        """Drop a representation (its morph target too); unknown ids are ignored.

        An arena left too sparse (``Arena.fragmented``) is compacted here, between frames.
        """
        blocks = self._slots.remove(int(rep))
        if blocks is None:
            return
        vblock, iblock, tex_class, tex_layer = blocks
        if tex_class >= 0:
            self.textures.remove(tex_class, tex_layer)
        if vblock >= 0:
            self.vertex_arena.free(vblock)
        if iblock >= 0:
            self.index_arena.free(iblock)
        self.vertex_arena.maybe_compact()
        self.index_arena.maybe_compact()

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

    def _view_projection(self, forward: np.ndarray, up: np.ndarray, near: float, far: float) -> np.ndarray:
        """(4, 4) float64 camera-relative projection @ view rotation (``proto.camera``)."""
        return projection_matrix(self.fov_y, self.width / self.height, near, far) @ view_matrix(np.zeros(3), forward, up)

    def in_view(self, reps: np.ndarray, eye, forward, up, near: float, far: float) -> tuple[np.ndarray, np.ndarray]:
        """For a camera about to draw: (s,) bool, which of ``reps`` are resident and in its view (as ``draw``
        culls them), and (s,) int64, the vertices of each resident one (0 where not resident)."""
        reps = np.asarray(reps, np.int64).ravel()
        slots = self._slots.lookup(reps)
        here = slots >= 0
        seen = here.copy()
        vertices = np.zeros(reps.size, np.int64)
        if here.any():
            eye = np.asarray(eye, np.float64)
            vp = self._view_projection(np.asarray(forward, np.float64), np.asarray(up, np.float64), near, far)
            if self.cull:
                seen[here] = in_frustum(self._slots, slots[here], vp, eye)
            vertices[here] = self._slots.vertices[slots[here]]
        return seen, vertices

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
        eye = np.asarray(eye, np.float64)
        up = np.asarray(up, np.float64)
        forward = np.asarray(forward, np.float64)
        vp64 = self._view_projection(forward, up, near, far)
        plan = plan_frame(reps, self._slots, vp64, eye, weights=weights, algorithms=algorithms, levels=levels,
                          cull=self.cull)
        self.missing += plan.missing
        self.unmorphed += plan.unmorphed
        n, per_alg = len(plan), plan.draws

        if n > self._draw_capacity:  # orphaning keeps the buffers' names, so the VAOs stay valid
            while self._draw_capacity < n:
                self._draw_capacity *= 2
            self._draw_rows.orphan(self._draw_capacity * DRAW.itemsize)
            self._commands.orphan(self._draw_capacity * 20)
        if n:
            self._draw_rows.write(plan.rows)
            self._commands.write(plan.commands)
        if self._vaos_stale:
            self._build_vaos()

        vp = vp64.astype(np.float32)
        vp_bytes = vp.T.tobytes()
        values = {
            "u_eye": tuple(eye),
            "u_up": tuple(up / np.linalg.norm(up)),
            "u_sun": tuple(key_light(forward, up) if self.sun is None else self.sun),
            "u_false_colour": bool(self.false_colour),
            "u_object_colours": self.colours == "objects",
            "u_light_mix": (0.5, 0.6) if self.sun is None else (0.8, 0.45),
            "u_level_scale": float(self.false_colour_levels),
            "u_eye_wrap": tuple(eye - _TEXTURE_PERIOD * np.floor(eye / _TEXTURE_PERIOD)),
        }
        for k in np.flatnonzero(per_alg).tolist():
            uniforms = self._uniforms[k]
            uniforms["u_view_projection"].write(vp_bytes)
            for name, value in values.items():
                if uniforms[name] is not None:
                    uniforms[name].value = value

        if per_alg[_TEXTURED]:
            self.textures.flush()
            self.textures.use(0)
        c1 = time.perf_counter()
        if self.sky is not None:
            self.fbo.use()
            self.sky.render(vp64, up, values["u_sun"])
        self.ctx.finish()  # uploads (and the sky) belong to no frame's selection: finish them outside the fence
        t0 = time.perf_counter()
        splats = 0
        with self._time_query:
            self.fbo.use()
            self.ctx.enable_only(moderngl.DEPTH_TEST)
            if self.sky is None:
                self.fbo.clear(*BACKGROUND, 1.0, depth=1.0)
            else:
                self.fbo.color_mask = (False, False, False, False)
                self.fbo.clear(depth=1.0)
                self.fbo.color_mask = (True, True, True, True)
                self.fbo.use()  # moderngl applies a framebuffer's colour mask when it is bound
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
        terms = FrameTerms(triangles=plan.triangles.tolist(), vertices=plan.vertices.tolist(), pixels=pixels,
                           draws=per_alg.astype(np.int64).tolist())
        return FrameStats(
            time=elapsed,
            triangles=int(plan.triangles.sum()),
            vertices=int(plan.vertices.sum()),
            draws=n,
            morphs=plan.morphs,
            pixels=int(sum(pixels)),
            gpu_time=gpu if self.gpu_time_plausible(gpu, elapsed, t2 - t1) else None,
            cpu_time=(c1 - c0) + (t1 - t0),
            prepare_time=c1 - c0,
            culled=plan.culled,
            splats=splats,
            terms=terms,
            seen=plan.seen,
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
        self.textures.release()
        self._draw_rows.release()
        self._commands.release()
        for prog in self.programs:
            prog.release()
        self.programs = None
        if self.sky is not None:
            self.sky.release()
            self.sky = None
        self.fbo.release()
        self._color.release()
        self._depth.release()
        if self._own_ctx:
            self.ctx.release()

    def __enter__(self) -> "Renderer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()
