"""What the client holds: resident representations and the selection to draw (no GL here).

The cache is the client's half of the server's client-cache mirror. It turns a
``Delta`` into GPU work (what to upload, what to free) without touching the GPU
itself, in the pygfx manner, so the rules — adds before drops before the
selection, never draw what isn't resident, a bad payload costs only itself —
are testable without a context.

The cache has a byte budget (``len(geometry)`` of every held representation,
the server's ``rep_bytes``). It never evicts on its own: the server's mirror is
the single authority on what is held, so an add that would overflow the budget
is refused like a bad payload, and the ack's ``rejected``, ``held``,
``held_bytes`` and ``digest`` (``proto.manifest``) let the server follow and
check. A delta's drops count as done when its adds are checked: the budget
holds for what the client keeps after the delta, which is what the mirror sizes.

A selected representation that isn't resident (its payload was refused, or the
server's mirror is out of step) is left out of the selection and counted in
``skipped``: drawing less is better than drawing garbage or failing the frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterator

import numpy as np

from proto.errors import ProtocolError
from proto.geometry import Geometry, decode_geometry
from proto.manifest import digest as manifest_digest
from proto.messages import Delta
from proto.morph import decode_morph
from proto.points import Instances, Points, decode_instances, decode_points

__all__ = ["Changes", "Group", "Resident", "ResidentCache"]


@dataclass(frozen=True)
class Resident:
    """One resident representation: which object and level it is, its size, and what morphing needs.

    positions : (vertices, 3) float32 — kept on the CPU so a finer level's morph targets can be built
    morph : (vertices,) uint32 map onto the previous level's vertices, or None
    colours : (vertices, 3) uint8, or None for a colourless payload — the finer level's target colours
    """

    object: int
    level: int
    faces: int
    vertices: int
    positions: np.ndarray | None = None
    morph: np.ndarray | None = None
    colours: np.ndarray | None = None


@dataclass(frozen=True)
class Group:
    """One resident tree group (a "trees" representation): its object, level and instance count."""

    object: int
    level: int
    instances: int


@dataclass
class Changes:
    """What one applied delta asks of the GPU, split by who draws it.

    uploads / frees : meshes for the renderer (re-adding a resident rep replaces it)
    groups / group_frees : tree groups (instance lists) for the splat layer
    models : tree models (prefix-ordered splats) for the splat layer, once per session
    rejected : reps of the delta's adds refused (bad payload or over budget) — the ack's ``rejected``

    Unpacks as ``(uploads, frees)``, the pair ``apply`` used to return.
    """

    uploads: list[tuple[int, Geometry]] = field(default_factory=list)
    frees: list[int] = field(default_factory=list)
    groups: list[tuple[int, Instances]] = field(default_factory=list)
    group_frees: list[int] = field(default_factory=list)
    models: list[tuple[int, Points]] = field(default_factory=list)
    rejected: list[int] = field(default_factory=list)

    def __iter__(self) -> Iterator[list]:
        yield self.uploads
        yield self.frees


class ResidentCache:
    """Resident representations (rep id → ``Resident`` / ``Group``), tree models and the current selection.

    Attributes
    ----------
    budget_bytes : payload bytes the cache may hold (None: unbounded)
    held_bytes : payload bytes held now (meshes and tree groups)
    digest : ``proto.manifest.digest`` of every held rep id, kept incrementally
    selection : (s,) int64 rep ids to draw, all resident, in the server's order
    seq : sequence number of the delta whose selection is current, -1 before any
    rejected : every ``ProtocolError('bad_geometry', ...)`` met so far, oldest first
    refused_full : adds refused because they would have taken the cache over its budget, in total
    skipped : how many selected reps were left out for not being resident, in total
    models : tree model id → decoded ``Points`` (kept, so a splat layer made late can still get them)
    """

    def __init__(self, budget_bytes: int | None = None) -> None:
        if budget_bytes is not None and budget_bytes < 0:
            raise ValueError(f"budget_bytes must be non-negative, got {budget_bytes}")
        self.budget_bytes = budget_bytes
        self.resident: dict[int, Resident] = {}
        self.groups: dict[int, Group] = {}
        self.models: dict[int, Points] = {}
        self.selection: np.ndarray = np.zeros(0, np.int64)
        self.seq: int = -1
        self.rejected: list[ProtocolError] = []
        self.refused_full: int = 0
        self.skipped: int = 0
        self.held_bytes: int = 0
        self.digest: int = 0
        self._bytes: dict[int, int] = {}  # payload bytes of every held rep
        self._triangles = 0
        self._vertices = 0
        self._ids = np.zeros(0, np.int64)  # held rep ids, sorted (for vectorised membership)
        self.last_rejected: list[int] = []  # reps of the last applied delta that were refused

    def __contains__(self, rep: int) -> bool:
        return rep in self._bytes

    def __len__(self) -> int:
        return len(self._bytes)

    @property
    def held(self) -> int:
        """Representations held (meshes and tree groups): the ack's ``held``."""
        return len(self._bytes)

    def held_reps(self) -> np.ndarray:
        """(h,) int64, sorted — the representations held (a copy): what a resuming hello's manifest names."""
        return self._ids.copy()

    @property
    def triangles(self) -> int:
        """Triangles in the current selection."""
        return self._triangles

    @property
    def vertices(self) -> int:
        """Vertices in the current selection."""
        return self._vertices

    def apply(self, delta: Delta) -> Changes:
        """Apply one delta: decode models and adds, then drop, then set the selection.

        A payload that does not decode, or that would take the cache over its
        budget (counting the delta's own drops as done), is refused: listed in
        ``Changes.rejected``, its rep not resident afterwards; the rest of the
        delta still applies.
        """
        out = Changes()
        toggled: list[int] = []  # ids that entered or left the held set (each flips the digest)
        drop = set(delta.drop)
        # Room the drops make, so the check is on what is held once the delta is applied.
        projected = self.held_bytes - sum(self._bytes.get(r, 0) for r in drop)
        for m in delta.models:
            try:
                self.models[m.model] = decode_points(m.points)
            except ProtocolError as exc:
                self.rejected.append(ProtocolError(exc.code, f"model {m.model}: {exc.message}"))
                continue
            out.models.append((m.model, self.models[m.model]))
        n_models = max(self.models) + 1 if self.models else None
        uploads: dict[int, Geometry] = {}
        groups: dict[int, Instances] = {}
        for add in delta.add:
            rep, size = add.rep, len(add.geometry)
            kept = rep not in drop  # an add its own delta drops never counts against the budget
            old = self._bytes.get(rep, 0) if kept else 0
            if kept and self.budget_bytes is not None and projected - old + size > self.budget_bytes:
                self.refused_full += 1
                projected -= old
                self._refuse(rep, toggled, uploads, groups, out)
                continue
            try:
                if add.kind == "trees":
                    instances = decode_instances(add.geometry, models=n_models)
                else:
                    geometry = decode_geometry(add.geometry)
                    vmap = decode_morph(add.morph, n_fine=geometry.vertices) if add.morph is not None else None
            except ProtocolError as exc:
                self.rejected.append(ProtocolError(exc.code, f"rep {rep}: {exc.message}"))
                projected -= old
                self._refuse(rep, toggled, uploads, groups, out)
                continue
            if kept:
                projected += size - old
            was = self._forget(rep, toggled, uploads, groups)
            if was is not None and was != add.kind:  # a replacement of another kind: free the old side
                (out.frees if was == "mesh" else out.group_frees).append(rep)
            self._bytes[rep] = size
            self.held_bytes += size
            toggled.append(rep)
            if add.kind == "trees":
                self.groups[rep] = Group(add.object, add.level, len(instances))
                groups[rep] = instances
            else:
                self.resident[rep] = Resident(add.object, add.level, geometry.faces, geometry.vertices,
                                              geometry.positions, vmap, geometry.colours)
                uploads[rep] = geometry
        for rep in delta.drop:
            kind = self._forget(rep, toggled, uploads, groups)
            if kind == "mesh":
                out.frees.append(rep)
            elif kind == "trees":
                out.group_frees.append(rep)
        self._settle(toggled)
        out.uploads, out.groups = list(uploads.items()), list(groups.items())
        self.last_rejected = out.rejected
        self._select(delta.selection, delta.seq)
        return out

    def discard(self, rep: int) -> bool:
        """Stop holding ``rep`` without the server's word (e.g. the GPU refused it); True if it was held.

        The server learns of it from the next ack's digest and resyncs; the
        caller frees the GPU side.
        """
        toggled: list[int] = []
        kind = self._forget(rep, toggled, {}, {})
        self._settle(toggled)
        if kind is not None and rep in self.selection:
            self._select(self.selection.tolist(), self.seq)
        return kind is not None

    def holds(self, reps: np.ndarray) -> np.ndarray:
        """(s,) bool — which of ``reps`` are resident (vectorised: the per-frame check)."""
        reps = np.asarray(reps, np.int64)
        if self._ids.size == 0:
            return np.zeros(reps.shape, bool)
        pos = np.minimum(np.searchsorted(self._ids, reps), self._ids.size - 1)
        return self._ids[pos] == reps

    def levels(self, reps: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """(reps, levels) of the resident meshes among ``reps``, as arrays (once per delta)."""
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

    def morph_target_colours(self, rep: int) -> np.ndarray | None:
        """(vertices, 3) uint8 — the colour each vertex of ``rep`` blends to at weight 0, where
        ``morph_targets`` has targets and both levels have colours (else None: each keeps its own)."""
        fine, coarse = self.resident.get(rep), self.resident.get(rep - 1)
        if self.morph_targets(rep) is None or fine.colours is None or coarse.colours is None:
            return None
        return coarse.colours[fine.morph]

    # ------------------------------------------------------------------ internals

    def _refuse(self, rep: int, toggled: list[int], uploads: dict, groups: dict, out: Changes) -> None:
        """A refused add leaves its rep not held (as the server's mirror will record it)."""
        out.rejected.append(rep)
        kind = self._forget(rep, toggled, uploads, groups)
        if kind == "mesh":
            out.frees.append(rep)
        elif kind == "trees":
            out.group_frees.append(rep)

    def _forget(self, rep: int, toggled: list[int], uploads: dict, groups: dict) -> str | None:
        """Stop holding ``rep``; returns its kind ("mesh" / "trees") if it was held."""
        size = self._bytes.pop(rep, None)
        if size is None:
            return None
        self.held_bytes -= size
        toggled.append(rep)
        uploads.pop(rep, None)  # added and dropped in one delta: never reaches the GPU
        groups.pop(rep, None)
        if self.resident.pop(rep, None) is not None:
            return "mesh"
        self.groups.pop(rep, None)
        return "trees"

    def _settle(self, toggled: list[int]) -> None:
        """Fold the ids that entered or left into the digest (one XOR each) and re-sort the held ids."""
        if toggled:
            self.digest ^= manifest_digest(np.asarray(toggled, np.int64))
        self._ids = np.fromiter(self._bytes.keys(), np.int64, len(self._bytes))
        self._ids.sort()

    def _select(self, reps: list[int], seq: int) -> None:
        keep = [r for r in reps if r in self.resident]
        self.skipped += len(reps) - len(keep)
        self.selection = np.asarray(keep, np.int64)
        self.seq = seq
        self._triangles = sum(self.resident[r].faces for r in keep)
        self._vertices = sum(self.resident[r].vertices for r in keep)
