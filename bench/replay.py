"""Drawing a traced frame again, untimed, and the full-detail frame at the same camera.

Image quality is measured against full detail at the same camera, drawn by the
same renderer. A client run with ``trace=True`` records per frame what
it drew (``client.records.FrameTrace``: reps, morph weights, levels, rendering
algorithms, tree groups and their resolutions, camera); ``Replayer`` draws that
frame again from the scene store, pixel for pixel as the client did, and draws
the full-detail frame beside it.

Geometry is loaded lazily from the store, decoded as the client decodes it
(``proto.geometry``, ``proto.morph``, ``proto.points``) and uploaded once; the
GPU side is an LRU cache with a byte budget, so a city whose full detail does
not fit still replays. Objects whose box lies outside the view frustum are not
even loaded: the box bounds every level and the morph targets (the store's
``object_box``), so leaving them out draws the same pixels.

Tree groups at full detail can be out of reach: a forest's groups can hold hundreds
of millions of splats, far too many to draw a frame of in reasonable time on a
software rasterizer. ``full`` keeps to a splat budget (``tree_splats``, default
``TREE_SPLATS``): when the groups in view exceed it, the ones smallest on screen get
fewer splats (``Replayer.full_resolutions``); a city's trees fit the budget whole.

Per frame the work is numpy over the drawn reps (membership, stamps, culling);
Python loops run once per representation loaded, never per frame.
"""

from __future__ import annotations

import os

import numpy as np

from client.renderer import Renderer
from client.shading import VERTEX
from client.splats import SplatLayer
from proto.camera import NEAR, far_plane, projection_matrix, view_matrix
from proto.messages import DEFAULT_SUN
from proto.geometry import decode_geometry
from proto.morph import decode_morph
from proto.points import decode_instances, decode_points
from server.scene.index import TREES, SceneIndex
from server.scene.store import SceneStore
from server.select.morph import rep_parents

__all__ = ["TREE_SPLATS", "Replayer", "finest_cut", "tree_groups"]

#: GPU bytes per vertex and per triangle in the renderer's arenas (``client.shading.VERTEX``, uint32 indices).
_VERTEX_BYTES, _TRIANGLE_BYTES = VERTEX.itemsize, 12
#: Representations fetched from the store per SELECT batch while loading.
_BATCH = 256
#: Splats a full-detail frame draws at most by default: a city's tree groups fit whole, a forest's are
#: thinned (the smallest on screen first) so a full-detail frame stays drawable on a software rasterizer.
TREE_SPLATS = 16_000_000


def finest_cut(index: SceneIndex) -> np.ndarray:
    """(k,) int64 rep ids of the scene at full detail, tree groups aside: the leaves of the rep forest.

    In the forest of ``server.select.morph.rep_parents`` a chain's level k hangs
    under level k − 1 and an object's level 0 under its parent object's finest
    level (HLOD nodes, terrain quadtree). Its leaves — reps no other rep hangs
    under — are the last level of every object without children: together they
    cover the scene once, none beside one of its ancestors. Tree groups are drawn
    by the splat layer (``tree_groups``) and left out.
    """
    parent = rep_parents(index.rep_level, index.rep_object, index.object_parent, index.rep_first, index.rep_count)
    inner = np.zeros(index.n_representations, bool)
    inner[parent[parent >= 0]] = True
    trees = np.asarray(index.object_kind)[np.asarray(index.rep_object)] == TREES
    return np.flatnonzero(~inner & ~trees).astype(np.int64)


def tree_groups(index: SceneIndex) -> np.ndarray:
    """(g,) int64 rep ids of the tree groups (a ``trees`` object's only representation), as the splat layer keys them."""
    obj = np.flatnonzero(np.asarray(index.object_kind) == TREES)
    return np.asarray(index.rep_first, np.int64)[obj] + np.asarray(index.rep_count, np.int64)[obj] - 1


class Replayer:
    """A scene store and a headless renderer (plus a splat layer) that redraw traced frames, untimed.

    store        : a scene store path (opened and closed here) or an open ``SceneStore`` (left open)
    viewport     : (width, height) of the run; fov_y: its vertical field of view (degrees)
    budget_bytes : GPU bytes the resident meshes may take (32 per vertex, 12 per triangle); least
                   recently drawn reps are freed beyond it, never those of the frame being drawn
    tree_resolution : the resolution x at which ``full`` draws tree groups (1.0: every splat)
    tree_splats  : the most splats ``full`` draws (None: no limit); see ``full_resolutions``

    ``loaded`` counts representations uploaded (a rep evicted and needed again counts twice);
    ``resident_bytes`` is what the meshes on the GPU take now.

    Its GL work runs with its own context made current and the previous one restored afterwards,
    so it can live beside a client's renderer or another Replayer in one process (GL calls go to
    the thread's current context, whichever object issues them). Constructing one leaves its
    context current, as constructing any ``Renderer`` does.
    """

    def __init__(self, store: str | os.PathLike[str] | SceneStore, *, viewport: tuple[int, int] = (640, 360),
                 fov_y: float = 60.0, backend: str | None = "egl", budget_bytes: int = 512 << 20,
                 tree_resolution: float = 1.0, tree_splats: int | None = TREE_SPLATS) -> None:
        if budget_bytes <= 0:
            raise ValueError(f"budget_bytes must be positive, got {budget_bytes}")
        if not 0.0 < tree_resolution <= 1.0:
            raise ValueError(f"tree_resolution must lie in (0, 1], got {tree_resolution}")
        if tree_splats is not None and tree_splats <= 0:
            raise ValueError(f"tree_splats must be positive or None, got {tree_splats}")
        self.tree_splats = tree_splats
        self._own_store = not isinstance(store, SceneStore)
        self.store = SceneStore.open(store) if self._own_store else store
        try:
            self._setup(viewport, fov_y, backend, budget_bytes, tree_resolution)
        except BaseException:
            if self._own_store:
                self.store.close()
            raise

    def _setup(self, viewport, fov_y: float, backend: str | None, budget_bytes: int, tree_resolution: float) -> None:
        ix = self.index
        width, height = (int(v) for v in viewport)
        self.viewport = (width, height)
        self.fov_y = float(fov_y)
        self.budget_bytes = int(budget_bytes)
        self.tree_resolution = float(tree_resolution)
        self.bounds = np.asarray(ix.bounds, np.float64)  # the welcome's bounds: the client's far plane
        m = ix.n_representations
        self._object = np.asarray(ix.rep_object, np.int64)
        self._level = np.asarray(ix.rep_level, np.int64)
        self._trees = np.asarray(ix.object_kind)[self._object] == TREES
        self._bytes = (_VERTEX_BYTES * np.asarray(ix.rep_vertices, np.int64)
                       + _TRIANGLE_BYTES * np.asarray(ix.rep_faces, np.int64))
        # A morph target exists where the client's cache could build one: a stored map onto level k − 1 of the
        # same object, which is representation rep − 1 (``ResidentCache.morph_targets``).
        prev_same = np.r_[False, self._object[1:] == self._object[:-1]]
        self._can_morph = np.asarray(ix.rep_morph, bool) & (self._level >= 1) & prev_same
        lo, hi = np.asarray(ix.object_lo, np.float64), np.asarray(ix.object_hi, np.float64)
        self._sphere = np.column_stack([(lo + hi) / 2.0, np.linalg.norm(hi - lo, axis=1) / 2.0])
        self.finest = finest_cut(ix)
        self.groups = tree_groups(ix)
        self._resident = np.zeros(m, bool)
        self._target = np.zeros(m, bool)
        self._stamp = np.zeros(m, np.int64)
        self._group_resident = np.zeros(m, bool)
        self._clock = 0
        self.loaded = 0
        self.resident_bytes = 0
        self.splats: SplatLayer | None = None
        self.renderer = Renderer(width, height, fov_y=fov_y, backend=backend)
        # Lit and painted as the client draws the scene: its sun (``Welcome.sun``) and the sky.
        sun = np.asarray(ix.meta.get("sun") or DEFAULT_SUN, np.float64)
        self.renderer.sun = sun / np.linalg.norm(sun)
        self.renderer.enable_sky()
        if ix.model_points.size:
            try:
                with self.renderer.ctx:
                    self.splats = SplatLayer(self.renderer.ctx)
                    self.splats.sun = self.renderer.sun
                    models = self.store.model_geometries(range(int(ix.model_points.size)))
                    for model, blob in enumerate(models):
                        self.splats.add_model(model, decode_points(blob))
            except BaseException:
                self.close()
                raise

    @property
    def index(self) -> SceneIndex:
        return self.store.index

    # ----------------------------------------------------------------- frames

    def drawn(self, trace, *, false_colour: bool = False) -> np.ndarray:
        """(h, w, 3) uint8 — the frame as the client drew it (``client.records.FrameTrace``), drawn again untimed.

        The rows the client held (``trace.drawn``) with their morph weights, levels and
        rendering algorithms, the tree groups at their resolutions, from the traced camera with
        the client's near and far planes. ``false_colour`` shades meshes by level, as the
        client's false-colour mode. A rep drawn with weight < 1 morphs toward level k − 1 where
        the store has a morph map (as the client does when the server sent it, i.e. with morphing on).
        """
        eye, forward, up = _pose(trace)
        rows = np.ones(np.asarray(trace.rep).shape, bool) if trace.drawn is None else np.asarray(trace.drawn, bool)
        reps = np.asarray(trace.rep, np.int64)[rows]
        weights = np.asarray(trace.weight, np.float64)[rows]
        levels = np.asarray(trace.level, np.float64)[rows]
        algorithms = None if trace.algorithm is None else np.asarray(trace.algorithm, np.int64)
        if algorithms is not None and algorithms.shape != reps.shape:
            raise ValueError(f"trace.algorithm must align with the drawn rows ({reps.size},), got {algorithms.shape}")
        self._check_reps(reps)
        keep = ~self._trees[reps]  # the client's renderer never holds a tree group: it would skip one
        keep &= self._seen(self._object[reps], eye, forward, up)
        reps, weights, levels = reps[keep], weights[keep], levels[keep]
        algorithms = None if algorithms is None else algorithms[keep]
        veg = np.zeros(0, np.int64) if trace.vegetation is None else np.asarray(trace.vegetation, np.int64)
        res = np.zeros(0) if trace.resolution is None else np.asarray(trace.resolution, np.float64)
        if veg.shape != res.shape:
            raise ValueError(f"trace.vegetation and trace.resolution must align, got {veg.shape} and {res.shape}")
        with self.renderer.ctx:
            return self._draw(reps, eye, forward, up, weights=weights, levels=levels, algorithms=algorithms,
                              groups=veg, resolutions=res, false_colour=false_colour)

    def full(self, eye, forward, up, *, algorithms_from=None, false_colour: bool = False) -> np.ndarray:
        """(h, w, 3) uint8 — the full-detail frame at a camera: every object at its finest representation.

        Meshes: the finest cut (``finest_cut``: the last level of every object without children,
        so HLOD proxies and coarse terrain patches give way to their leaves); the tree groups in
        view at ``tree_resolution`` (1.0 unless set), within the ``tree_splats`` budget
        (``full_resolutions``). No morphing; false colour shows each rep's level.

        Rendering algorithm: flat, unless ``algorithms_from`` (a ``FrameTrace``) is given; then each
        object takes the algorithm that frame drew it with, and an object it did not draw (a leaf under
        a drawn HLOD node or terrain patch) that of its nearest drawn ancestor — flat if none. So the
        image error between ``drawn(trace)`` and ``full(..., algorithms_from=trace)`` measures the
        geometry chosen, not the shading choice.
        """
        eye, forward, up = (np.asarray(v, np.float64).reshape(3) for v in (eye, forward, up))
        reps = self.finest[self._seen(self._object[self.finest], eye, forward, up)]
        algorithms = None if algorithms_from is None else self._inherited(algorithms_from, self._object[reps])
        groups = self.groups[self._seen(self._object[self.groups], eye, forward, up)]
        with self.renderer.ctx:
            return self._draw(reps, eye, forward, up, weights=None, levels=self._level[reps].astype(np.float64),
                              algorithms=algorithms, groups=groups, resolutions=self.full_resolutions(groups, eye),
                              false_colour=false_colour)

    def full_resolutions(self, groups: np.ndarray, eye) -> np.ndarray:
        """(g,) float — the resolution x ``full`` draws tree groups ``groups`` (rep ids) at, seen from ``eye``.

        ``tree_resolution`` for all when their splats at it fit ``tree_splats`` (always on Den Haag).
        Otherwise full detail is out of reach (St. Helens: 490 M splats) and the budget goes by
        screen size: each group gets x = min(tree_resolution, d · A / N) — A its bounding disc's
        projected area in pixels, N its splats at x = 1 — with the one density d (splats per pixel)
        that spends the budget, and never fewer than one splat per tree; a group around the eye keeps
        ``tree_resolution``. Groups small on screen thin out first, where more splats change least.
        """
        groups = np.asarray(groups, np.int64)
        top = np.full(groups.size, self.tree_resolution)
        n = np.asarray(self.index.rep_vertices, np.float64)[groups]
        if self.tree_splats is None or float((top * n).sum()) <= self.tree_splats:
            return top
        centre, radius = self._sphere[self._object[groups], :3], self._sphere[self._object[groups], 3]
        distance = np.linalg.norm(centre - np.asarray(eye, np.float64), axis=1)
        inside = distance <= radius
        pixels = radius / np.maximum(distance, 1e-9) * (self.viewport[1] / 2) / np.tan(np.radians(self.fov_y) / 2)
        area = np.where(inside, np.inf, np.pi * pixels ** 2)
        floor = np.minimum(top, 1.0 / max(int(np.asarray(self.index.model_points).min()), 1))

        def at(density: float) -> np.ndarray:
            return np.clip(density * area / np.maximum(n, 1.0), floor, top)

        lo, hi = 0.0, 1.0
        while float((at(hi) * n).sum()) < self.tree_splats and hi < 1e12:
            lo, hi = hi, hi * 4.0
        for _ in range(40):  # bisection on the density: splats drawn grow with it
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if float((at(mid) * n).sum()) <= self.tree_splats else (lo, mid)
        return at(lo)

    # ----------------------------------------------------------------- internals

    def _draw(self, reps: np.ndarray, eye, forward, up, *, weights, levels, algorithms, groups, resolutions,
              false_colour: bool) -> np.ndarray:
        self._clock += 1
        self._ensure(reps)
        if weights is not None:
            self._ensure_targets(reps[(weights < 1.0) & self._can_morph[reps] & ~self._target[reps]])
        layers = ()
        if self.splats is not None:
            self._ensure_groups(groups)
            self.splats.set_resolutions(groups, resolutions)
            layers = (self.splats,)
        elif groups.size:
            raise ValueError("tree groups asked for, but the scene store has no tree models")
        self.renderer.false_colour = bool(false_colour)
        self.renderer.draw(reps, eye, forward, up, NEAR, far_plane(eye, self.bounds), weights=weights,
                           algorithms=algorithms, levels=levels, layers=layers)
        return self.renderer.read_image()

    def _check_reps(self, reps: np.ndarray) -> None:
        m = self.index.n_representations
        if reps.size and (int(reps.min()) < 0 or int(reps.max()) >= m):
            raise ValueError(f"trace names representations outside the store's 0..{m - 1}: is it this scene's trace?")

    def _seen(self, objects: np.ndarray, eye: np.ndarray, forward: np.ndarray, up: np.ndarray) -> np.ndarray:
        """(s,) bool — objects whose bounding sphere meets the view frustum (the renderer's own test, on object boxes)."""
        vp = (projection_matrix(self.fov_y, self.viewport[0] / self.viewport[1], NEAR, far_plane(eye, self.bounds))
              @ view_matrix(np.zeros(3), forward, up))
        planes = np.stack([vp[3] + vp[0], vp[3] - vp[0], vp[3] + vp[1], vp[3] - vp[1], vp[3] + vp[2], vp[3] - vp[2]])
        planes /= np.linalg.norm(planes[:, :3], axis=1, keepdims=True)
        m = np.vstack([planes[:, :3].T, np.ones(6)])
        return (self._sphere[objects] @ m + (planes[:, 3] - planes[:, :3] @ eye) >= 0.0).all(axis=1)

    def _ensure(self, reps: np.ndarray) -> None:
        """Upload the reps not resident (in store batches), stamp all as used now, then keep to the budget."""
        self._stamp[reps] = self._clock
        missing = np.unique(reps[~self._resident[reps]])
        for start in range(0, missing.size, _BATCH):
            ids = missing[start:start + _BATCH].tolist()
            for rep, blob in zip(ids, self.store.geometries(ids)):
                self.renderer.upload(rep, decode_geometry(blob), object_id=int(self._object[rep]))
            self._resident[ids] = True
            self.resident_bytes += int(self._bytes[ids].sum())
            self.loaded += len(ids)
        if self.resident_bytes > self.budget_bytes:
            self._evict()

    def _evict(self) -> None:
        """Free least recently drawn reps until the budget holds (the current frame's are kept)."""
        held = np.flatnonzero(self._resident & (self._stamp < self._clock))
        order = held[np.argsort(self._stamp[held], kind="stable")]
        excess = self.resident_bytes - self.budget_bytes
        take = int(np.searchsorted(np.cumsum(self._bytes[order]), excess)) + 1
        for rep in order[:take].tolist():
            self.renderer.free(rep)
        gone = order[:take]
        self._resident[gone] = self._target[gone] = False
        self.resident_bytes -= int(self._bytes[gone].sum())

    def _ensure_targets(self, reps: np.ndarray) -> None:
        """Give resident reps their morph targets: level k − 1's positions through the stored map."""
        reps = np.unique(reps)
        for start in range(0, reps.size, _BATCH):
            ids = reps[start:start + _BATCH].tolist()
            coarse = self.store.geometries([r - 1 for r in ids])
            for rep, cblob, mblob in zip(ids, coarse, self.store.morphs(ids)):
                c = decode_geometry(cblob)
                vmap = decode_morph(mblob, n_fine=int(self.index.rep_vertices[rep]))
                if vmap.size and int(vmap.max()) >= c.vertices:
                    continue  # as the client's cache: a map beyond the coarse level builds no target
                self.renderer.set_morph_target(rep, np.ascontiguousarray(c.positions[vmap], np.float32),
                                               None if c.colours is None else c.colours[vmap])
            self._target[ids] = True

    def _ensure_groups(self, groups: np.ndarray) -> None:
        """Make the tree groups resident in the splat layer (kept: instance lists are small)."""
        if groups.size and (int(groups.min()) < 0 or int(groups.max()) >= self._trees.size
                            or not self._trees[groups].all()):
            raise ValueError("tree groups must be the reps of trees objects")
        missing = np.unique(groups[~self._group_resident[groups]])
        n_models = int(self.index.model_points.size)
        for start in range(0, missing.size, _BATCH):
            ids = missing[start:start + _BATCH].tolist()
            for rep, blob in zip(ids, self.store.geometries(ids)):
                self.splats.add_group(rep, decode_instances(blob, models=n_models))
            self._group_resident[ids] = True

    def _inherited(self, trace, objects: np.ndarray) -> np.ndarray:
        """(s,) int — per object, the algorithm ``trace`` drew it (or its nearest drawn ancestor) with; 0 if none."""
        ix = self.index
        per_object = np.full(ix.n_objects, -1, np.int64)
        if trace.algorithm is not None:
            rows = np.ones(np.asarray(trace.rep).shape, bool) if trace.drawn is None else np.asarray(trace.drawn, bool)
            drawn = np.asarray(trace.rep, np.int64)[rows]
            self._check_reps(drawn)
            per_object[self._object[drawn]] = np.asarray(trace.algorithm, np.int64)
        parent = np.asarray(ix.object_parent, np.int64)
        out = per_object[objects]
        cur = objects.copy()
        todo = np.flatnonzero(out < 0)
        while todo.size:
            cur[todo] = parent[cur[todo]]
            todo = todo[cur[todo] >= 0]
            out[todo] = per_object[cur[todo]]
            todo = todo[out[todo] < 0]
        return np.maximum(out, 0)

    # ----------------------------------------------------------------- lifetime

    def close(self) -> None:
        """Release the splat layer, the renderer (and its context) and a store opened here. Safe to call twice."""
        renderer = getattr(self, "renderer", None)
        if renderer is not None:
            # GL objects are freed in the current context: make ours current, and afterwards restore the one
            # that was (the context object is released with the renderer, so hold its handle to leave it).
            handle = renderer.ctx.mglo
            handle.__enter__()
            try:
                if self.splats is not None:
                    self.splats.release()
                    self.splats = None
                renderer.release()
            finally:
                handle.__exit__(None, None, None)
            self.renderer = None
        if self._own_store:
            self.store.close()

    def __enter__(self) -> "Replayer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _pose(trace) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if trace.eye is None or trace.forward is None or trace.up is None:
        raise ValueError("the trace has no camera (eye, forward, up): record it with run_client(trace=True)")
    return tuple(np.asarray(v, np.float64).reshape(3) for v in (trace.eye, trace.forward, trace.up))
