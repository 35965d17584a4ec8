"""Resident base-colour textures on the GPU: one texture array per size class, one layer per representation.

The textured algorithm draws every representation in one multi-draw, so a draw
cannot bind its own texture. Textures instead live in ``GL_TEXTURE_2D_ARRAY`` s,
one per *size class* (a square power-of-two side, ``SIDES``), and a draw's row
(``client.frame_plan.DRAW``) names its class and layer; the fragment shader
picks the class's sampler (``mesh_textured.frag.glsl``). The server sends square
power-of-two textures (``server.scene.texcoords``); any other texture a payload
brings is resampled to the class of its larger side here, since the UVs are
normalised the surface does not notice.

A class's array grows geometrically (its layers read back and written into
one twice the size) and its freed layers are reused, so an upload or a free
touches one layer. Mipmaps keep a distant checker from aliasing: moderngl
writes only a texture array's base level, so a class whose layers changed has
its mipmaps rebuilt once, at ``flush`` — the renderer calls it before a frame,
outside the fence, as it finishes other uploads there.

Layer bookkeeping (``Layers``) is free of GL, so its rules are tested without a
context.
"""

from __future__ import annotations

import numpy as np

__all__ = ["SIDES", "Layers", "TextureStore", "size_class"]

#: The sides of the size classes, class k holding textures of SIDES[k] × SIDES[k] px.
SIDES = tuple(8 << k for k in range(10))  # 8 .. 4096, proto.texture's cap


def size_class(height: int, width: int) -> int:
    """The class of a (height × width) texture: the smallest side in ``SIDES`` not below its larger side."""
    larger = max(int(height), int(width), 1)
    for k, side in enumerate(SIDES):
        if side >= larger:
            return k
    raise ValueError(f"texture {width}×{height} is larger than {SIDES[-1]} px a side")


class Layers:
    """The layers of one class's array: which are in use, which are free, how many the array has."""

    def __init__(self, capacity: int = 4) -> None:
        self.capacity = int(capacity)
        self._free: list[int] = list(range(self.capacity - 1, -1, -1))
        self.used = 0

    def take(self) -> tuple[int, bool]:
        """(a free layer, whether the array had to double to have one)."""
        grew = False
        if not self._free:
            self._free = list(range(2 * self.capacity - 1, self.capacity - 1, -1))
            self.capacity *= 2
            grew = True
        self.used += 1
        return self._free.pop(), grew

    def give(self, layer: int) -> None:
        if not 0 <= layer < self.capacity or layer in self._free:
            raise ValueError(f"layer {layer} is not in use")
        self._free.append(int(layer))
        self.used -= 1


def _rgba(texture: np.ndarray, side: int) -> np.ndarray:
    """(side, side, 4) uint8 rows bottom-up (GL's t = 0 first) from an (h, w, 3) texture rows top-down."""
    t = np.asarray(texture, np.uint8)
    if t.shape[:2] != (side, side):
        from PIL import Image

        t = np.asarray(Image.fromarray(np.ascontiguousarray(t), "RGB").resize((side, side), Image.Resampling.LANCZOS))
    out = np.full((side, side, 4), 255, np.uint8)
    out[:, :, :3] = t[::-1]
    return out


class TextureStore:
    """The texture arrays of a GL context (``moderngl``), their layers and which need their mipmaps rebuilt."""

    def __init__(self, ctx) -> None:
        self.ctx = ctx
        self.arrays: list = [None] * len(SIDES)
        self.layers = [Layers() for _ in SIDES]
        self._dirty: set[int] = set()

    def add(self, texture: np.ndarray) -> tuple[int, int]:
        """Put an (h, w, 3) uint8 texture (rows top-down) in its class's array; returns (class, layer)."""
        t = np.asarray(texture)
        if t.ndim != 3 or t.shape[2] != 3 or t.dtype != np.uint8:
            raise ValueError(f"texture must be (h, w, 3) uint8, got {t.dtype} {t.shape}")
        k = size_class(*t.shape[:2])
        side = SIDES[k]
        layers = self.layers[k]
        layer, grew = layers.take()
        if self.arrays[k] is None or grew:
            self._grow(k, layers.capacity)
        self.arrays[k].write(_rgba(t, side).tobytes(), viewport=(0, 0, layer, side, side, 1))
        self._dirty.add(k)
        return k, layer

    def remove(self, k: int, layer: int) -> None:
        """Free a layer (its pixels stay until the layer is taken again; nothing draws them)."""
        self.layers[k].give(layer)

    def _grow(self, k: int, capacity: int) -> None:
        side = SIDES[k]
        new = self.ctx.texture_array((side, side, capacity), 4)
        old = self.arrays[k]
        if old is not None:
            data = old.read()
            new.write(data, viewport=(0, 0, 0, side, side, old.layers))
            old.release()
        new.repeat_x = new.repeat_y = True
        new.filter = (self.ctx.LINEAR_MIPMAP_LINEAR, self.ctx.LINEAR)
        new.anisotropy = 4.0
        self.arrays[k] = new

    def flush(self) -> None:
        """Rebuild the mipmaps of every class whose layers changed since the last flush."""
        for k in sorted(self._dirty):
            self.arrays[k].build_mipmaps()
        self._dirty.clear()

    def use(self, first_unit: int = 0) -> None:
        """Bind class k's array to texture unit first_unit + k (classes without one stay unbound)."""
        for k, array in enumerate(self.arrays):
            if array is not None:
                array.use(first_unit + k)

    @property
    def nbytes(self) -> int:
        """GPU bytes the arrays hold (RGBA8 and a third more for the mipmaps)."""
        return sum(4 * SIDES[k] ** 2 * self.layers[k].capacity * 4 // 3 for k, a in enumerate(self.arrays)
                   if a is not None)

    def release(self) -> None:
        for array in self.arrays:
            if array is not None:
                array.release()
        self.arrays = [None] * len(SIDES)
        self.layers = [Layers() for _ in SIDES]
        self._dirty.clear()
