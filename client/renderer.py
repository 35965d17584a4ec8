"""Headless moderngl renderer: resident geometry on the GPU, one fenced draw per frame.

The frame time this module measures is what the server's cost model is fitted
to, so the fence holds drawing only: clear, one draw per representation and
``ctx.finish()``. Uploads and frees happen between frames, outside it.

Skeleton layout: one VBO + IBO + VAO per representation (a later change moves
to arenas and multi-draw). The object tint is a per-vertex attribute, not a
uniform: on llvmpipe a uniform change between draws costs about as much as the
draw itself (measured: 500 small draws 17 ms with a per-draw uniform, 7 ms
without), and multi-draw will not allow per-draw uniforms anyway. No back-face culling: simplified meshes do not
keep a consistent winding, and the flat shading takes its normal from
screen-space derivatives, so it faces the viewer either way.

Geomorphing (Zach 2002, 3.4): a representation can carry a morph target, the
position each of its vertices morphs to on the next coarser level
(``morph_targets``: coarse positions gathered through the level's morph map),
in a second buffer with its own VAO over a second program
(``mesh_morph.vert.glsl``). A draw with weight w < 1 blends w · fine +
(1 − w) · target; only those draws pay the per-draw ``u_weight`` uniform. The
static draws go first, then the morphing ones, so the program changes once per
frame. A morph costs the finer level's triangles and vertices, and is counted so.
"""

from __future__ import annotations

import colorsys
import time
from dataclasses import dataclass
from pathlib import Path

import moderngl
import numpy as np

from proto.camera import projection_matrix, view_matrix
from proto.geometry import Geometry

__all__ = ["FrameStats", "Renderer", "RendererError", "BACKGROUND", "VERTEX", "object_tint", "morph_targets"]

#: Clear colour (sky), RGB in [0, 1].
BACKGROUND = (0.62, 0.74, 0.86)
_SHADERS = Path(__file__).with_name("shaders")
_EGL_HINT = (
    "walkstream's client renders headless through EGL and needs Mesa's EGL "
    "(apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri)"
)


class RendererError(RuntimeError):
    """The GL context could not be created."""


@dataclass(frozen=True)
class FrameStats:
    """One drawn frame: fenced wall time (s) and what was drawn.

    A morphing representation counts its own (the finer level's) triangles and
    vertices; ``morphs`` is how many of the ``draws`` were morphing (weight < 1).
    """

    time: float
    triangles: int
    vertices: int
    draws: int
    morphs: int = 0


#: Interleaved vertex layout: world position and the object's tint (RGBA8, normalised). 16 bytes.
VERTEX = np.dtype([("position", "<f4", 3), ("tint", "u1", 4)])


@dataclass
class _Morph:
    """A representation's morph target: 12 bytes per vertex and a VAO over the morph program."""

    vao: moderngl.VertexArray
    tbo: moderngl.Buffer

    def release(self) -> None:
        self.vao.release()
        self.tbo.release()


@dataclass
class _Mesh:
    vao: moderngl.VertexArray
    vbo: moderngl.Buffer
    ibo: moderngl.Buffer
    faces: int
    vertices: int
    morph: _Morph | None = None

    def release(self) -> None:
        if self.morph is not None:
            self.morph.release()
            self.morph = None
        self.vao.release()
        self.vbo.release()
        self.ibo.release()


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


def _key_light(forward: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Unit direction (3,) towards a light carried above, behind and right of the camera.

    A camera-borne key light lights every visible face (no black backs in a
    walkthrough) while the angle still separates the faces of a shape.
    """
    f = forward / np.linalg.norm(forward)
    s = np.cross(f, up)
    s /= np.linalg.norm(s)
    u = np.cross(s, f)
    light = -f + 0.6 * u + 0.35 * s
    return light / np.linalg.norm(light)


class Renderer:
    """An offscreen framebuffer (colour + depth) and the meshes resident on the GPU.

    width, height : framebuffer size in pixels
    fov_y : vertical field of view in degrees (the ``Hello`` value)
    backend : moderngl standalone backend; "egl" for headless, None for the platform default
    """

    morph_targets = staticmethod(morph_targets)

    def __init__(self, width: int, height: int, *, fov_y: float = 60.0, backend: str | None = "egl",
                 ctx: moderngl.Context | None = None) -> None:
        self._own_ctx = ctx is None
        if ctx is not None:
            self.ctx = ctx  # a window's context (``client.window``): drawn offscreen, then blitted
        else:
            try:
                kwargs = {"backend": backend} if backend else {}
                self.ctx = moderngl.create_standalone_context(require=330, **kwargs)
            except Exception as exc:
                raise RendererError(f"cannot create a GL context ({exc}); {_EGL_HINT}") from exc
        self.width, self.height, self.fov_y = int(width), int(height), float(fov_y)
        self._color = self.ctx.renderbuffer((self.width, self.height))
        self._depth = self.ctx.depth_renderbuffer((self.width, self.height))
        self.fbo = self.ctx.framebuffer(color_attachments=[self._color], depth_attachment=self._depth)
        fragment = (_SHADERS / "mesh.frag.glsl").read_text()
        self.program = self.ctx.program(vertex_shader=(_SHADERS / "mesh.vert.glsl").read_text(),
                                        fragment_shader=fragment)
        self.morph_program = self.ctx.program(vertex_shader=(_SHADERS / "mesh_morph.vert.glsl").read_text(),
                                              fragment_shader=fragment)
        self._u_weight = self.morph_program["u_weight"]
        self.meshes: dict[int, _Mesh] = {}
        self.missing = 0
        """Draw requests for reps not uploaded, in total (skipped, never drawn)."""
        self.unmorphed = 0
        """Draw requests with weight < 1 for reps without a morph target, in total (drawn at full detail)."""
        self._warm_up()

    def _warm_up(self) -> None:
        """Draw one triangle statically and morphing, so llvmpipe's shader compiles (~25 ms each) are not in frame 0's time."""
        tri = Geometry(np.array([[-1, -1, -5], [1, -1, -5], [0, 1, -5]], np.float32), np.array([[0, 1, 2]], np.uint32))
        self.upload(-1, tri)
        self.set_morph_target(-1, tri.positions[[0, 0, 2]])
        self.draw(np.array([-1, -1]), np.zeros(3), np.array([0.0, 0.0, -1.0]), np.array([0.0, 1.0, 0.0]), 0.1, 10.0,
                  weights=np.array([1.0, 0.5]))
        self.free(-1)

    # ----------------------------------------------------------------- resident geometry

    def upload(self, rep: int, geometry: Geometry, object_id: int | None = None) -> None:
        """Put one representation on the GPU (replacing any with the same id).

        geometry.positions : (nv, 3) float32; geometry.indices : (nf, 3) uint32.
        object_id picks the tint, so all levels of one object share a colour. GPU memory:
        16 bytes per vertex (``VERTEX``: position + RGBA8 tint) and 12 per triangle.
        """
        self.free(rep)
        vertices = np.empty(geometry.vertices, VERTEX)
        vertices["position"] = geometry.positions
        tint = object_tint(rep if object_id is None else object_id)
        vertices["tint"] = [round(255 * c) for c in tint] + [255]
        vbo = self.ctx.buffer(vertices)
        ibo = self.ctx.buffer(np.ascontiguousarray(geometry.indices, np.uint32))
        vao = self.ctx.vertex_array(
            self.program, [(vbo, "3f 4f1", "in_pos", "in_tint")], index_buffer=ibo, index_element_size=4
        )
        self.meshes[rep] = _Mesh(vao, vbo, ibo, geometry.faces, geometry.vertices)

    def set_morph_target(self, rep: int, targets: np.ndarray) -> None:
        """Give an uploaded representation its morph target (replacing any it had).

        targets : (nv, 3) float — the position each of ``rep``'s nv vertices morphs
            to, on the next coarser level (``morph_targets``). GPU memory: 12 bytes
            per vertex. Released with the representation (``free``, or ``upload``
            over it). Raises KeyError if ``rep`` is not uploaded, ValueError on a
            wrong shape or non-finite targets.
        """
        mesh = self.meshes.get(rep)
        if mesh is None:
            raise KeyError(f"representation {rep} is not uploaded")
        t = np.asarray(targets)
        if t.shape != (mesh.vertices, 3):
            raise ValueError(f"morph target of representation {rep} must be ({mesh.vertices}, 3), got {t.shape}")
        t = np.ascontiguousarray(t, np.float32)
        if not np.isfinite(t).all():
            raise ValueError(f"morph target of representation {rep} is not finite")
        tbo = self.ctx.buffer(t)
        vao = self.ctx.vertex_array(
            self.morph_program,
            [(mesh.vbo, "3f 4f1", "in_pos", "in_tint"), (tbo, "3f", "in_target")],
            index_buffer=mesh.ibo,
            index_element_size=4,
        )
        if mesh.morph is not None:
            mesh.morph.release()
        mesh.morph = _Morph(vao, tbo)

    def has_morph_target(self, rep: int) -> bool:
        """Whether ``rep`` is uploaded with a morph target."""
        mesh = self.meshes.get(rep)
        return mesh is not None and mesh.morph is not None

    def free(self, rep: int) -> None:
        """Release a representation's GL objects (its morph target too); unknown ids are ignored."""
        mesh = self.meshes.pop(rep, None)
        if mesh is not None:
            mesh.release()

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
    ) -> FrameStats:
        """Draw ``reps`` (s,) int from the pose (eye, forward, up: (3,) float) and time it.

        weights : (s,) float in [0, 1] aligned with ``reps``, the morph weight of
            each (None: all 1). A rep with weight ≥ 1 is drawn as it is; one with
            weight < 1 and a morph target is drawn blended toward its coarser
            level (below 0 counts as 0); one with weight < 1 and no target is
            drawn as it is and counted in ``unmorphed``.
        Returns the fenced wall time of clear + draws + ``ctx.finish()``, and
        the triangles, vertices, draw calls and morphing draws actually issued.
        Raises ValueError if weights is not (s,) finite.
        """
        eye = np.asarray(eye, np.float64)
        up = np.asarray(up, np.float64)
        rotation = view_matrix(np.zeros(3), forward, up)
        vp = projection_matrix(self.fov_y, self.width / self.height, near, far) @ rotation
        reps = np.asarray(reps).ravel()
        if weights is None:
            drawn = [m for m in map(self.meshes.get, reps.tolist()) if m is not None]
            self.missing += reps.size - len(drawn)
            morphing: list[tuple[_Mesh, float]] = []
        else:
            drawn, morphing = self._split(reps, weights)
        uniforms = {
            "u_view_projection": vp.T.astype("f4").tobytes(),
            "u_eye": tuple(eye),
            "u_up": tuple(up / np.linalg.norm(up)),
            "u_sun": tuple(_key_light(np.asarray(forward, np.float64), up)),
        }
        for prog in (self.program, self.morph_program) if morphing else (self.program,):
            prog["u_view_projection"].write(uniforms["u_view_projection"])
            for name in ("u_eye", "u_up", "u_sun"):
                prog[name].value = uniforms[name]
        u_weight = self._u_weight

        self.ctx.finish()  # uploads still in flight belong to no frame: finish them outside the fence
        t0 = time.perf_counter()
        self.fbo.use()
        self.ctx.enable_only(moderngl.DEPTH_TEST)
        self.fbo.clear(*BACKGROUND, 1.0, depth=1.0)
        for mesh in drawn:
            mesh.vao.render(moderngl.TRIANGLES)
        for mesh, w in morphing:
            u_weight.value = w
            mesh.morph.vao.render(moderngl.TRIANGLES)
        self.ctx.finish()
        elapsed = time.perf_counter() - t0

        return FrameStats(
            time=elapsed,
            triangles=sum(m.faces for m in drawn) + sum(m.faces for m, _ in morphing),
            vertices=sum(m.vertices for m in drawn) + sum(m.vertices for m, _ in morphing),
            draws=len(drawn) + len(morphing),
            morphs=len(morphing),
        )

    def _split(self, reps: np.ndarray, weights: np.ndarray) -> tuple[list[_Mesh], list[tuple[_Mesh, float]]]:
        """The resident meshes of ``reps``: those drawn as they are, and (mesh, weight) of those morphing."""
        w = np.asarray(weights, np.float64).ravel()
        if w.shape != reps.shape:
            raise ValueError(f"weights must be aligned with reps ({reps.size},), got {np.shape(weights)}")
        if not np.isfinite(w).all():
            raise ValueError("morph weights must be finite")
        drawn: list[_Mesh] = []
        morphing: list[tuple[_Mesh, float]] = []
        missing = unmorphed = 0
        for rep, weight in zip(reps.tolist(), w.tolist()):
            mesh = self.meshes.get(rep)
            if mesh is None:
                missing += 1
            elif weight >= 1.0:
                drawn.append(mesh)
            elif mesh.morph is not None:
                morphing.append((mesh, max(weight, 0.0)))
            else:
                unmorphed += 1
                drawn.append(mesh)
        self.missing += missing
        self.unmorphed += unmorphed
        return drawn, morphing

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
        """Release every GL object and the context."""
        for rep in list(self.meshes):
            self.free(rep)
        self.program.release()
        self.morph_program.release()
        self.fbo.release()
        self._color.release()
        self._depth.release()
        if self._own_ctx:
            self.ctx.release()

    def __enter__(self) -> "Renderer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()
