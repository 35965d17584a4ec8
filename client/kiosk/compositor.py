"""Blend the kiosk's overlay image over the renderer's frame, after the timed draw.

The renderer's offscreen framebuffer is what the window shows (``client.window.Window.present`` blits it)
and what screenshots read (``Renderer.read_image``), so the overlay is drawn into it: a full-frame quad
textured with ``client.kiosk.overlay.Overlay``'s RGBA image and alpha-blended. It happens after the
renderer's fence has closed, so the measured frame time — the cost model's input — never includes it;
the next frame's draw begins with ``ctx.finish()`` outside its fence, so it does not leak into that one
either. The texture is uploaded only when the image changed.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import moderngl
import numpy as np

if TYPE_CHECKING:
    from ..renderer import Renderer

__all__ = ["Compositor"]

_SHADERS = Path(__file__).resolve().parents[1] / "shaders"


class Compositor:
    """Draws an RGBA image (height, width, 4) uint8, rows top-down, over ``renderer``'s framebuffer."""

    def __init__(self, renderer: "Renderer") -> None:
        self.renderer = renderer
        ctx = self.ctx = renderer.ctx
        self.program = ctx.program(vertex_shader=(_SHADERS / "overlay.vert.glsl").read_text(),
                                   fragment_shader=(_SHADERS / "overlay.frag.glsl").read_text())
        self.texture = ctx.texture((renderer.width, renderer.height), 4)
        self.texture.filter = (moderngl.NEAREST, moderngl.NEAREST)  # one texel per pixel: no blur on text
        self.vao = ctx.vertex_array(self.program, [])
        self.uploads = 0
        """Textures uploaded so far (one per changed image)."""

    def draw(self, image: np.ndarray, changed: bool = True) -> None:
        """Blend ``image`` over the renderer's last frame; ``changed`` False reuses the uploaded texture."""
        h, w = image.shape[:2]
        if (w, h) != (self.renderer.width, self.renderer.height) or image.shape[2] != 4:
            raise ValueError(f"the overlay must be {self.renderer.height}×{self.renderer.width}×4, got {image.shape}")
        if changed or self.uploads == 0:
            self.texture.write(np.ascontiguousarray(image, np.uint8).tobytes())
            self.uploads += 1
        ctx = self.ctx
        self.renderer.fbo.use()
        ctx.enable_only(moderngl.BLEND)  # no depth test: the overlay lies over everything
        ctx.blend_func = moderngl.SRC_ALPHA, moderngl.ONE_MINUS_SRC_ALPHA
        self.texture.use(0)
        self.program["u_overlay"] = 0
        self.vao.render(moderngl.TRIANGLE_STRIP, vertices=4)
        ctx.disable(moderngl.BLEND)

    def release(self) -> None:
        for obj in (self.vao, self.texture, self.program):
            obj.release()
