"""The renderer's bookkeeping of resident representations, without GL: one slot per representation.

A slot is a row of numpy tables (its indirect-draw command template, vertex
and triangle counts, tint, whether it has a morph target, its arena blocks and
bounding sphere), so a frame gathers what it draws with fancy indexing
instead of a Python loop. Rep ids map to slots through a dense int32 table
indexed by rep id; ids beyond it (and negative ones) go to a sorted overflow,
so ``lookup`` resolves a whole frame's reps in one vectorised pass.
"""

from __future__ import annotations

import numpy as np

__all__ = ["SlotTable", "DENSE_LIMIT"]

#: Rep ids below this live in the dense lookup table (≤ 64 MiB); others (and negatives) in a sorted overflow.
DENSE_LIMIT = 1 << 24

_COLUMNS = ("command", "vertices", "faces", "tint", "target", "vblock", "iblock", "centre", "half", "sphere",
            "tex_class", "tex_layer")


def _sphere(centre: np.ndarray, half: np.ndarray) -> tuple[float, float, float, float]:
    """A box's bounding sphere for the float32 table: the radius grows by more than float32 rounds the centre
    (2⁻²⁴ relative), so the rounded sphere still holds the box."""
    r = float(np.linalg.norm(half))
    return (*map(float, centre), r + 1e-6 * (float(np.abs(centre).max()) + r))


class SlotTable:
    """Per-slot tables (grown geometrically) and the rep id → slot map.

    command  : (c, 5) uint32 — DrawElementsIndirectCommand template: count, 1, firstIndex, baseVertex, 0
    vertices, faces : (c,) int64 — the representation's vertex and triangle counts
    tint     : (c,) uint32 — RGBA8 packed little-endian
    target   : (c,) bool — whether a morph target is set
    vblock, iblock : (c,) int64 — vertex / index arena offsets, −1: none
    centre, half : (c, 3) float64 — the box over the fine positions and the morph target
    sphere   : (c, 4) float32 — its bounding sphere x, y, z, r (half the bytes a frame gathers),
               r padded over float32's rounding
    tex_class, tex_layer : (c,) int32 / float32 — its texture's size class and layer (``client.textures``),
               −1 / 0: no texture
    meshes   : resident rep id → slot
    """

    def __init__(self, capacity: int = 256) -> None:
        self.command = np.zeros((0, 5), np.uint32)
        self.vertices = np.zeros(0, np.int64)
        self.faces = np.zeros(0, np.int64)
        self.tint = np.zeros(0, np.uint32)
        self.target = np.zeros(0, bool)
        self.vblock = np.zeros(0, np.int64)
        self.iblock = np.zeros(0, np.int64)
        self.centre = np.zeros((0, 3), np.float64)
        self.half = np.zeros((0, 3), np.float64)
        self.sphere = np.zeros((0, 4), np.float32)
        self.tex_class = np.zeros(0, np.int32)
        self.tex_layer = np.zeros(0, np.float32)
        self.grow(capacity)
        self._free: list[int] = list(range(capacity - 1, -1, -1))
        self._table = np.full(1024, -1, np.int32)
        self._overflow: dict[int, int] = {}
        self._overflow_keys: np.ndarray | None = np.zeros(0, np.int64)
        self._overflow_slots = np.zeros(0, np.int32)
        self.meshes: dict[int, int] = {}

    def grow(self, capacity: int) -> None:
        old = self.vertices.size
        for name in _COLUMNS:
            a = getattr(self, name)
            b = np.zeros((capacity,) + a.shape[1:], a.dtype)
            b[:old] = a
            setattr(self, name, b)
        self.vblock[old:] = -1
        self.iblock[old:] = -1
        self.tex_class[old:] = -1

    def new(self) -> int:
        """A free slot (the tables grow when none is left); ``bind`` it to a rep once filled."""
        if not self._free:
            old = self.vertices.size
            self.grow(2 * old)
            self._free = list(range(2 * old - 1, old - 1, -1))
        return self._free.pop()

    def bind(self, rep: int, slot: int) -> None:
        self.meshes[rep] = slot
        if 0 <= rep < DENSE_LIMIT:
            if rep >= self._table.size:
                table = np.full(1 << int(rep).bit_length(), -1, np.int32)
                table[: self._table.size] = self._table
                self._table = table
            self._table[rep] = slot
        else:
            self._overflow[rep] = slot
            self._overflow_keys = None

    def remove(self, rep: int) -> tuple[int, int, int, int] | None:
        """Unbind ``rep`` and recycle its slot; returns the (vertex, index) arena blocks it held (−1: none)
        and its texture's (class, layer) (−1, −1: none).

        None if ``rep`` is not resident.
        """
        slot = self.meshes.pop(rep, None)
        if slot is None:
            return None
        if 0 <= rep < DENSE_LIMIT:
            self._table[rep] = -1
        else:
            del self._overflow[rep]
            self._overflow_keys = None  # rebuilt at the next lookup
        blocks = (int(self.vblock[slot]), int(self.iblock[slot]), int(self.tex_class[slot]),
                  int(self.tex_layer[slot]) if self.tex_class[slot] >= 0 else -1)
        self.tex_class[slot], self.tex_layer[slot] = -1, 0.0
        self.command[slot] = 0
        self.vertices[slot] = self.faces[slot] = 0
        self.target[slot] = False
        self.vblock[slot] = self.iblock[slot] = -1
        self._free.append(slot)
        return blocks

    def bound(self, slot: int, lo: np.ndarray, hi: np.ndarray) -> None:
        """Set the slot's box to [lo, hi] (3,) and its bounding sphere."""
        self.centre[slot], self.half[slot] = (lo + hi) / 2.0, (hi - lo) / 2.0
        self.sphere[slot] = _sphere(self.centre[slot], self.half[slot])

    def lookup(self, reps: np.ndarray) -> np.ndarray:
        """Slots (s,) int32 of ``reps`` (s,) int64, −1 where not resident; vectorised."""
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
