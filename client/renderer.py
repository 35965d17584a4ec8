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

__all__ = ["FrameStats", "Renderer", "RendererError", "BACKGROUND", "VERTEX", "object_tint"]

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
    """One drawn frame: fenced wall time (s) and what was drawn."""

    time: float
    triangles: int
    vertices: int
    draws: int


#: Interleaved vertex layout: world position and the object's tint (RGBA8, normalised). 16 bytes.
VERTEX = np.dtype([("position", "<f4", 3), ("tint", "u1", 4)])


@dataclass
class _Mesh:
    vao: moderngl.VertexArray
    vbo: moderngl.Buffer
    ibo: moderngl.Buffer
    faces: int
    vertices: int

    def release(self) -> None:
        self.vao.release()
        self.vbo.release()
        self.ibo.release()


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

    def __init__(self, width: int, height: int, *, fov_y: float = 60.0, backend: str | None = "egl") -> None:
        try:
            kwargs = {"backend": backend} if backend else {}
            self.ctx = moderngl.create_standalone_context(require=330, **kwargs)
        except Exception as exc:
            raise RendererError(f"cannot create a GL context ({exc}); {_EGL_HINT}") from exc
        self.width, self.height, self.fov_y = int(width), int(height), float(fov_y)
        self._color = self.ctx.renderbuffer((self.width, self.height))
        self._depth = self.ctx.depth_renderbuffer((self.width, self.height))
        self.fbo = self.ctx.framebuffer(color_attachments=[self._color], depth_attachment=self._depth)
        self.program = self.ctx.program(
            vertex_shader=(_SHADERS / "mesh.vert.glsl").read_text(),
            fragment_shader=(_SHADERS / "mesh.frag.glsl").read_text(),
        )
        self.meshes: dict[int, _Mesh] = {}
        self.missing = 0
        """Draw requests for reps not uploaded, in total (skipped, never drawn)."""
        self._warm_up()

    def _warm_up(self) -> None:
        """Draw one triangle once, so llvmpipe's shader compile (~25 ms) is not in frame 0's time."""
        tri = Geometry(np.array([[-1, -1, -5], [1, -1, -5], [0, 1, -5]], np.float32), np.array([[0, 1, 2]], np.uint32))
        self.upload(-1, tri)
        self.draw(np.array([-1]), np.zeros(3), np.array([0.0, 0.0, -1.0]), np.array([0.0, 1.0, 0.0]), 0.1, 10.0)
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

    def free(self, rep: int) -> None:
        """Release a representation's GL objects; unknown ids are ignored."""
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
    ) -> FrameStats:
        """Draw ``reps`` (s,) int from the pose (eye, forward, up: (3,) float) and time it.

        Returns the fenced wall time of clear + draws + ``ctx.finish()``, and
        the triangles, vertices and draw calls actually issued.
        """
        eye = np.asarray(eye, np.float64)
        up = np.asarray(up, np.float64)
        rotation = view_matrix(np.zeros(3), forward, up)
        vp = projection_matrix(self.fov_y, self.width / self.height, near, far) @ rotation
        prog = self.program
        prog["u_view_projection"].write(vp.T.astype("f4").tobytes())
        prog["u_eye"].value = tuple(eye)
        prog["u_up"].value = tuple(up / np.linalg.norm(up))
        prog["u_sun"].value = tuple(_key_light(np.asarray(forward, np.float64), up))
        meshes = [self.meshes.get(int(r)) for r in np.asarray(reps).ravel()]
        drawn = [m for m in meshes if m is not None]
        self.missing += len(meshes) - len(drawn)

        self.ctx.finish()  # uploads still in flight belong to no frame: finish them outside the fence
        t0 = time.perf_counter()
        self.fbo.use()
        self.ctx.enable_only(moderngl.DEPTH_TEST)
        self.fbo.clear(*BACKGROUND, 1.0, depth=1.0)
        for mesh in drawn:
            mesh.vao.render(moderngl.TRIANGLES)
        self.ctx.finish()
        elapsed = time.perf_counter() - t0

        return FrameStats(
            time=elapsed,
            triangles=sum(m.faces for m in drawn),
            vertices=sum(m.vertices for m in drawn),
            draws=len(drawn),
        )

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
        self.fbo.release()
        self._color.release()
        self._depth.release()
        self.ctx.release()

    def __enter__(self) -> "Renderer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()
