"""Turn a ``SourceScene`` into a scene store: LOD chains, hierarchies, point models, tours.

The stages, each with its own progress count:

1. **chains** — every mesh object gets its LOD chain (quadric decimation with
   collapse-map morphs, or the levels the source gave with nearest-vertex
   morphs), its errors and its payloads, in worker processes;
2. **hlod** — when the scene has many buildings, an HLOD tree over them whose
   inner nodes carry merged, simplified proxies (one root covers the city);
3. **terrain** — each height grid becomes a quadtree of patches with skirts; a scene
   without terrain first gets a ground under its objects (``server.scene.ground``);
4. **trees** — tree models become prefix-ordered point sets, instances are
   grouped ≤ 64 per quadtree leaf;
5. **write** — everything goes into one ``SceneWriter`` transaction, parents
   before children, so a failed build leaves no store behind.

Geometry is recentred on an ``origin`` (recorded in meta) before anything is
encoded: CityJSON and DEM coordinates are hundreds of kilometres from their
datum, and float32 on the GPU would keep only decimetres there.

Every named scene and every imported file is built here, except the demo:
``server.scene.demo`` builds its store itself and says why.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from proto.geometry import encode_geometry
from proto.messages import DEFAULT_SUN

from .blocks import oriented_box
from .colours import Appearance, coloured_levels, coloured_mesh, constant
from .palette import class_colour
from .fidelity import Bounds, Fidelity
from .ground import GROUND_NAME, ground_grid, needs_ground
from .index import HLOD, MESH, TERRAIN, TREES
from .ladder import shaped_chain, shaped_source_chain
from .scans import model_source
from .lod import build_chain, chain_from_levels
from .source import Mesh, SourceScene
from .store import SceneStore
from .surface import is_closed
from .texcoords import UVReference, textured_levels
from .tour import named_tours, orbit_tour, scene_tours
from .workers import POOL_MIN_JOBS, default_workers, pool_map
from .writer import SceneWriter, encode_levels

__all__ = ["BuildOptions", "build_store", "Progress"]

#: progress(stage, done, total)
Progress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class BuildOptions:
    """How a scene is built; the defaults suit real data.

    hlod            : "auto" builds an HLOD tree when at least ``hlod_min`` objects are
                      buildings (or, for a generic source, any mesh objects); True/False force it
    hlod_classes    : classes that go into the HLOD tree ("auto": building-like classes)
    morph           : "collapse" (topology-consistent, from the simplifier) or "nearest" (Zach 2002)
    min_saving      : a coarser level must save at least this share of the faces
    patch           : terrain patch size in grid cells
    points_per_model: splats per tree model at full resolution
    max_group       : trees per group (ZMK: 64)
    workers         : processes for the chain stage (default: one per CPU, at most 8)
    shape_guard     : measure every coarse level (``server.scene.fidelity``) and keep only those
                      within ``bounds``, regenerating failed ones by the shape ladder
                      (``server.scene.ladder``); False: plain quadric chains, unmeasured
    bounds          : silhouette IoU / area ratio / FLIP a kept level or proxy must reach
    max_proxy_faces : most faces of an HLOD proxy
    ground          : lay a ground under a scene that has no terrain (``server.scene.ground``)
    street_tours    : make the ``walk`` and ``flyover`` tours where the scene's streets allow them
                      (``server.scene.tour.scene_tours``)
    """

    hlod: bool | str = "auto"
    hlod_min: int = 64
    hlod_classes: tuple[str, ...] | None = None
    morph: str = "collapse"
    min_saving: float = 0.4
    patch: int = 32
    points_per_model: int = 4096
    max_group: int = 64
    workers: int | None = None
    shape_guard: bool = True
    bounds: Bounds = Bounds()
    max_proxy_faces: int = 4096
    ground: bool = True
    street_tours: bool = True


#: Full-detail vertices per object from which HLOD proxies' errors are measured.
HLOD_POINTS = 48

_BUILDING_CLASSES = ("building", "buildingpart", "building_part", "house")


@dataclass
class ChainRows:
    """One object's chain as the store takes it, plus what the HLOD stage needs of it.

    lo, hi  : (3,) box; errors, blobs, morphs: per level, coarsest first
    coarsest: (positions, faces) of the coarsest level, an HLOD parent's stand-in for it
    fidelity: per level (method, area ratio, IoU, FLIP), or None when unmeasured
    sample  : (≤ HLOD_POINTS, 3) full-detail vertices, for its HLOD ancestors' errors
    box     : its LoD1 box (``blocks.oriented_box`` of the finest level), when measured
    full_closed : whether the finest level is closed (the area bound applies to its levels)
    appearance : its coarsest level's colours, from which its HLOD ancestors' proxies take theirs
                 (None: a colourless object)
    """

    lo: np.ndarray
    hi: np.ndarray
    errors: list[float]
    blobs: list
    morphs: list
    coarsest: tuple[np.ndarray, np.ndarray]
    fidelity: list | None
    regenerated: int
    dropped: int
    sample: np.ndarray
    box: tuple[np.ndarray, np.ndarray] | None = None
    full_closed: bool = False
    appearance: Appearance | None = None


def _chain_job(args: tuple) -> ChainRows:
    """One object's rows (``ChainRows``); every level takes its colours from ``ref`` (``server.scene.colours``)
    and, for a textured object, its UVs and its own texture from ``uvref`` (``server.scene.texcoords``)."""
    levels, morph, min_saving, building, guard, bounds, ref, uvref = args
    fidelity = None
    box = None
    regenerated = dropped = 0
    if guard:
        if len(levels) == 1:
            shaped = shaped_chain(levels[0][0], levels[0][1], building=building, bounds=bounds,
                                  min_saving=min_saving)
        else:
            shaped = shaped_source_chain(levels, building=building, bounds=bounds)
        chain, regenerated, dropped, box = shaped.chain, shaped.regenerated, shaped.dropped, shaped.box
        fidelity = [f.as_tuple() for f in shaped.fidelity]
    elif len(levels) == 1:
        chain = build_chain(levels[0][0], levels[0][1], min_saving=min_saving, morph=morph)
    else:
        # The source's own LoDs are real data and stay, except a dominated one: a coarser LoD
        # with no fewer faces than a finer one costs as much to draw and shows less (LoD 1.2
        # and 1.3 are often the same box). ``min_saving`` rules levels we make, not these.
        kept = [levels[-1]]
        for p, f in reversed(levels[:-1]):
            if len(f) < len(kept[-1][1]):
                kept.append((p, f))
        chain = chain_from_levels(kept[::-1], morph="nearest")
    # morph[k] maps level k's vertices onto level k-1's; the coarsest level (and morph="none") has none.
    appearance = None
    if uvref is not None:
        stored, maps, colours, uvs, textures = textured_levels(ref, uvref, chain.levels, chain.morph)
        lo, hi, blobs, morphs = encode_levels(stored, maps, reorder=False, colours=colours, uvs=uvs,
                                              textures=textures)
        if ref is not None:
            appearance = Appearance.of_level(*stored[0], colours[0], ref.by_face)
    elif ref is None:
        lo, hi, blobs, morphs = encode_levels(chain.levels, chain.morph, reorder=False)
    else:
        stored, maps, colours = coloured_levels(ref, chain.levels, chain.morph)
        lo, hi, blobs, morphs = encode_levels(stored, maps, reorder=False, colours=colours)
        appearance = Appearance.of_level(*stored[0], colours[0], ref.by_face)
    coarsest = chain.levels[0]
    full, full_faces = chain.levels[-1]
    sample = full[np.linspace(0, full.shape[0] - 1, min(full.shape[0], HLOD_POINTS)).astype(np.int64)]
    rows = ChainRows(lo, hi, [float(e) for e in chain.errors], blobs, morphs, coarsest, fidelity, regenerated,
                     dropped, sample, appearance=appearance)
    if guard:
        rows.box = box if box is not None else oriented_box(full, full_faces)
        rows.full_closed = is_closed(full_faces)
        rows.fidelity = [q + (rows.full_closed,) for q in fidelity]
    return rows


def scene_origin(source: SourceScene) -> np.ndarray:
    """A round-numbered point near the scene's centre (xy) and ground (z) to recentre on."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for obj in source.objects:
        for m in obj.levels:
            if m.n_vertices:
                lo = np.minimum(lo, m.positions.min(axis=0))
                hi = np.maximum(hi, m.positions.max(axis=0))
    for g in source.grids:
        rows, cols = g.heights.shape
        x0, y0 = g.origin
        lo = np.minimum(lo, [x0, y0, np.nanmin(g.heights)])
        hi = np.maximum(hi, [x0 + (cols - 1) * g.spacing[0], y0 + (rows - 1) * g.spacing[1], np.nanmax(g.heights)])
    if source.trees is not None and len(source.trees):
        t = source.trees.matrix[:, :3, 3]
        lo, hi = np.minimum(lo, t.min(axis=0)), np.maximum(hi, t.max(axis=0))
    if not np.isfinite(lo).all():
        raise ValueError("the scene holds no geometry")
    centre = (lo + hi) / 2
    span = float(np.max(hi - lo))
    step = 10.0 ** max(0, math.floor(math.log10(max(span, 1.0))) - 1)  # keep the origin a round number
    origin = np.round(centre / step) * step
    origin[2] = 0.0 if abs(lo[2]) < 10 * max(span, 1.0) else math.floor(lo[2])
    return origin


def _subtree_boxes(parent: Sequence[int], lo: Sequence[np.ndarray], hi: Sequence[np.ndarray]
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Each node's box grown to hold its subtree's, so culling a node culls everything under it.

    A coarse terrain patch can lie below a finer child (its samples skip the peaks); parents come
    before children (``parent[j] < j``).
    """
    lo, hi = np.array(lo, np.float64), np.array(hi, np.float64)
    for j in range(len(parent) - 1, 0, -1):
        p = parent[j]
        if p >= 0:
            lo[p] = np.minimum(lo[p], lo[j])
            hi[p] = np.maximum(hi[p], hi[j])
    return lo, hi


def _is_ground(cls: str) -> bool:
    """Ground sheets (a TIN, ground tiles) keep plain border-pinned decimation: seen edge-on their
    silhouettes are a few pixels thick, so the silhouette measure says nothing about them."""
    return cls.lower() in ("terrain", "ground", "tin", "reliefFeature".lower())


def _is_building(cls: str) -> bool:
    return cls.lower() in _BUILDING_CLASSES


def build_store(
    path: str | os.PathLike[str],
    source: SourceScene,
    *,
    name: str | None = None,
    tour: list[dict] | None = None,
    viewpoints: dict[str, float] | None = None,
    seed: int | None = None,
    generator: str = "walkstream build",
    options: BuildOptions = BuildOptions(),
    progress: Progress | None = None,
    recentre: bool = True,
    default_tour: str | None = None,
) -> dict:
    """Build ``source`` into a new store at ``path`` (atomically); returns a summary.

    tour       : the camera tour in source coordinates (named "scene"); default: an orbit of the scene
                 (named "orbit"); either is the default tour, beside the street tours (``options``)
    viewpoints : named tour times (e.g. F&S's A, B, C) of that tour, recorded in meta
    default_tour: the name of a street tour ("walk", "flyover") to make the default where the scene has it
    """
    started = time.perf_counter()
    tick = progress or (lambda stage, done, total: None)
    source.check()
    bare = needs_ground(source)
    if options.ground and bare:
        source = replace(source, grids=[*source.grids, ground_grid(source)])
    origin = scene_origin(source) if recentre else np.zeros(3)
    workers = options.workers or default_workers()
    timings: dict[str, float] = {}

    # 1. chains
    t0 = time.perf_counter()
    objects = [o for o in source.objects if o.levels and all(m.n_faces for m in o.levels)]
    jobs = [([(m.positions - origin, m.faces) for m in o.levels], options.morph, options.min_saving,
             _is_building(o.cls), options.shape_guard and not _is_ground(o.cls), options.bounds,
             Appearance.of(o.levels[-1], origin), UVReference.of(o.levels[-1], origin))
            for o in objects]
    chains: list[tuple] = []
    tick("chains", 0, len(jobs))
    pooled = workers if len(jobs) >= POOL_MIN_JOBS else 1
    chunk = max(1, min(64, len(jobs) // (workers * 16)))
    for done, result in enumerate(pool_map(_chain_job, jobs, pooled, chunk), 1):
        chains.append(result)
        tick("chains", done, len(jobs))
    timings["chains"] = time.perf_counter() - t0

    # 2. HLOD over buildings
    t0 = time.perf_counter()
    classes = options.hlod_classes
    if classes is None:
        has_buildings = any(_is_building(o.cls) for o in objects)
        members = [i for i, o in enumerate(objects)
                   if (_is_building(o.cls) if has_buildings else o.cls not in ("terrain", "ground"))]
    else:
        members = [i for i, o in enumerate(objects) if o.cls in classes]
    use_hlod = options.hlod is True or (options.hlod == "auto" and len(members) >= options.hlod_min)
    tree = None
    if use_hlod and len(members) >= 2:
        from .hlod import build_hlod

        rows = [chains[i] for i in members]
        guarded = options.shape_guard and all(r.fidelity is not None for r in rows)
        tree = build_hlod(np.array([r.lo for r in rows]), np.array([r.hi for r in rows]),
                          [Mesh(*r.coarsest) for r in rows], object_error=np.array([r.errors[0] for r in rows]),
                          workers=workers, progress=lambda d, t: tick("hlod", d, t),
                          points=[r.sample for r in rows] if options.shape_guard else None,
                          bounds=options.bounds if guarded else None,
                          boxes=[r.box for r in rows] if guarded else None,
                          min_saving=options.min_saving, max_proxy_faces=options.max_proxy_faces)
    timings["hlod"] = time.perf_counter() - t0

    # 3. terrain quadtrees
    t0 = time.perf_counter()
    terrains = []
    if source.grids:
        from .source import HeightGrid
        from .terrain import build_quadtree

        for g in source.grids:
            shifted = HeightGrid(g.name, g.heights - origin[2], (g.origin[0] - origin[0], g.origin[1] - origin[1]),
                                 g.spacing, g.attributes)
            terrains.append((g.name, build_quadtree(shifted, patch=options.patch),
                             class_colour(str(g.attributes.get("class", "terrain")))))
            tick("terrain", len(terrains), len(source.grids))
    timings["terrain"] = time.perf_counter() - t0

    # 4. trees
    t0 = time.perf_counter()
    models = []
    groups = None
    if source.trees is not None and len(source.trees):
        from proto.points import encode_instances, encode_points

        from .points import point_model
        from .vegetation import group_trees

        for i, tm in enumerate(source.tree_models):
            pm = point_model(tm, n_points=options.points_per_model, seed=(seed or 0) * 7919 + i)
            models.append(pm)
            tick("tree models", i + 1, len(source.tree_models))
        shifted = source.trees.matrix.copy()
        shifted[:, :3, 3] -= origin
        from .source import TreeInstances

        placed = TreeInstances(source.trees.model, shifted, source.trees.names)
        groups = group_trees(placed, [int(m.positions.shape[0]) for m in models], max_group=options.max_group,
                             model_boxes=[(m.lo, m.hi) for m in models])
    timings["trees"] = time.perf_counter() - t0

    # 5. write
    t0 = time.perf_counter()
    levels, proxies = _guard_summary(chains, tree, options.bounds)
    counts = {k: 0 for k in ("mesh", "hlod", "terrain", "trees")}
    with SceneWriter(path, name=name or Path(path).stem, generator=generator, seed=seed) as writer:
        total = len(objects) + (int(tree.kept.sum()) if tree is not None else 0) + sum(
            len(t.parent) for _, t, _ in terrains) + (len(groups.group_first) if groups is not None else 0)
        written = 0

        def wrote() -> None:
            nonlocal written
            written += 1
            if written % 256 == 0 or written == total:
                tick("write", written, total)

        node_id = np.full(len(tree.parent) if tree is not None else 0, -1, np.int64)
        parent_of = np.full(len(objects), -1)
        if tree is not None:
            # Only kept nodes are written; each links to its nearest kept ancestor.
            up = tree.kept_parent()
            for j in np.flatnonzero(tree.kept):  # ascending ids: parents first
                p, f = tree.proxies[j].positions, tree.proxies[j].faces
                ref = Appearance.merge([rows[i].appearance for i in tree.leaves_under(int(j))])
                colours = None
                if ref is not None:
                    p, f, colours = coloured_mesh(ref, p, f)
                blob = encode_geometry(p, f, p.min(axis=0), p.max(axis=0), colours=colours)
                q = tree.fidelity[j] if tree.fidelity else None
                node_id[j] = writer.add_encoded(
                    f"hlod_{j}", "hlod", np.minimum(tree.lo[j], p.min(axis=0)), np.maximum(tree.hi[j], p.max(axis=0)),
                    [float(tree.error[j])], [blob], kind=HLOD, parent=-1 if up[j] < 0 else int(node_id[up[j]]),
                    fidelity=None if q is None else [q.as_tuple() + (bool(tree.closed[j]),)])
                counts["hlod"] += 1
                wrote()
            above = tree.kept_object_parent()
            parent_of[members] = np.where(above >= 0, node_id[np.maximum(above, 0)], -1)
        for i, (obj, rows) in enumerate(zip(objects, chains)):
            writer.add_encoded(obj.name, obj.cls, rows.lo, rows.hi, rows.errors, rows.blobs, kind=MESH,
                               parent=int(parent_of[i]), morphs=rows.morphs, fidelity=rows.fidelity)
            counts["mesh"] += 1
            wrote()
        tour_box = None  # the generated ground's padding is no part of what a tour looks at
        for tname, t, colour in terrains:
            if tname == GROUND_NAME and tour_box is None:
                tour_box = writer.bounds
            ids: list[int] = []
            patches = [t.mesh(j) for j in range(len(t.parent))]
            box_lo, box_hi = _subtree_boxes(t.parent, [p.min(axis=0) for p, _ in patches],
                                            [p.max(axis=0) for p, _ in patches])
            for j, (p, f) in enumerate(patches):
                parent = -1 if t.parent[j] < 0 else ids[t.parent[j]]
                # the geometry is quantized in its own box; the object's box bounds its whole subtree
                blob = encode_geometry(p, f, p.min(axis=0), p.max(axis=0),
                                       colours=constant(p.shape[0], colour))
                ids.append(writer.add_encoded(f"{tname}/patch_{j}", "terrain", box_lo[j], box_hi[j],
                                              [float(t.error[j])], [blob], kind=TERRAIN, parent=parent))
                counts["terrain"] += 1
                wrote()
        if groups is not None:
            for k, pm in enumerate(models):
                writer.add_model(pm.name, encode_points(pm), int(pm.positions.shape[0]), float(pm.radius[-1]),
                                 pm.lo, pm.hi)
            order = groups.order
            for g in range(len(groups.group_first)):
                sel = order[groups.group_first[g] : groups.group_first[g] + groups.group_count[g]]
                blob = encode_instances(placed.model[sel], placed.matrix[sel])
                writer.add_encoded(f"trees_{g}", "trees", groups.lo[g], groups.hi[g], [0.0], [blob], kind=TREES,
                                   counts=[(int(groups.points[g]), 0)])
                counts["trees"] += 1
                wrote()
        if tour_box is not None and groups is not None and len(groups.group_first):
            tour_box = (np.minimum(tour_box[0], groups.lo.min(axis=0)), np.maximum(tour_box[1], groups.hi.max(axis=0)))
        if tour is None:
            writer.set_tour(orbit_tour(*(tour_box if tour_box is not None else writer.bounds)), name="orbit",
                            kind="orbit")
        else:
            writer.set_tour([{**k, "eye": (np.asarray(k["eye"], np.float64) - origin).tolist()} for k in tour])
        if options.street_tours:
            writer.make_tours(_street_tours, prefer=(default_tour,) if default_tour else ())
        writer.set_meta(shape_guard={"levels": levels, **({"proxies": proxies} if proxies else {})},
                        origin=origin.tolist(), crs=source.crs, viewpoints=viewpoints or {}, sun=list(DEFAULT_SUN),
                        ground="generated" if tour_box is not None else ("none" if bare else "terrain"),
                        sources=list(source.sources), kinds=counts,
                        tree_instances=len(source.trees) if source.trees is not None else 0,
                        tree_models=[{"name": pm.name, "source": model_source(tm), "points": len(pm)}
                                     for tm, pm in zip(source.tree_models, models)])
    timings["write"] = time.perf_counter() - t0

    with SceneStore.open(path) as store:
        idx = store.index
        full = idx.rep_first + idx.rep_count - 1
        flat = idx.flat
        triangles = int(idx.rep_faces[full[flat]].sum())
        height = idx.height
        tours = {name: round(float(t["duration"]), 1) for name, t in named_tours(idx).items()}
    return {
        "path": str(path),
        "objects": counts,
        "representations": int(idx.n_representations),
        "triangles": triangles,
        "tree_instances": len(source.trees) if source.trees is not None else 0,
        "hierarchy_depth": height,
        "tours": tours,
        "bytes": Path(path).stat().st_size,
        "seconds": round(time.perf_counter() - started, 2),
        "stages": {k: round(v, 2) for k, v in timings.items()},
        "levels": levels,
        **({"proxies": proxies} if proxies is not None else {}),
    }


def _street_tours(store: SceneStore) -> dict:
    """The walk and flyover of a finished store (``SceneWriter.make_tours``)."""
    return scene_tours(store.index, store.walkable())


def _guard_summary(chains: list[ChainRows], tree, bounds: Bounds) -> tuple[dict, dict | None]:
    """What the shape guard did to the coarse levels, and to the HLOD proxies (None: no HLOD tree).

    levels : measured (coarse levels kept), below_bounds (of those, checked again: none, unless
             the guard is broken), regenerated (made by a
             later method of the ladder than decimation), dropped (a coarser level no candidate
             made within the bounds), methods (kept levels per method)
    proxies: nodes (clustered), kept (with a proxy within the bounds), measured, regenerated,
             dropped (not kept: the cut goes to their children), methods
    """
    measured = [q for c in chains if c.fidelity is not None for q in c.fidelity[:-1]]
    below = sum(not bounds.passes(Fidelity(q[1], q[2], q[3], q[0]), q[4])
                for c in chains if c.fidelity is not None for q in c.fidelity[:-1])
    levels = {"measured": len(measured), "below_bounds": int(below), "regenerated": int(sum(c.regenerated for c in chains)),
              "dropped": int(sum(c.dropped for c in chains)),
              "methods": {m: sum(q[0] == m for q in measured) for m in sorted({q[0] for q in measured})}}
    if tree is None:
        return levels, None
    fids = [q for q in tree.fidelity if q is not None]
    closed = [bool(c) for q, c in zip(tree.fidelity, tree.closed) if q is not None]
    proxies = {"nodes": int(tree.n_nodes), "kept": int(tree.kept.sum()), "measured": len(fids),
               "below_bounds": sum(not bounds.passes(q, c) for q, c in zip(fids, closed)),
               "regenerated": int(tree.regenerated), "dropped": int(tree.dropped),
               "methods": {m: sum(q.method == m for q in fids) for m in sorted({q.method for q in fids})}}
    return levels, proxies
