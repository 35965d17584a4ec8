"""A sub-allocator over one growable GPU buffer: resident geometry in a few large buffers.

One buffer per kind of data (vertices, indices) instead of a buffer per
representation lets a frame be a single multi-draw over shared VAOs. The arena
hands out blocks of fixed-size elements (a vertex record, an index) by first
fit from a free list of holes kept sorted by offset, coalescing a freed block
with its neighbours. Space above the highest live block (the tail) is not a
hole: freeing the top block lowers ``top`` instead.

When neither a hole nor the tail fits, the arena either compacts (if the holes
are a large share of it) or grows: a new, larger buffer and a GPU-side
``ctx.copy_buffer`` of the live range. Both replace ``buffer``, so whoever
built VAOs over it registers a listener (``listeners``) and rebuilds them;
compaction also moves blocks, and the listener receives the ``Relocation``.

The bookkeeping runs per upload and free, never per frame: live blocks are a
dict (offset → size), holes two sorted numpy arrays, so first fit is one
vectorised scan.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import moderngl
import numpy as np

__all__ = ["Arena", "Relocation"]


@dataclass(frozen=True)
class Relocation:
    """Where compaction moved the live blocks: ``old[i]`` → ``new[i]``, sorted by ``old`` (int64 element offsets)."""

    old: np.ndarray
    new: np.ndarray

    def map(self, offsets: np.ndarray) -> np.ndarray:
        """New offsets of the given old block offsets (every one must be a live block's); vectorised."""
        offsets = np.asarray(offsets, np.int64)
        i = np.searchsorted(self.old, offsets)
        if offsets.size and (i.max() >= self.old.size or (self.old[np.minimum(i, self.old.size - 1)] != offsets).any()):
            raise KeyError("an offset is not the start of a relocated block")
        return self.new[i]

    def as_dict(self) -> dict[int, int]:
        return dict(zip(self.old.tolist(), self.new.tolist()))


#: listener(arena, relocation): relocation is None after a growth (offsets unchanged, buffer replaced).
Listener = Callable[["Arena", "Relocation | None"], None]


class Arena:
    """Blocks of ``element_size``-byte elements in one moderngl buffer, addressed by element offset.

    capacity : initial size in elements (the buffer grows by ``growth`` as needed)
    compact_ratio, compact_min : ``fragmented`` when the holes below ``top``
        exceed ``compact_ratio`` × the live elements and ``compact_min`` elements;
        then ``maybe_compact`` (and an allocation that would otherwise grow) compacts.
    """

    def __init__(self, ctx: moderngl.Context, element_size: int, capacity: int = 1 << 16, *,
                 growth: float = 2.0, compact_ratio: float = 0.5, compact_min: int = 1 << 14) -> None:
        if element_size <= 0 or capacity <= 0 or growth <= 1.0:
            raise ValueError("element_size and capacity must be positive, growth > 1")
        self.ctx = ctx
        self.element_size = int(element_size)
        self.capacity = int(capacity)
        self.growth = float(growth)
        self.compact_ratio = float(compact_ratio)
        self.compact_min = int(compact_min)
        self.buffer = ctx.buffer(reserve=self.capacity * self.element_size)
        self.listeners: list[Listener] = []
        self._blocks: dict[int, int] = {}
        self._hole_off = np.zeros(0, np.int64)
        self._hole_len = np.zeros(0, np.int64)
        self.top = 0
        """End of the highest live block (elements); the tail above it is free."""
        self.used = 0
        """Elements in live blocks."""
        self.grows = 0
        self.compactions = 0

    # ----------------------------------------------------------------- state

    @property
    def holes(self) -> int:
        """Free elements below ``top`` (fragmentation)."""
        return self.top - self.used

    @property
    def fragmented(self) -> bool:
        h = self.holes
        return h > self.compact_ratio * self.used and h >= self.compact_min

    def blocks(self) -> tuple[np.ndarray, np.ndarray]:
        """Live blocks as (offsets, sizes), int64 sorted by offset."""
        off = np.fromiter(self._blocks.keys(), np.int64, len(self._blocks))
        size = np.fromiter(self._blocks.values(), np.int64, len(self._blocks))
        order = np.argsort(off)
        return off[order], size[order]

    def free_list(self) -> tuple[np.ndarray, np.ndarray]:
        """Holes as (offsets, sizes), sorted by offset, never adjacent to each other or to ``top``."""
        return self._hole_off.copy(), self._hole_len.copy()

    def size_of(self, offset: int) -> int:
        """Elements in the live block at ``offset`` (KeyError if none starts there)."""
        return self._blocks[int(offset)]

    def __contains__(self, offset: int) -> bool:
        return int(offset) in self._blocks

    def __len__(self) -> int:
        return len(self._blocks)

    # ----------------------------------------------------------------- allocation

    def alloc(self, n: int) -> int:
        """A block of ``n`` > 0 elements (first fit); may compact or grow the buffer first (listeners told)."""
        n = int(n)
        if n <= 0:
            raise ValueError(f"a block needs at least one element, asked for {n}")
        fits = self._hole_len >= n
        if self._hole_len.size and fits.any():
            i = int(np.argmax(fits))
            off = int(self._hole_off[i])
            if self._hole_len[i] == n:
                self._hole_off = np.delete(self._hole_off, i)
                self._hole_len = np.delete(self._hole_len, i)
            else:
                self._hole_off[i] += n
                self._hole_len[i] -= n
        else:
            if self.top + n > self.capacity:
                if self.fragmented and self.used + n <= self.capacity:
                    self.compact()
                if self.top + n > self.capacity:
                    self._grow(self.top + n)
            off = self.top
            self.top += n
        self._blocks[off] = n
        self.used += n
        return off

    def reserve(self, n: int) -> None:
        """Make room for ``n`` more elements with at most one growth, before a batch of ``alloc`` calls that
        would otherwise grow the buffer step by step (a new buffer and a copy each time)."""
        n = int(n)
        if n > 0 and self.used + n > self.capacity:
            self._grow(self.top + n)

    def free(self, offset: int) -> None:
        """Return the block at ``offset`` to the free list, merged with adjacent holes (KeyError: no block there)."""
        off = int(offset)
        n = self._blocks.pop(off)
        self.used -= n
        end = off + n
        i = int(np.searchsorted(self._hole_off, off))
        left = i > 0 and int(self._hole_off[i - 1] + self._hole_len[i - 1]) == off
        right = i < self._hole_off.size and int(self._hole_off[i]) == end
        if left and right:
            self._hole_len[i - 1] += n + self._hole_len[i]
            self._hole_off = np.delete(self._hole_off, i)
            self._hole_len = np.delete(self._hole_len, i)
            i -= 1
        elif left:
            self._hole_len[i - 1] += n
            i -= 1
        elif right:
            self._hole_off[i] = off
            self._hole_len[i] += n
        else:
            self._hole_off = np.insert(self._hole_off, i, off)
            self._hole_len = np.insert(self._hole_len, i, n)
        if int(self._hole_off[i] + self._hole_len[i]) == self.top:  # the hole reaches the tail: it becomes tail
            self.top = int(self._hole_off[i])
            self._hole_off = np.delete(self._hole_off, i)
            self._hole_len = np.delete(self._hole_len, i)

    def write(self, offset: int, data: np.ndarray | bytes) -> None:
        """Write whole elements at the start of the live block at ``offset`` (at most the block's size)."""
        off = int(offset)
        raw = data.tobytes() if isinstance(data, np.ndarray) else bytes(data)
        size = self._blocks.get(off)
        if size is None:
            raise KeyError(f"no live block at {off}")
        if len(raw) % self.element_size or len(raw) > size * self.element_size:
            raise ValueError(f"{len(raw)} bytes are not whole elements within block {off} "
                             f"({size} × {self.element_size} bytes)")
        self.buffer.write(raw, offset=off * self.element_size)

    def read(self, offset: int, n: int | None = None) -> bytes:
        """The bytes of ``n`` elements from ``offset`` (default: the live block there). Waits for the GPU."""
        off = int(offset)
        n = self._blocks[off] if n is None else int(n)
        if off < 0 or off + n > self.capacity:
            raise ValueError(f"elements {off}..{off + n} are outside the arena ({self.capacity})")
        return self.buffer.read(n * self.element_size, offset=off * self.element_size)

    # ----------------------------------------------------------------- moving

    def _grow(self, needed: int) -> None:
        capacity = self.capacity
        while capacity < needed:
            capacity = max(int(capacity * self.growth), capacity + 1)
        new = self.ctx.buffer(reserve=capacity * self.element_size)
        if self.top:
            self.ctx.copy_buffer(new, self.buffer, size=self.top * self.element_size)
        self.buffer.release()
        self.buffer, self.capacity = new, capacity
        self.grows += 1
        self._notify(None)

    def compact(self) -> Relocation:
        """Move every live block down, in order, so that the holes vanish; returns old → new offsets.

        GPU-side: the live runs are copied into a fresh buffer of the same
        capacity (a buffer cannot copy onto an overlapping range of itself).
        """
        old, size = self.blocks()
        new = np.zeros_like(old)
        if old.size:
            np.cumsum(size[:-1], out=new[1:])
        moved = Relocation(old, new)
        if old.size and (old != new).any():
            # Runs of adjacent live blocks move together: one copy per run.
            start = np.ones(old.size, bool)
            start[1:] = old[1:] != old[:-1] + size[:-1]
            first = np.flatnonzero(start)
            last_end = np.append(first[1:], old.size) - 1
            src = old[first]
            length = old[last_end] + size[last_end] - src
            buf = self.ctx.buffer(reserve=self.capacity * self.element_size)
            es = self.element_size
            for s, d, n in zip(src.tolist(), new[first].tolist(), length.tolist()):
                self.ctx.copy_buffer(buf, self.buffer, size=n * es, read_offset=s * es, write_offset=d * es)
            self.buffer.release()
            self.buffer = buf
        self._blocks = dict(zip(new.tolist(), size.tolist()))
        self._hole_off = np.zeros(0, np.int64)
        self._hole_len = np.zeros(0, np.int64)
        self.top = self.used
        self.compactions += 1
        self._notify(moved)
        return moved

    def maybe_compact(self) -> Relocation | None:
        """Compact if ``fragmented``; the relocation, or None when nothing was done."""
        return self.compact() if self.fragmented else None

    def _notify(self, moved: Relocation | None) -> None:
        for listener in list(self.listeners):
            listener(self, moved)

    def release(self) -> None:
        self.buffer.release()
        self._blocks.clear()
        self.listeners.clear()
