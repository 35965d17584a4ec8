"""Scanned trees as tree models, and a scene's trees drawn with them.

A scan comes in its file's coordinates (often georeferenced: the AHN3 tree sits
at its Dutch national grid offset) and is put into model space the way the
generated models are (``server.scene.vegetation``): z up, the trunk's foot at
the origin. The trunk axis is the median xy of the points in the lowest tenth
of the tree's height; the foot is the lowest point's z. A scan of more than
``MAX_SCAN_POINTS`` points is thinned on a voxel grid first (one point per
voxel, the voxel chosen so about that many remain), because ordering it is
the expensive part and the builder keeps only a prefix anyway.

Each point then gets what a generated model's splat carries
(``server.scene.points.PointModel``): a normal — the direction of least spread
of its ``NEIGHBOURS`` nearest points, turned away from the tree (from the
trunk axis below the crown's centre, from that centre above it) — and a colour,
the file's own or else ``points.tree_colors``' bark and foliage. The model
records its point spacing (the median distance to the 4th nearest point), from
which ``points.point_model`` sizes the splats; the order for prefix resolution
is the same K-d order as every tree model's (``points.prefix_tree``).

**Which tree gets which scan.** ``use_tree_models`` replaces the models of a
scene's trees: an instance that names a file (the ``tree_model`` attribute of a
CityGML or CityJSON vegetation object, ``TreeInstances.model_file``) gets that
scan; every other tree gets one of the scans given to the build, by shape: the
trees ranked by crown width / height, and the scans likewise, the slenderest
1/J of the trees take the slenderest of J scans, and so on — so every scan is
used and a columnar tree does not get a round crown. A scan keeps its
proportions: it is scaled uniformly to the tree's height, turned by the tree's
yaw and stood on the tree's foot. A vegetation object given as a mesh (CityJSON
trees, CityGML trees with explicit geometry) becomes such a tree too, its
height and crown width its mesh's.

Files are read by ``importers.pointcloud`` and turned into models by
``catalog.load_tree_model``; this module only works on arrays.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .points import tree_colors
from .source import PointCloud, SourceError, SourceScene, TreeInstances, TreeModel

__all__ = ["MAX_SCAN_POINTS", "NEIGHBOURS", "TREE_MODEL_ATTRIBUTE", "VEGETATION_CLASSES", "scan_tree_model",
           "named_files", "use_tree_models", "model_source"]

MAX_SCAN_POINTS = 1 << 18
NEIGHBOURS = 10
#: The attribute by which a CityGML/CityJSON vegetation object names its point-cloud file.
TREE_MODEL_ATTRIBUTE = "tree_model"
#: Source classes of vegetation objects given as meshes (CityJSON, CityGML explicit geometry).
VEGETATION_CLASSES = ("solitaryvegetationobject", "tree")


def _thin(p: np.ndarray, target: int) -> np.ndarray:
    """Indices (sorted) of at most ``target`` points of p (n, 3): the first point in each voxel of the
    finest cubic grid that leaves no more than that many (bisected in log voxel size)."""
    lo = p.min(axis=0)
    span = float(np.max(p.max(axis=0) - lo)) or 1.0

    def first_per_voxel(voxel: float) -> np.ndarray:
        cell = np.floor((p - lo) / voxel).astype(np.int64)
        side = int(cell.max()) + 1
        _, first = np.unique((cell[:, 0] * side + cell[:, 1]) * side + cell[:, 2], return_index=True)
        return first

    fine, coarse = span / min(4.0 * target, 2e6), span  # too many points / one point (keys fit int64)
    keep = first_per_voxel(coarse)
    for _ in range(24):
        mid = float(np.sqrt(fine * coarse))
        got = first_per_voxel(mid)
        if got.size > target:
            fine = mid
        else:
            coarse, keep = mid, got
    return np.sort(keep)


def _normals(p: np.ndarray, neighbours: np.ndarray, centre_z: float) -> np.ndarray:
    """(n, 3) unit normals from the covariance of each point's neighbours (n, k), turned outward."""
    nb = p[neighbours]  # (n, k, 3)
    d = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", d, d)
    _, vectors = np.linalg.eigh(cov)
    normal = vectors[:, :, 0]  # eigh sorts eigenvalues ascending: least spread first
    out = p - np.column_stack([np.zeros((p.shape[0], 2)), np.minimum(p[:, 2], centre_z)])
    flip = np.einsum("ni,ni->n", normal, out) < 0
    normal[flip] *= -1
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    return np.where(length > 1e-12, normal / np.maximum(length, 1e-12), [0.0, 0.0, 1.0])


def scan_tree_model(cloud: PointCloud, name: str, source: str, *, max_points: int = MAX_SCAN_POINTS,
                    seed: int = 0) -> TreeModel:
    """A scan as a tree model in model space, every point with a normal and a colour (module docstring)."""
    from scipy.spatial import cKDTree

    p = np.asarray(cloud.positions, np.float64)
    if p.shape[0] < 2:
        raise SourceError(f"{source}: a tree model needs at least 2 points, the file has {p.shape[0]}")
    keep = _thin(p, max_points) if p.shape[0] > max_points else np.arange(p.shape[0])
    p = p[keep]
    z0, z1 = float(p[:, 2].min()), float(p[:, 2].max())
    height = z1 - z0
    if height <= 0:
        raise SourceError(f"{source}: the points are flat (no height): not a tree")
    foot = p[:, 2] <= z0 + 0.1 * height
    axis = np.median(p[foot, :2], axis=0)
    offset = np.array([axis[0], axis[1], z0])
    p = p - offset
    tree = cKDTree(p)
    k = min(NEIGHBOURS, p.shape[0])
    dist, idx = tree.query(p, k=k)
    spacing = float(np.median(dist[:, min(4, k - 1)]))
    normals = cloud.normals[keep] if cloud.normals is not None else _normals(p, idx, float(p[:, 2].mean()))
    colors = cloud.colors[keep] if cloud.colors is not None else tree_colors(p, seed=seed)
    width = float(np.mean(p[:, :2].max(axis=0) - p[:, :2].min(axis=0)))
    attributes = {"generator": "scan", "source": source, "height": height, "crown_width": width,
                  "spacing": spacing, "scan_points": len(cloud), "offset": offset.tolist()}
    return TreeModel(name, None, attributes, PointCloud(p, colors, normals))


def _object_file(obj) -> str | None:
    attrs = obj.attributes or {}
    value = attrs.get(TREE_MODEL_ATTRIBUTE)
    if value is None and isinstance(attrs.get("attributes"), dict):  # CityJSON keeps its attributes nested
        value = attrs["attributes"].get(TREE_MODEL_ATTRIBUTE)
    return None if value in (None, "") else str(value)


def named_files(scene: SourceScene, base: Path) -> dict[str, Path]:
    """The point-cloud files the scene's trees name, each as written → resolved against ``base``."""
    names = [f for f in (scene.trees.model_file if scene.trees is not None else []) if f]
    names += [f for o in scene.objects if o.cls in VEGETATION_CLASSES and (f := _object_file(o))]
    out = {}
    for name in dict.fromkeys(names):
        path = Path(name) if Path(name).is_absolute() else base / name
        if not path.is_file():
            raise SourceError(f"{scene.sources[0] if scene.sources else base}: a tree's {TREE_MODEL_ATTRIBUTE} "
                              f"names {name!r}, which is not a file ({path})")
        out[name] = path
    return out


def model_source(model: TreeModel) -> str:
    """Where a tree model came from, for ``walkstream inspect``: a file, a generator, or a prototype."""
    a = model.attributes
    if a.get("source"):
        return str(a["source"])
    if a.get("generator"):
        return f"generated ({a['generator']}, seed {a.get('seed')})"
    return f"prototype {a['id']}" if a.get("id") else "source"


def _model_shape(model: TreeModel) -> tuple[np.ndarray, np.ndarray]:
    """Model-space box (lo, hi) of a tree model's mesh or points."""
    p = model.points.positions if model.points is not None else model.mesh.positions
    return p.min(axis=0), p.max(axis=0)


def _by_shape(aspect: np.ndarray, scan_aspect: np.ndarray) -> np.ndarray:
    """(k,) index into the scans: trees and scans both ranked by aspect, rank quantiles matched."""
    k, j = aspect.size, scan_aspect.size
    scans = np.argsort(scan_aspect, kind="stable")
    rank = np.empty(k, np.int64)
    rank[np.argsort(aspect, kind="stable")] = np.arange(k)
    return scans[rank * j // max(k, 1)]


def _placed(base: np.ndarray, yaw: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """(k, 4, 4) model → world: uniform scale, then yaw about z, then the foot at ``base`` (k, 3)."""
    m = np.zeros((base.shape[0], 4, 4))
    c, s = np.cos(yaw) * scale, np.sin(yaw) * scale
    m[:, 0, 0], m[:, 0, 1], m[:, 1, 0], m[:, 1, 1], m[:, 2, 2] = c, -s, s, c, scale
    m[:, :3, 3] = base
    m[:, 3, 3] = 1.0
    return m


def use_tree_models(scene: SourceScene, scans: list[TreeModel], named: dict[str, TreeModel] | None = None) -> int:
    """Draw the scene's trees with scans (in place); returns how many trees now use a scan.

    scans : the build's tree models (``--tree-model``), shared out by shape
    named : the scans of the files the scene's trees name (``named_files``, loaded), by name as written
    Trees the scans do not reach keep their models; models no tree uses are dropped.
    Raises ``SourceError`` when scans are given but the scene has no trees.
    """
    named = named or {}
    veg = [o for o in scene.objects if o.cls in VEGETATION_CLASSES and (scans or _object_file(o))]
    old = scene.trees if scene.trees is not None else TreeInstances(np.zeros(0), np.zeros((0, 4, 4)))
    if scans and not len(old) and not veg:
        raise SourceError(f"{', '.join(scene.sources) or 'the scene'}: it has no trees to draw with the tree "
                          f"models ({', '.join(model_source(s) for s in scans)})")
    # Every tree as (foot, yaw, height, crown width): instances through their matrices, meshes by their boxes.
    k = len(old)
    if k:
        boxes = np.array([_model_shape(m) for m in scene.tree_models]).reshape(-1, 2, 3)
        lo, hi = boxes[old.model, 0], boxes[old.model, 1]
        a = old.matrix[:, :3, :3]
        foot = np.einsum("kij,kj->ki", a, np.column_stack([np.zeros((k, 2)), lo[:, 2]])) + old.matrix[:, :3, 3]
        yaw = np.arctan2(a[:, 1, 0], a[:, 0, 0])
        height = (hi[:, 2] - lo[:, 2]) * np.abs(a[:, 2, 2])
        width = (hi[:, :2] - lo[:, :2]).mean(axis=1) * np.sqrt(np.abs(np.linalg.det(a[:, :2, :2])))
    else:
        foot, yaw, height, width = np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(0)
    vlo = np.array([o.levels[-1].positions.min(axis=0) for o in veg]).reshape(-1, 3)
    vhi = np.array([o.levels[-1].positions.max(axis=0) for o in veg]).reshape(-1, 3)
    foot = np.concatenate([foot, np.column_stack([(vlo[:, :2] + vhi[:, :2]) / 2, vlo[:, 2]])])
    yaw = np.concatenate([yaw, np.zeros(len(veg))])
    height = np.concatenate([height, vhi[:, 2] - vlo[:, 2]])
    width = np.concatenate([width, (vhi[:, :2] - vlo[:, :2]).mean(axis=1)])
    files = (list(old.model_file) or [None] * k) + [_object_file(o) for o in veg]
    names = (list(old.names) or [f"tree{i + 1}" for i in range(k)]) + [o.name for o in veg]
    bad = np.flatnonzero(~(np.isfinite(height) & (height > 0)))
    if bad.size:
        raise SourceError(f"tree {names[int(bad[0])]}: has no height to fit a tree model to")

    # Models: the scene's first, then the build's scans, then the named ones; unused ones dropped below.
    models = list(scene.tree_models) + list(scans) + list(named.values())
    first_named = {name: len(scene.tree_models) + len(scans) + i for i, name in enumerate(named)}
    n = height.size
    model = np.r_[old.model.astype(np.int64), np.full(len(veg), -1)]
    scanned = np.zeros(n, bool)
    if scans:
        model_scan = np.array([s.attributes["crown_width"] / s.attributes["height"] for s in scans])
        model[:] = len(scene.tree_models) + _by_shape(width / height, model_scan)
        scanned[:] = True
    for i, f in enumerate(files):
        if f:
            if f not in first_named:
                raise SourceError(f"tree {names[i]}: its {TREE_MODEL_ATTRIBUTE} {f!r} was not loaded")
            model[i], scanned[i] = first_named[f], True
    matrix = np.r_[old.matrix, np.zeros((len(veg), 4, 4))]
    if scanned.any():
        model_height = np.array([m.attributes.get("height", np.nan) if m.points is not None else np.nan
                                 for m in models])
        matrix[scanned] = _placed(foot[scanned], yaw[scanned], height[scanned] / model_height[model[scanned]])
    used, model = np.unique(model, return_inverse=True)
    scene.tree_models = [models[m] for m in used]
    scene.trees = TreeInstances(model, matrix, names)
    gone = {id(o) for o in veg}
    scene.objects = [o for o in scene.objects if id(o) not in gone]
    return int(scanned.sum())
