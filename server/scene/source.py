"""What importers and generators hand to the scene builder: plain meshes, height grids, tree instances.

These are the in-memory form of a scene *before* LOD chains, hierarchies and
encoding. Coordinates are float64 in the source's own frame (a CityJSON file in
EPSG:7415 keeps its metres east/north/up); the builder recentres on an origin
it records, so float32 on the GPU keeps centimetres. The up axis is +z
everywhere in walkstream (CityJSON, CityGML and DEMs are all z-up; glTF's +y up
is rotated to +z by its importer).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Mesh", "PointCloud", "SourceObject", "HeightGrid", "TreeModel", "TreeInstances", "SourceScene",
           "SourceError"]


class SourceError(ValueError):
    """Input that cannot be imported; the message names the file and the place in it."""


@dataclass
class Mesh:
    """A triangle mesh: positions (n, 3) float64, faces (m, 3) int64 with every entry < n.

    Its appearance, when the source gives one (``server.scene.palette`` says from what):
    face_colours   : (m, 3) uint8 RGB per face — semantic surfaces, materials; or None
    vertex_colours : (n, 3) uint8 RGB per vertex — colours that vary across a surface; or None
    A mesh has at most one of the two; the builder carries either through its levels
    (``server.scene.colours``).
    uv             : (n, 2) float64 texture coordinates (OpenGL's: v = 0 at the image's bottom row); or None
    texture        : (h, w, 3) uint8 RGB base-colour texture, rows top-down, with ``uv``; or None
    A textured mesh keeps its colours too (the material's colour), which the flat and lit
    algorithms draw; the builder gives every level its own UVs and texture
    (``server.scene.texcoords``).
    """

    positions: np.ndarray
    faces: np.ndarray
    face_colours: np.ndarray | None = None
    vertex_colours: np.ndarray | None = None
    uv: np.ndarray | None = None
    texture: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.positions = np.asarray(self.positions, np.float64).reshape(-1, 3)
        self.faces = np.asarray(self.faces, np.int64).reshape(-1, 3)
        if self.face_colours is not None and self.vertex_colours is not None:
            raise ValueError("a mesh has face colours or vertex colours, not both")
        if self.face_colours is not None:
            self.face_colours = _rgb8(self.face_colours, self.faces.shape[0], "face_colours")
        if self.vertex_colours is not None:
            self.vertex_colours = _rgb8(self.vertex_colours, self.positions.shape[0], "vertex_colours")
        if (self.uv is None) != (self.texture is None):
            raise ValueError("a mesh has uv and texture together, or neither")
        if self.uv is not None:
            self.uv = np.asarray(self.uv, np.float64)
            if self.uv.shape != (self.n_vertices, 2) or not np.isfinite(self.uv).all():
                raise ValueError(f"uv must be ({self.n_vertices}, 2) finite, got {self.uv.shape}")
            t = np.asarray(self.texture)
            if t.ndim != 3 or t.shape[2] != 3 or t.dtype != np.uint8 or min(t.shape[:2]) < 1:
                raise ValueError(f"texture must be (h, w, 3) uint8, got {t.dtype} {t.shape}")
            self.texture = t

    @property
    def textured(self) -> bool:
        return self.texture is not None

    @property
    def coloured(self) -> bool:
        return self.face_colours is not None or self.vertex_colours is not None

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def n_vertices(self) -> int:
        return int(self.positions.shape[0])


def _rgb8(colours, n: int, name: str) -> np.ndarray:
    c = np.asarray(colours)
    if c.shape != (n, 3) or c.dtype != np.uint8:
        raise ValueError(f"{name} must be ({n}, 3) uint8, got {c.dtype} {c.shape}")
    return c


@dataclass
class SourceObject:
    """One object as the source gives it.

    levels : coarsest → finest; usually one (full detail). A source that carries
             several LoDs of one object (CityJSON LoD 1.2 / 1.3 / 2.2) gives them all,
             and the builder keeps them as the object's LOD chain.
    cls    : semantic class ("building", "terrain", "chair", ...), the Importance key
    """

    name: str
    cls: str
    levels: list[Mesh]
    attributes: dict = field(default_factory=dict)


@dataclass
class HeightGrid:
    """A regular height field: heights[row, col] at (origin[0] + col·spacing[0], origin[1] + row·spacing[1]).

    heights : (rows, cols) float64; NaN where the source has no sample
    origin  : (x, y) of sample [0, 0]
    spacing : (dx, dy) > 0
    """

    name: str
    heights: np.ndarray
    origin: tuple[float, float]
    spacing: tuple[float, float]
    attributes: dict = field(default_factory=dict)


@dataclass
class PointCloud:
    """Measured points (a laser scan), as a point-cloud file gives them.

    positions : (n, 3) float64
    colors    : (n, 3) uint8, or None when the file has none
    normals   : (n, 3) float64 unit vectors, or None when the file has none
    """

    positions: np.ndarray
    colors: np.ndarray | None = None
    normals: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.positions = np.asarray(self.positions, np.float64).reshape(-1, 3)
        n = self.positions.shape[0]
        if self.colors is not None:
            self.colors = np.asarray(self.colors, np.uint8).reshape(n, 3)
        if self.normals is not None:
            self.normals = np.asarray(self.normals, np.float64).reshape(n, 3)

    def __len__(self) -> int:
        return int(self.positions.shape[0])


@dataclass
class TreeModel:
    """A tree prototype in model space (base at the origin, z up): a mesh, or a scan's points.

    mesh   : the surface the splats are sampled from (generated and CityGML prototypes)
    points : the splats themselves, for a scanned tree (``server.scene.scans``); then
             ``mesh`` is None and every point has a colour and a normal
    """

    name: str
    mesh: Mesh | None
    attributes: dict = field(default_factory=dict)
    points: PointCloud | None = None


@dataclass
class TreeInstances:
    """Placed trees: instance i draws ``models[model[i]]`` with the 4×4 ``matrix[i]`` (model → world).

    model_file : per instance, a point-cloud file the source names for that tree (the
                 ``tree_model`` attribute, ``server.scene.scans``), or None; empty: none do
    """

    model: np.ndarray  # (k,) int32
    matrix: np.ndarray  # (k, 4, 4) float64
    names: list[str] = field(default_factory=list)
    model_file: list[str | None] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.model = np.asarray(self.model, np.int32).reshape(-1)
        self.matrix = np.asarray(self.matrix, np.float64).reshape(-1, 4, 4)

    def __len__(self) -> int:
        return int(self.model.shape[0])


@dataclass
class SourceScene:
    """Everything one or more sources hold: meshes, height grids, tree models and their instances."""

    objects: list[SourceObject] = field(default_factory=list)
    grids: list[HeightGrid] = field(default_factory=list)
    tree_models: list[TreeModel] = field(default_factory=list)
    trees: TreeInstances | None = None
    crs: str | None = None
    sources: list[str] = field(default_factory=list)

    def check(self) -> None:
        """Raise ``SourceError`` naming the first object, grid or tree the builder could not use.

        Importers check their files; this catches what a generator or an API caller hands
        over (a NaN vertex, an index past the end), before any work is spent on it.
        """
        for obj in self.objects:
            for k, m in enumerate(obj.levels):
                where = f"object {obj.name!r} level {k}"
                if not np.isfinite(m.positions).all():
                    raise SourceError(f"{where}: a vertex position is not a finite number")
                if m.n_faces and (m.faces.min() < 0 or m.faces.max() >= m.n_vertices):
                    raise SourceError(f"{where}: a face index lies outside 0..{m.n_vertices - 1}")
        for g in self.grids:
            if g.heights.ndim != 2 or min(g.heights.shape) < 2 or not np.isfinite(g.heights).any():
                raise SourceError(f"height grid {g.name!r}: needs at least 2 × 2 samples, some of them finite")
            if not (np.isfinite(g.spacing).all() and min(g.spacing) > 0 and np.isfinite(g.origin).all()):
                raise SourceError(f"height grid {g.name!r}: origin {g.origin} / spacing {g.spacing} not finite and > 0")
        for t in self.tree_models:
            if t.points is not None:
                p = t.points
                if len(p) == 0 or not np.isfinite(p.positions).all() or p.colors is None or p.normals is None:
                    raise SourceError(f"tree model {t.name!r}: needs finite points, each with a colour and a normal")
            elif t.mesh is None or not np.isfinite(t.mesh.positions).all() or t.mesh.n_faces == 0:
                raise SourceError(f"tree model {t.name!r}: needs faces and finite vertices")
        if self.trees is not None and len(self.trees):
            bad = np.nonzero(~np.isfinite(self.trees.matrix).all(axis=(1, 2)))[0]
            if bad.size:
                name = self.trees.names[bad[0]] if len(self.trees.names) > bad[0] else f"#{bad[0]}"
                raise SourceError(f"tree {name}: its matrix is not finite ({bad.size} trees like it)")
            m = self.trees.model
            if m.min() < 0 or m.max() >= len(self.tree_models):
                raise SourceError(f"tree instances refer to model {int(m.max())}, "
                                  f"but the scene has {len(self.tree_models)} tree models")
