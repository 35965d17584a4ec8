"""The sky a scene is drawn against: a gradient from the horizon to the zenith, haze below the horizon.

One full-screen triangle (``shaders/sky.*.glsl``) computes each pixel's view
direction from the inverse camera-relative view-projection, so the horizon
sits where the scene's horizon is whatever the camera's pitch and roll. The
renderer paints it before its fenced frame (``client.renderer``): it costs the
same every frame, whatever the selection draws.
"""

from __future__ import annotations

from pathlib import Path

import moderngl
import numpy as np

__all__ = ["Sky", "ZENITH", "HORIZON", "BELOW"]

ZENITH = (0.30, 0.50, 0.82)
HORIZON = (0.78, 0.86, 0.93)
#: Below the horizon, where a scene has no ground to draw: a haze, not the sky's blue.
BELOW = (0.56, 0.57, 0.52)
_SHADERS = Path(__file__).with_name("shaders")


class Sky:
    """The sky pass on a moderngl context (which it does not own)."""

    def __init__(self, ctx: moderngl.Context) -> None:
        self.ctx = ctx
        self.program = ctx.program(vertex_shader=(_SHADERS / "sky.vert.glsl").read_text(),
                                   fragment_shader=(_SHADERS / "sky.frag.glsl").read_text())
        for name, value in (("u_zenith", ZENITH), ("u_horizon", HORIZON), ("u_below", BELOW)):
            self.program[name].value = value
        self.vao = ctx.vertex_array(self.program, [])

    def render(self, view_projection: np.ndarray, up: np.ndarray, sun) -> None:
        """Paint the bound framebuffer's colour (no depth test or write).

        view_projection : (4, 4) float, row-major camera-relative projection @ view rotation
        up, sun : (3,) world up and the direction towards the sun
        """
        inverse = np.linalg.inv(np.asarray(view_projection, np.float64)).astype(np.float32)
        self.program["u_inverse_view_projection"].write(inverse.T.tobytes())
        up = np.asarray(up, np.float64)
        self.program["u_up"].value = tuple(up / np.linalg.norm(up))
        self.program["u_sun"].value = tuple(float(x) for x in sun)
        self.ctx.disable(moderngl.DEPTH_TEST)
        self.vao.render(moderngl.TRIANGLES, vertices=3)

    def release(self) -> None:
        self.vao.release()
        self.program.release()
