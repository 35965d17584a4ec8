"""What the client holds: resident representations and the selection to draw (no GL here).

The cache is the client's half of the server's client-cache mirror. It turns a
``Delta`` into GPU work (what to upload, what to free) without touching the GPU
itself, in the pygfx manner, so the rules — adds before drops before the
selection, never draw what isn't resident, a bad payload costs only itself —
are testable without a context.

A selected representation that isn't resident (its payload was refused, or the
server's mirror is out of step) is left out of the selection and counted in
``skipped``: drawing less is better than drawing garbage or failing the frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from proto.errors import ProtocolError
from proto.geometry import Geometry, decode_geometry
from proto.messages import Delta
from proto.morph import decode_morph

__all__ = ["Resident", "ResidentCache"]


@dataclass(frozen=True)
class Resident:
    """One resident representation: which object and level it is, its size, and what morphing needs.

    positions : (vertices, 3) float32 — kept on the CPU so a finer level's morph targets can be built
    morph : (vertices,) uint32 map onto the previous level's vertices, or None
    """

    object: int
    level: int
    faces: int
    vertices: int
    positions: np.ndarray | None = None
    morph: np.ndarray | None = None


class ResidentCache:
    """Resident representations (rep id → ``Resident``) and the current selection.

    Attributes
    ----------
    selection : (s,) int64 rep ids to draw, all resident, in the server's order
    seq : sequence number of the delta whose selection is current, -1 before any
    rejected : every ``ProtocolError('bad_geometry', ...)`` met so far, oldest first
    skipped : how many selected reps were left out for not being resident, in total
    """

    def __init__(self) -> None:
        self.resident: dict[int, Resident] = {}
        self.selection: np.ndarray = np.zeros(0, np.int64)
        self.seq: int = -1
        self.rejected: list[ProtocolError] = []
        self.skipped: int = 0
        self._triangles = 0
        self._vertices = 0
        self._ids = np.zeros(0, np.int64)  # resident rep ids, sorted (for vectorised membership)
        self.last_rejected: list[int] = []  # reps the last applied delta's payloads were refused for

    def __contains__(self, rep: int) -> bool:
        return rep in self.resident

    def __len__(self) -> int:
        return len(self.resident)

    @property
    def triangles(self) -> int:
        """Triangles in the current selection."""
        return self._triangles

    @property
    def vertices(self) -> int:
        """Vertices in the current selection."""
        return self._vertices

    def apply(self, delta: Delta) -> tuple[list[tuple[int, Geometry]], list[int]]:
        """Apply one delta: decode adds, then drop, then set the selection.

        Returns ``(to_upload, to_free)``: geometry the renderer must upload
        (re-adding a resident rep replaces it) and rep ids it must release.
        A payload that does not decode is refused — recorded in ``rejected``,
        its rep not made resident — and the rest of the delta still applies.
        """
        uploads: dict[int, Geometry] = {}
        self.last_rejected = []
        for add in delta.add:
            try:
                geometry = decode_geometry(add.geometry)
                vmap = decode_morph(add.morph, n_fine=geometry.vertices) if add.morph is not None else None
            except ProtocolError as exc:
                self.rejected.append(ProtocolError(exc.code, f"rep {add.rep}: {exc.message}"))
                self.last_rejected.append(add.rep)
                self.resident.pop(add.rep, None)
                continue
            self.resident[add.rep] = Resident(add.object, add.level, geometry.faces, geometry.vertices,
                                              geometry.positions, vmap)
            uploads[add.rep] = geometry
        to_free: list[int] = []
        for rep in delta.drop:
            if self.resident.pop(rep, None) is not None:
                to_free.append(rep)
                uploads.pop(rep, None)  # added and dropped in one delta: never reaches the GPU
        self._ids = np.fromiter(self.resident.keys(), np.int64, len(self.resident))
        self._ids.sort()
        self._select(delta.selection, delta.seq)
        return list(uploads.items()), to_free

    def holds(self, reps: np.ndarray) -> np.ndarray:
        """(s,) bool — which of ``reps`` are resident (vectorised: the per-frame check)."""
        reps = np.asarray(reps, np.int64)
        if self._ids.size == 0:
            return np.zeros(reps.shape, bool)
        pos = np.minimum(np.searchsorted(self._ids, reps), self._ids.size - 1)
        return self._ids[pos] == reps

    def levels(self, reps: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """(reps, levels) of the resident ones among ``reps``, as arrays (once per delta)."""
        keep = [r for r in reps if r in self.resident]
        return np.asarray(keep, np.int64), np.asarray([self.resident[r].level for r in keep], np.float64)

    def morph_targets(self, rep: int) -> np.ndarray | None:
        """(vertices, 3) float32 — where each vertex of ``rep`` goes at morph weight 0, if both levels are here.

        The previous level of the same object is representation ``rep − 1``.
        """
        fine = self.resident.get(rep)
        coarse = self.resident.get(rep - 1)
        if fine is None or coarse is None or fine.morph is None or coarse.positions is None:
            return None
        if coarse.object != fine.object or coarse.level != fine.level - 1:
            return None
        if fine.morph.size and int(fine.morph.max()) >= coarse.vertices:
            return None
        return np.ascontiguousarray(coarse.positions[fine.morph], np.float32)

    def _select(self, reps: list[int], seq: int) -> None:
        keep = [r for r in reps if r in self.resident]
        self.skipped += len(reps) - len(keep)
        self.selection = np.asarray(keep, np.int64)
        self.seq = seq
        self._triangles = sum(self.resident[r].faces for r in keep)
        self._vertices = sum(self.resident[r].vertices for r in keep)
