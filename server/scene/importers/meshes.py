"""glTF / GLB / OBJ / PLY → SourceScene through trimesh: one SourceObject per mesh node.

Each node's world transform is baked into its positions (an instanced mesh becomes
several objects, which is what LOD selection wants: each copy is culled on its own).
glTF is +y up, walkstream +z up, so glTF positions are rotated x→x, y→z, z→−y.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..source import Mesh, SourceError, SourceObject, SourceScene

__all__ = ["MESH_SUFFIXES", "Y_UP_TO_Z_UP", "load_mesh_file"]

MESH_SUFFIXES = (".gltf", ".glb", ".obj", ".ply")

# Proper rotation (det +1, windings kept): +y → +z, +z → −y.
Y_UP_TO_Z_UP = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])

# Node-name prefixes that say nothing about what the object is.
_GENERIC = {"geometry", "mesh", "node", "object", "obj", "scene", "group", "default", "primitive"}


def load_mesh_file(path: str | Path) -> SourceScene:
    """Import a glTF/GLB/OBJ/PLY file; ``SourceError`` names the file (and node) on failure."""
    import trimesh

    path = Path(path)
    kind = path.suffix.lower()
    if kind not in MESH_SUFFIXES:
        raise SourceError(f"{path}: not a mesh file (supported: {', '.join(MESH_SUFFIXES)})")
    if not path.is_file():
        raise SourceError(f"{path}: file not found")
    # OBJ: one object per "o" block rather than one merged mesh.
    options = {"split_objects": True, "group_material": False} if kind == ".obj" else {}
    try:
        scene = trimesh.load(path, force="scene", process=False, **options)
    except Exception as exc:  # trimesh raises anything from KeyError to struct.error on bad input
        raise SourceError(f"{path}: cannot read as {kind[1:].upper()} ({type(exc).__name__}: {exc})") from None
    up = Y_UP_TO_Z_UP if kind in (".gltf", ".glb") else np.eye(4)
    objects, skipped = [], []
    for node in sorted(scene.graph.nodes_geometry):
        transform, geom_name = scene.graph[node]
        geom = scene.geometry.get(geom_name)
        if not isinstance(geom, trimesh.Trimesh) or len(geom.faces) == 0:
            skipped.append(node)  # points, lines, empty meshes: nothing to draw
            continue
        name = path.stem if node == path.name else str(node)
        mesh = _node_mesh(path, node, geom, up @ np.asarray(transform, np.float64))
        objects.append(SourceObject(name, _cls(name), [mesh],
                                    {"node": str(node), "geometry": str(geom_name), "format": kind[1:]}))
    if not objects:
        what = f" (nodes without triangles: {', '.join(map(str, skipped))})" if skipped else ""
        raise SourceError(f"{path}: no triangle geometry{what}")
    return SourceScene(objects=objects, sources=[str(path)])


def _node_mesh(path: Path, node: str, geom, matrix: np.ndarray) -> Mesh:
    """The node's triangles in world (z-up) coordinates, checked for NaNs and bad indices."""
    where = f"{path}: node {node!r}"
    positions = np.asarray(geom.vertices, np.float64).reshape(-1, 3)
    faces = np.asarray(geom.faces, np.int64).reshape(-1, 3)
    finite = np.isfinite(positions).all(axis=1)
    if not finite.all():
        i = int(np.argmin(finite))
        raise SourceError(f"{where}: vertex {i} = {positions[i].tolist()} is not finite")
    bad = (faces < 0) | (faces >= positions.shape[0])
    if bad.any():
        f = int(np.flatnonzero(bad.any(axis=1))[0])
        raise SourceError(f"{where}: face {f} = {faces[f].tolist()} indexes outside "
                          f"the {positions.shape[0]} vertices")
    if not np.isfinite(matrix).all():
        raise SourceError(f"{where}: node transform is not finite")
    world = positions @ matrix[:3, :3].T + matrix[:3, 3]
    if np.linalg.det(matrix[:3, :3]) < 0:
        faces = faces[:, ::-1]  # a mirroring transform would turn the mesh inside out
    return Mesh(world, faces)


def _cls(name: str) -> str:
    """Semantic class from a node name like ``chair_01`` / ``Chair.003`` → ``chair``; else ``mesh``."""
    m = re.match(r"([A-Za-z]+)(?:[_.\-\s]|\d|$)", name)
    if m is None:
        return "mesh"
    prefix = m.group(1).lower()
    return "mesh" if prefix in _GENERIC or len(prefix) < 3 else prefix
