"""The scene index: everything about a scene but its geometry, as numpy arrays.

The server selects, culls and prices representations from these arrays alone;
geometry blobs stay in the store (``server.scene.store``) until they are sent.
This module imports numpy only, so code that reasons about a scene (selection,
benchmarks) needs no database.

Level convention: **level 0 is the coarsest**; levels increase with detail and
an object's last level is its full detail (Funkhouser & Séquin's "highest
LOD"). Object ids are 0..n-1; representation ids are 0..m-1 in (object, level)
order, so a representation's id is its row in the index arrays and an
object's representations are ``rep_first[o] + arange(rep_count[o])``.

Objects come in four kinds (``KINDS``): ``mesh`` (a discrete LOD chain; may
hang under an HLOD node), ``hlod`` (an inner node of a building hierarchy,
carrying a merged proxy of its subtree), ``terrain`` (a quadtree patch), and
``trees`` (a group of ≤ 64 tree instances drawn as point splats at a continuous
resolution x ∈ [0, 1]). Hierarchies are parent links; a parent's id is always
less than its children's, so one pass in id order visits parents first.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["KINDS", "MESH", "HLOD", "TERRAIN", "TREES", "SceneIndex", "hierarchy"]

#: Object kinds, by their id in the store's ``kind`` column and in ``SceneIndex.object_kind``.
KINDS = ("mesh", "hlod", "terrain", "trees")
MESH, HLOD, TERRAIN, TREES = range(4)


@dataclass
class SceneIndex:
    """Everything about a scene but its geometry, as a structure of arrays.

    Objects (n of them, ids 0..n-1):
        object_lo, object_hi : (n, 3) float32 — box over all levels (≈ full detail), world space
        object_class         : (n,) int16 — index into ``class_names``
        object_kind          : (n,) int8 — index into ``KINDS`` (mesh, hlod, terrain, trees)
        object_parent        : (n,) int32 — parent object in its hierarchy, −1 for a root or a
                               free object; always less than the object's own id
        object_depth         : (n,) int16 — 0 for roots
        child_ptr, child_ids : CSR children: the children of o are child_ids[child_ptr[o]:child_ptr[o+1]]
        rep_first            : (n,) int32 — id of the object's level 0 (coarsest)
        rep_count            : (n,) int32 — number of levels; the last is full detail
    Representations (m of them, ids 0..m-1, in (object, level) order):
        rep_object   : (m,) int32
        rep_level    : (m,) int16 — 0 coarsest … rep_count-1 full detail
        rep_faces    : (m,) int32 — triangles
        rep_vertices : (m,) int32
        rep_error    : (m,) float32 — object-space geometric error against full detail
                       (metres; 0 at full detail, non-increasing with level)
        rep_bytes    : (m,) int32 — size of the geometry payload
        rep_morph    : (m,) bool — a morph map onto the previous level is stored
        rep_texels   : (m,) int32 — width × height of the base-colour texture the payload carries,
                       0 for none (and for every rep of a store built before it was recorded)
    Tree models (M of them), shared by ``trees`` objects:
        model_points : (M,) int32 — splats at full resolution
        model_radius : (M,) float32 — splat radius at full resolution (model space)
        model_lo, model_hi : (M, 3) float32 — model-space boxes
    Scene:
        bounds : (2, 3) float64 — [min, max] over all objects
        tour   : list of {"t", "eye", "forward", "up"} (``proto.messages.TourKey`` fields)
        start  : {"eye", "forward", "up"}
        meta   : every meta value, decoded from JSON
    """

    name: str
    bounds: np.ndarray
    object_lo: np.ndarray
    object_hi: np.ndarray
    object_class: np.ndarray
    class_names: list[str]
    object_kind: np.ndarray
    object_parent: np.ndarray
    object_depth: np.ndarray
    child_ptr: np.ndarray
    child_ids: np.ndarray
    rep_first: np.ndarray
    rep_count: np.ndarray
    rep_object: np.ndarray
    rep_level: np.ndarray
    rep_faces: np.ndarray
    rep_vertices: np.ndarray
    rep_error: np.ndarray
    rep_bytes: np.ndarray
    rep_morph: np.ndarray
    model_points: np.ndarray
    model_radius: np.ndarray
    model_lo: np.ndarray
    model_hi: np.ndarray
    tour: list[dict]
    start: dict
    meta: dict
    rep_texels: np.ndarray | None = None  # None: all zero (an index made without it)

    def __post_init__(self) -> None:
        if self.rep_texels is None:
            self.rep_texels = np.zeros(self.rep_object.shape[0], np.int32)

    @property
    def n_objects(self) -> int:
        return int(self.object_lo.shape[0])

    @property
    def n_representations(self) -> int:
        return int(self.rep_object.shape[0])

    def children(self, o: int) -> np.ndarray:
        """Ids of object ``o``'s children (empty for a leaf)."""
        return self.child_ids[self.child_ptr[o] : self.child_ptr[o + 1]]

    @property
    def leaf(self) -> np.ndarray:
        """(n,) bool — objects without children."""
        return np.diff(self.child_ptr) == 0

    @property
    def flat(self) -> np.ndarray:
        """(n,) bool — the objects a flat (non-hierarchical) selection draws: triangle-mesh leaves.

        Together they cover the whole scene at full detail: every building, every
        finest terrain patch; HLOD proxies and coarse patches only stand in for them.
        Tree groups need the splat renderer and the mixed solver, so they are left out.
        """
        return self.leaf & (self.object_kind != TREES)

    @property
    def height(self) -> int:
        """Levels of the deepest hierarchy (1 for a scene without hierarchies)."""
        return int(self.object_depth.max()) + 1 if self.n_objects else 0


def hierarchy(parent: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depths and CSR children of a forest given by parent links.

    parent : (n,) int32 — −1 for a root, else an id less than the node's own
    Returns depth (n,) int16, child_ptr (n + 1,) int64 and child_ids (int32, children
    grouped by parent in parent order, each group in id order).
    """
    n = parent.shape[0]
    depth = np.zeros(n, np.int16)
    up = parent.copy()
    while (up >= 0).any():  # pointer jumping: one vectorised step per hierarchy level
        depth += up >= 0
        up = np.where(up >= 0, parent[np.maximum(up, 0)], -1)
    child_ids = np.nonzero(parent >= 0)[0].astype(np.int32)
    child_ids = child_ids[np.argsort(parent[child_ids], kind="stable")]
    child_ptr = np.zeros(n + 1, np.int64)
    child_ptr[1:] = np.cumsum(np.bincount(parent[child_ids], minlength=n)) if child_ids.size else 0
    return depth, child_ptr, child_ids
