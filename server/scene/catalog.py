"""The named scenes ``walkstream build`` knows, and building any file a user passes.

Every named scene is deterministic from its seed:

- ``demo``       — the walking skeleton's sculpture garden;
- ``auditorium`` — Funkhouser & Séquin's test: ≥ 400 detailed chairs in a hall, tour through A, B, C;
- ``denhaag``    — the real Den Haag buildings and TIN terrain, plus generated trees on open ground;
- ``sthelens``   — the Mount St. Helens DEM as a terrain quadtree under a forest of splat trees;
- ``megacity``   — ≥ 40k generated buildings and ≥ 20M triangles, for scale benchmarks.

Anything else is taken as a path to a CityJSON, glTF/GLB, OBJ, PLY, USGS DEM,
``.npz`` height grid or CityGML file, built with generated tours: a ``walk`` through its
streets (its default tour, where it has streets), a ``flyover`` and an ``orbit``
(``server.scene.tour``). A named scene gets the street tours beside its own default tour.

Either kind can draw its trees with scanned tree models (``tree_models``: point-cloud
files, ``server.scene.scans``); a file's own trees may name theirs (the ``tree_model``
attribute), resolved against the file's folder.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from .builder import BuildOptions, Progress, build_store
from .data import data_file
from .source import HeightGrid, SourceError, SourceScene, TreeInstances, TreeModel

__all__ = ["BUILD_VERSION", "SCENES", "build_named", "build_path", "is_named", "load_tree_model", "with_tree_models"]

#: The version of what a build puts in a store. Bump when a build makes something a cached store
#: lacks — a new tour, colours an importer now reads — though the schema that holds it stays the
#: same: every cache key carries it (``bench.stores.cache_key``), so a store cached by an older build
#: is built anew instead of being reused. 2: the walk and flyover tours, CityGML appearances and
#: textures as colours. 3: CityJSON and CityGML textures drawn as textures (per-object atlas).
BUILD_VERSION = 3


@dataclass(frozen=True)
class Recipe:
    """How one named scene is made: its source, tour and build options."""

    make: Callable[..., tuple[SourceScene, list[dict] | None, dict]]
    options: BuildOptions
    help: str


def _auditorium(seed: int, size: int | None, progress: Progress) -> tuple:
    from .generate.auditorium import auditorium

    return auditorium(seed=seed)


def _megacity(seed: int, size: int | None, progress: Progress) -> tuple:
    from .generate.megacity import megacity

    return megacity(buildings=size or 40000, seed=seed,
                    progress=lambda d, t: progress("generate", d, t))


def _denhaag(seed: int, size: int | None, progress: Progress) -> tuple:
    from .importers.cityjson import load_cityjson
    from .vegetation import broadleaf, conifer

    scene = load_cityjson(data_file("city/DenHaag_01.city.json"))
    models = [broadleaf(seed + i) for i in range(4)] + [conifer(seed + 10 + i) for i in range(2)]
    scene.tree_models = models
    scene.trees = _trees_on_open_ground(scene, size or 1500, len(models), seed)
    return scene, None, {}


def _trees_on_open_ground(scene: SourceScene, n: int, models: int, seed: int) -> TreeInstances:
    """Trees on the TIN terrain wherever no building footprint is within 3 m (vectorised rejection)."""
    from scipy.interpolate import LinearNDInterpolator
    from scipy.spatial import cKDTree

    terrain = [o for o in scene.objects if o.cls == "terrain" or o.cls == "tinrelief"]
    if not terrain:
        return TreeInstances(np.zeros(0), np.zeros((0, 4, 4)))
    tin = terrain[0].levels[-1]
    ground = LinearNDInterpolator(tin.positions[:, :2], tin.positions[:, 2])
    footprints = np.concatenate([m.positions[:, :2] for o in scene.objects if o not in terrain
                                 for m in o.levels[-1:]])
    # Building outlines are sampled densely enough (facade vertices every few metres) to keep trees off them.
    edges = cKDTree(footprints)
    lo, hi = tin.positions[:, :2].min(axis=0), tin.positions[:, :2].max(axis=0)
    rng = np.random.default_rng(seed)
    kept = np.zeros((0, 3))
    while kept.shape[0] < n:
        xy = rng.uniform(lo, hi, (4 * n, 2))
        z = ground(xy)
        clear = edges.query(xy, k=1)[0] > 6.0
        ok = np.isfinite(z) & clear & ~_inside_any(xy, scene, terrain)
        kept = np.concatenate([kept, np.column_stack([xy[ok], z[ok]])])[:n]
        if not ok.any():
            break
    k = kept.shape[0]
    yaw = rng.uniform(0, 2 * np.pi, k)
    scale = rng.uniform(0.8, 1.2, k)
    m = np.zeros((k, 4, 4))
    m[:, 0, 0] = m[:, 1, 1] = np.cos(yaw) * scale
    m[:, 0, 1], m[:, 1, 0] = -np.sin(yaw) * scale, np.sin(yaw) * scale
    m[:, 2, 2] = scale
    m[:, :3, 3] = kept
    m[:, 3, 3] = 1.0
    return TreeInstances(rng.integers(0, models, k), m)


def _inside_any(xy: np.ndarray, scene: SourceScene, terrain: list) -> np.ndarray:
    """(k,) bool — points inside some building's xy box (a cheap, conservative footprint test)."""
    boxes = np.array([np.r_[o.levels[-1].positions[:, :2].min(axis=0), o.levels[-1].positions[:, :2].max(axis=0)]
                      for o in scene.objects if o not in terrain])
    from scipy.spatial import cKDTree

    centres = (boxes[:, :2] + boxes[:, 2:]) / 2
    reach = float(np.max(np.linalg.norm(boxes[:, 2:] - boxes[:, :2], axis=1))) / 2
    tree = cKDTree(centres)
    inside = np.zeros(xy.shape[0], bool)
    for i, near in enumerate(tree.query_ball_point(xy, reach)):
        if near:
            b = boxes[near]
            inside[i] = bool(((xy[i] >= b[:, :2]) & (xy[i] <= b[:, 2:])).all(axis=1).any())
    return inside


def resample_grid(grid: HeightGrid, n: int) -> HeightGrid:
    """The grid resampled to n × n samples over the same extent (cubic; voids stay voids).

    ZMK 2002 measure on a 2049² height field; the St. Helens DEM has 466 × 327. The
    extra samples are interpolated, not measured: this gives the paper's scale (patch
    count, triangles, build time), not more real detail.
    """
    from scipy import ndimage

    h = grid.heights
    rows, cols = h.shape
    void = ~np.isfinite(h)
    if void.any():  # fill voids from the nearest sample, so the spline does not smear NaN
        near = ndimage.distance_transform_edt(void, return_distances=False, return_indices=True)
        h = h[tuple(near)]
    zoom = ((n - 1) / (rows - 1), (n - 1) / (cols - 1))
    fine = ndimage.zoom(h, zoom, order=3, mode="nearest", grid_mode=False)[:n, :n]
    if void.any():
        fine[ndimage.zoom(void.astype(np.uint8), zoom, order=0, grid_mode=False)[:n, :n].astype(bool)] = np.nan
    spacing = (grid.spacing[0] * (cols - 1) / (n - 1), grid.spacing[1] * (rows - 1) / (n - 1))
    return HeightGrid(grid.name, fine, grid.origin, spacing, {**grid.attributes, "resampled_from": [rows, cols]})


def _sthelens(seed: int, size: int | None, progress: Progress, grid: int | None = None) -> tuple:
    from .importers.dem import load_dem
    from .vegetation import conifer, forest

    scene = load_dem(data_file("terrain/SainteHelens.dem"))
    if grid is not None:
        scene.grids = [resample_grid(scene.grids[0], grid)]
    models = [conifer(seed + i) for i in range(6)]
    scene.tree_models = models
    scene.trees = forest(scene.grids[0], size or 120_000, seed, len(models))
    return scene, None, {}


SCENES: dict[str, Recipe] = {
    "auditorium": Recipe(_auditorium, BuildOptions(hlod=False, ground=False),
                         "Funkhouser & Séquin's auditorium, ≥400 chairs"),
    "denhaag": Recipe(_denhaag, BuildOptions(), "Den Haag buildings + TIN terrain + generated trees"),
    "sthelens": Recipe(_sthelens, BuildOptions(), "St. Helens DEM quadtree + ≥100k splat trees"),
    "megacity": Recipe(_megacity, BuildOptions(), "≥40k generated buildings, ≥20M triangles"),
}


def load_tree_model(path: str | os.PathLike[str], seed: int = 0) -> TreeModel:
    """Read a point-cloud file (``importers.pointcloud``) as a tree model named after the file (``scans``)."""
    from .importers.pointcloud import read_point_cloud
    from .scans import scan_tree_model

    path = Path(path)
    return scan_tree_model(read_point_cloud(path), path.name.split(".")[0], str(path), seed=seed)


def with_tree_models(scene: SourceScene, files: Sequence[str | os.PathLike[str]], base: Path | None = None,
                     progress: Progress | None = None) -> SourceScene:
    """Draw the scene's trees with the scans of ``files`` and of the files its trees name (under ``base``)."""
    from .scans import named_files, use_tree_models

    tick = progress or (lambda stage, done, total: None)
    named_paths = named_files(scene, base) if base is not None else {}
    total = len(files) + len(named_paths)
    scans, named = [], {}
    for i, f in enumerate(files):
        scans.append(load_tree_model(f, seed=i))
        tick("tree scans", i + 1, total)
    for name, path in named_paths.items():
        named[name] = load_tree_model(path, seed=len(scans) + len(named))
        tick("tree scans", len(scans) + len(named), total)
    if scans or named:
        use_tree_models(scene, scans, named)
    return scene


def is_named(name: str) -> bool:
    return name in SCENES or name == "demo"


def build_named(name: str, path: str | os.PathLike[str], *, seed: int = 0, size: int | None = None,
                grid: int | None = None, workers: int | None = None, progress: Progress | None = None,
                tree_models: Sequence[str | os.PathLike[str]] = ()) -> dict:
    """Build the named scene into ``path``; ``size`` scales it (buildings, trees) where that makes sense,
    ``grid`` resamples a height-field scene's DEM to grid × grid samples (``sthelens`` only),
    ``tree_models`` (point-cloud files) draw its trees instead of the generated models."""
    if grid is not None and (name != "sthelens" or not 2 <= grid <= 8193):
        raise ValueError(f"--grid resamples the sthelens DEM to 2..8193 samples a side; got {grid} for {name!r}")
    tick = progress or (lambda stage, done, total: None)
    if name == "demo":
        from .demo import build_demo

        if tree_models:
            raise SourceError("demo: the scene has no trees to draw with tree models")
        return build_demo(path, objects=size or 576, seed=seed, workers=workers,
                          progress=lambda d, t: tick("objects", d, t))
    if name not in SCENES:
        raise KeyError(f"unknown scene {name!r}; named scenes: demo, {', '.join(SCENES)}")
    recipe = SCENES[name]
    source, tour, viewpoints = recipe.make(seed, size, tick, **({"grid": grid} if grid else {}))
    with_tree_models(source, tree_models, progress=tick)
    options = replace(recipe.options, workers=workers) if workers else recipe.options
    return build_store(path, source, name=name, tour=tour, viewpoints=viewpoints, seed=seed,
                       generator=f"walkstream build {name}", options=options, progress=tick)


def build_path(source: str | os.PathLike[str], path: str | os.PathLike[str], *, workers: int | None = None,
               progress: Progress | None = None, tree_models: Sequence[str | os.PathLike[str]] = ()) -> dict:
    """Import a user's file and build it, with generated tours (the walk the default where there is one);
    ``tree_models`` as in ``build_named``."""
    from .importers import load_source

    scene = with_tree_models(load_source(Path(source)), tree_models, Path(source).parent, progress)
    options = BuildOptions(workers=workers) if workers else BuildOptions()
    return build_store(path, scene, name=Path(source).name.split(".")[0], generator=f"walkstream build {source}",
                       options=options, progress=progress, default_tour="walk")
