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

__all__ = ["Resident", "ResidentCache"]


@dataclass(frozen=True)
class Resident:
    """One resident representation: which object and level it is, and its size."""

    object: int
    level: int
    faces: int
    vertices: int


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
        for add in delta.add:
            try:
                geometry = decode_geometry(add.geometry)
            except ProtocolError as exc:
                self.rejected.append(ProtocolError(exc.code, f"rep {add.rep}: {exc.message}"))
                continue
            self.resident[add.rep] = Resident(add.object, add.level, geometry.faces, geometry.vertices)
            uploads[add.rep] = geometry
        to_free: list[int] = []
        for rep in delta.drop:
            if self.resident.pop(rep, None) is not None:
                to_free.append(rep)
                uploads.pop(rep, None)  # added and dropped in one delta: never reaches the GPU
        self._select(delta.selection, delta.seq)
        return list(uploads.items()), to_free

    def _select(self, reps: list[int], seq: int) -> None:
        keep = [r for r in reps if r in self.resident]
        self.skipped += len(reps) - len(keep)
        self.selection = np.asarray(keep, np.int64)
        self.seq = seq
        self._triangles = sum(self.resident[r].faces for r in keep)
        self._vertices = sum(self.resident[r].vertices for r in keep)
