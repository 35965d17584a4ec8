"""glTF / GLB / OBJ / PLY → SourceScene through trimesh: one SourceObject per mesh node.

Each node's world transform is baked into its positions (an instanced mesh becomes
several objects, which is what LOD selection wants: each copy is culled on its own).
glTF is +y up, walkstream +z up, so glTF positions are rotated x→x, y→z, z→−y.

Appearance (``server.scene.palette``): a PLY's or OBJ's vertex or face colours as they
are; a material's base colour factor (glTF) or diffuse colour (OBJ), times its
base-colour texture's mean colour when it has one; a mesh with none of these is
drawn in its class colour.

Textures: a mesh whose material has a base-colour texture (glTF's
``baseColorTexture``, OBJ's ``map_Kd``) and whose vertices have UVs keeps both
(``Mesh.uv``, ``Mesh.texture``: the image times the colour factor, as glTF
multiplies them), beside the face colours above, so the textured algorithm
draws the image and flat and lit its mean. An image that cannot be read leaves
the factor alone, with a warning: a model with a broken texture still imports.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from ..palette import class_colour
from ..source import Mesh, SourceError, SourceObject, SourceScene

__all__ = ["MESH_SUFFIXES", "Y_UP_TO_Z_UP", "load_mesh_file"]

MESH_SUFFIXES = (".gltf", ".glb", ".obj", ".ply")

# Proper rotation (det +1, windings kept): +y → +z, +z → −y.
Y_UP_TO_Z_UP = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])

_log = logging.getLogger(__name__)

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
        _colour(mesh, geom, _cls(name))
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


def _colour(mesh: Mesh, geom, cls: str) -> None:
    """Give ``mesh`` the appearance trimesh read for its geometry (see the module docstring)."""
    visual = getattr(geom, "visual", None)
    kind = getattr(visual, "kind", None)
    if kind == "vertex" and len(visual.vertex_colors) == mesh.n_vertices:
        mesh.vertex_colours = np.ascontiguousarray(np.asarray(visual.vertex_colors)[:, :3], np.uint8)
        return
    if kind == "face" and len(visual.face_colors) == mesh.n_faces:
        mesh.face_colours = np.ascontiguousarray(np.asarray(visual.face_colors)[:, :3], np.uint8)
        return
    factor, image = _material_parts(getattr(visual, "material", None))
    colour = _material_colour(factor, image)
    mesh.face_colours = np.tile(np.asarray(colour if colour is not None else class_colour(cls), np.uint8),
                                (mesh.n_faces, 1))
    uv = getattr(visual, "uv", None)
    if image is not None and uv is not None:
        uv = np.asarray(uv, np.float64)
        if uv.shape == (mesh.n_vertices, 2) and np.isfinite(uv).all():
            mesh.uv, mesh.texture = uv, _times(image, factor)
        else:
            _log.warning("%s: its UVs %s do not fit its %d vertices; drawn without its texture",
                         cls, uv.shape, mesh.n_vertices)


def _material_parts(material) -> tuple[np.ndarray | None, np.ndarray | None]:
    """A material's colour factor (3,) float in [0, 1] — base colour factor (PBR) or diffuse (simple, OBJ's
    Kd) — and its base-colour texture (h, w, 3) uint8 rows top-down; each None where it sets none.

    The image is decoded here, once: pillow decodes lazily, and an image whose data is corrupt can fail
    its first decode and then pass as a half-filled one. One that fails is logged and left out.
    """
    if material is None:
        return None, None
    if hasattr(material, "baseColorFactor"):  # trimesh's PBR material (glTF): RGBA uint8
        factor, texture = material.baseColorFactor, getattr(material, "baseColorTexture", None)
    else:  # trimesh's simple material (OBJ's MTL)
        factor, texture = getattr(material, "diffuse", None), getattr(material, "image", None)
    if factor is not None:
        factor = np.asarray(factor, np.float64).reshape(-1)[:3] / 255.0
    image = None
    if texture is not None:
        try:
            image = np.ascontiguousarray(np.asarray(texture.convert("RGB"), np.uint8))
        except Exception as exc:  # pillow raises OSError, SyntaxError, zlib.error... on corrupt data
            _log.warning("a base-colour texture cannot be read (%s: %s); its material's colour is used instead",
                         type(exc).__name__, exc)
        else:
            if image.ndim != 3 or image.shape[2] != 3 or min(image.shape[:2]) < 1:
                image = None
    return factor, image


def _times(image: np.ndarray, factor: np.ndarray | None) -> np.ndarray:
    """The texture as drawn: (h, w, 3) uint8 image times the colour factor, as glTF multiplies them."""
    if factor is None or (factor == 1.0).all():
        return image
    return np.clip(np.rint(image * factor), 0, 255).astype(np.uint8)


def _material_colour(factor: np.ndarray | None, image: np.ndarray | None) -> tuple[int, int, int] | None:
    """A material's colour: its factor times its texture's mean; None for a material that sets neither."""
    if factor is None and image is None:
        return None
    rgb = np.ones(3) if factor is None else factor
    if image is not None:
        rgb = rgb * image.reshape(-1, 3).mean(axis=0) / 255.0
    r, g, b = (int(v) for v in np.rint(np.clip(rgb, 0.0, 1.0) * 255.0))
    return (r, g, b)


def _cls(name: str) -> str:
    """Semantic class from a node name like ``chair_01`` / ``Chair.003`` → ``chair``; else ``mesh``."""
    m = re.match(r"([A-Za-z]+)(?:[_.\-\s]|\d|$)", name)
    if m is None:
        return "mesh"
    prefix = m.group(1).lower()
    return "mesh" if prefix in _GENERIC or len(prefix) < 3 else prefix
