"""CityJSON 1.0 / 1.1 / 2.0 → SourceScene: one SourceObject per CityObject with surface geometry.

An object's geometries at different LoDs become its levels, coarsest → finest, which
is the LOD chain the builder keeps. Every surface gets a colour (``Mesh.face_colours``):
its texture's mean colour (``server.scene.importers.textures``; the geometry's first
texture theme), else its material's ``diffuseColor`` (the first material theme), else
its semantic type's, else its object's IFC or class colour (``server.scene.palette``).
The texture wins over the material for the reason the CityGML importer gives
(``citygml_appearance``): the texture is the surface's measurement, the material its
constant approximation; a texture whose image cannot be read (warned once per image)
leaves the material or semantic colour.

**Textures drawn.** A textured ring's values ``[t, i0, i1, ...]`` give, per ring vertex, an
index into ``appearance["vertices-texture"]`` (u, v pairs, v = 0 at the image's bottom).
Those UVs ride on each ring corner through the triangulation, and an object with a
readable texture gets one atlas of its images and per-vertex UVs in it on every level
that has a textured face (``server.scene.importers.atlas``: repeating UVs are wrapped per
polygon and clamped; surfaces without an image get a patch of their colour), its
vertices split where their corners' UVs differ. Geometry instances are not textured.

All polygons of the file are triangulated in one vectorised pass (polygons.py), by ring
corner, so a face knows its corners' UVs; each level then gets a compact vertex array of
its own.
The whole file is validated before anything is returned, so a malformed file never
yields a partial scene.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np

from ..palette import class_colour, ifc_colour, rgb8, surface_colour
from ..source import Mesh, SourceError, SourceObject, SourceScene
from .polygons import Rings, flatten_polygons, triangulate_rings
from .atlas import object_texture, split_by_uv
from .textures import TextureImages

__all__ = ["SUPPORTED_VERSIONS", "load_cityjson", "normalise_crs"]

SUPPORTED_VERSIONS = ("1.0", "1.1", "2.0")

# How many list levels sit above a polygon (list of rings) in each geometry type's boundaries.
_DEPTH = {"MultiSurface": 1, "CompositeSurface": 1, "Solid": 2, "MultiSolid": 3, "CompositeSolid": 3}
_NO_SURFACES = {"MultiPoint", "MultiLineString"}  # valid CityJSON, nothing to draw


def load_cityjson(path: str | Path) -> SourceScene:
    """Read a CityJSON file; ``SourceError`` names the file and the offending place on malformed input."""
    path = Path(path)
    doc = _read_json(path)
    _check_header(path, doc)
    vertices = _vertices(path, doc)
    city_objects = doc.get("CityObjects")
    if not isinstance(city_objects, dict):
        raise SourceError(f"{path}: 'CityObjects' is missing or not an object")
    walk = _Walk(path, vertices, doc.get("geometry-templates"), _materials(path, doc), _textures(path, doc),
                 _texture_vertices(path, doc))
    for oid, obj in city_objects.items():
        walk.add_object(str(oid), obj)
    objects = walk.build()
    if not objects:
        raise SourceError(f"{path}: no CityObject has surface geometry")
    return SourceScene(objects=objects, crs=normalise_crs(_reference_system(doc)), sources=[str(path)])


def normalise_crs(ref: str | None) -> str | None:
    """``urn:ogc:def:crs:EPSG::7415`` / ``https://www.opengis.net/def/crs/EPSG/0/7415`` → ``EPSG:7415``."""
    if ref is None:
        return None
    ref = str(ref).strip()
    m = (re.search(r"EPSG/[^/]*/(\d+)\s*$", ref, re.I) or re.search(r"EPSG:[\d.]*:(\d+)\s*$", ref, re.I)
         or re.fullmatch(r"EPSG:(\d+)", ref, re.I))
    return f"EPSG:{m.group(1)}" if m else ref


def _read_json(path: Path) -> dict:
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise SourceError(f"{path}: cannot read ({exc.strerror or exc})") from None
    try:
        doc = json.loads(raw)
    except json.JSONDecodeError as exc:
        raise SourceError(f"{path}: invalid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}") from None
    except UnicodeDecodeError as exc:
        raise SourceError(f"{path}: not UTF-8 text (byte {exc.start})") from None
    if not isinstance(doc, dict):
        raise SourceError(f"{path}: top level is a JSON {type(doc).__name__}, expected a CityJSON object")
    return doc


def _check_header(path: Path, doc: dict) -> None:
    if doc.get("type") != "CityJSON":
        raise SourceError(f"{path}: 'type' is {doc.get('type')!r}, expected 'CityJSON'")
    version = str(doc.get("version", ""))
    if ".".join(version.split(".")[:2]) not in SUPPORTED_VERSIONS:
        raise SourceError(f"{path}: CityJSON version {version or '(missing)'!r} is not supported "
                          f"(supported: {', '.join(SUPPORTED_VERSIONS)})")


def _vertices(path: Path, doc: dict) -> np.ndarray:
    """The decoded (n, 3) float64 vertices: ``transform`` applied to integer vertices when present."""
    if "vertices" not in doc:
        raise SourceError(f"{path}: 'vertices' is missing")
    rows = doc["vertices"]
    if not isinstance(rows, list):
        raise SourceError(f"{path}: 'vertices' is not a list")
    v = _numeric_rows(path, "vertices", rows)
    transform = doc.get("transform")
    if transform is not None:
        scale = _triple(path, transform, "scale")
        translate = _triple(path, transform, "translate")
        v = v * scale + translate
    finite = np.isfinite(v).all(axis=1)
    if not finite.all():
        i = int(np.argmin(finite))
        raise SourceError(f"{path}: vertices[{i}] = {rows[i]!r} is not finite")
    return v


def _numeric_rows(path: Path, where: str, rows: list) -> np.ndarray:
    """rows as (n, 3) float64; the first row that is not three numbers is named on failure."""
    if not rows:
        return np.zeros((0, 3))
    try:
        arr = np.array(rows)
    except (ValueError, TypeError):
        arr = None
    if arr is not None and arr.ndim == 2 and arr.shape[1] == 3 and arr.dtype.kind in "iuf":
        return arr.astype(np.float64)
    for i, row in enumerate(rows):
        if not (isinstance(row, list) and len(row) == 3
                and all(isinstance(c, (int, float)) and not isinstance(c, bool) for c in row)):
            raise SourceError(f"{path}: {where}[{i}] = {row!r} is not three numbers")
    raise SourceError(f"{path}: {where} hold numbers out of range")


def _triple(path: Path, transform: dict, key: str) -> np.ndarray:
    value = transform.get(key) if isinstance(transform, dict) else None
    if not (isinstance(value, list) and len(value) == 3
            and all(isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c) for c in value)):
        raise SourceError(f"{path}: transform.{key} = {value!r} is not three finite numbers")
    return np.asarray(value, np.float64)


def _reference_system(doc: dict) -> str | None:
    meta = doc.get("metadata")
    if not isinstance(meta, dict):
        return None
    ref = meta.get("referenceSystem")
    if ref is None and isinstance(meta.get("crs"), dict) and "epsg" in meta["crs"]:  # CityJSON 0.x style
        ref = f"EPSG:{meta['crs']['epsg']}"
    return ref


def _materials(path: Path, doc: dict) -> list:
    """Per material of the file's appearance, its ``diffuseColor`` as RGB8 (None where it has none)."""
    appearance = doc.get("appearance")
    materials = appearance.get("materials") if isinstance(appearance, dict) else None
    if not isinstance(materials, list):
        return []
    out = []
    for i, m in enumerate(materials):
        colour = m.get("diffuseColor") if isinstance(m, dict) else None
        try:
            out.append(None if colour is None else rgb8(colour))
        except (ValueError, TypeError):
            raise SourceError(f"{path}: appearance.materials[{i}].diffuseColor = {colour!r} "
                              "is not three numbers") from None
    return out


def _textures(path: Path, doc: dict) -> list[str]:
    """Per texture of the file's appearance, its image path (read when a surface first uses it)."""
    appearance = doc.get("appearance")
    textures = appearance.get("textures") if isinstance(appearance, dict) else None
    if not isinstance(textures, list):
        return []
    out = []
    for i, t in enumerate(textures):
        image = t.get("image") if isinstance(t, dict) else None
        if not isinstance(image, str) or not image.strip():
            raise SourceError(f"{path}: appearance.textures[{i}].image = {image!r} is not an image path")
        out.append(image)
    return out


def _texture_vertices(path: Path, doc: dict) -> np.ndarray:
    """``appearance["vertices-texture"]`` as (k, 2) float64; the first entry that is not two numbers is named."""
    appearance = doc.get("appearance")
    rows = appearance.get("vertices-texture") if isinstance(appearance, dict) else None
    if rows is None:
        return np.zeros((0, 2))
    if not isinstance(rows, list):
        raise SourceError(f"{path}: appearance.vertices-texture is not a list")
    for i, row in enumerate(rows):
        if not (isinstance(row, list) and len(row) == 2
                and all(isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c) for c in row)):
            raise SourceError(f"{path}: appearance.vertices-texture[{i}] = {row!r} is not two finite numbers")
    return np.asarray(rows, np.float64).reshape(-1, 2)


def _flat_values(values, depth: int) -> list:
    """A semantics or material ``values`` array flattened to one entry per polygon (None where absent)."""
    level = values if isinstance(values, list) else []
    for _ in range(depth - 1):
        level = [x for sub in level if isinstance(sub, list) for x in sub]
    return level


def _lod_key(lod) -> tuple:
    """Numeric sort of LoD values ("1.2" < "1.3" < "2.2"; 2 == "2.0"); unparseable ones last."""
    try:
        return (float(lod), "")
    except (TypeError, ValueError):
        return (math.inf, str(lod))


class _Walk:
    """Collects every surface of every object, then triangulates them all at once."""

    def __init__(self, path: Path, vertices: np.ndarray, templates, materials: list | None = None,
                 textures: list | None = None, texture_vertices: np.ndarray | None = None) -> None:
        self.path = path
        self.materials = materials or []
        self.textures = textures or []  # image path per texture
        self.uv = np.zeros((0, 2)) if texture_vertices is None else texture_vertices  # (k, 2) vertices-texture
        self.images = TextureImages(path)  # their mean colours and pixels
        self.poly_colour: list = []  # RGB8 of each polygon in ``polygons``
        self.poly_texture: list[int] = []  # texture of each polygon in ``polygons``, -1 for none
        self.corner_uv: list = []  # per ring corner of ``polygons``, in order: its vertices-texture index or -1
        self.instance_colour: list = []  # RGB8 of each instance's polygons
        self.vertices = vertices
        self.extra: list[np.ndarray] = []  # placed template vertices, appended after ``vertices``
        self.n_total = vertices.shape[0]
        self.polygons: list = []  # polygons indexing ``vertices``
        self.poly_slot: list[int] = []  # slot of each polygon in ``polygons``
        self.instance_rings: list[tuple[Rings, int]] = []  # (rings with absolute indices, slot)
        self.slots: list[tuple[int, str]] = []  # (object number, lod) per mesh level
        self.slot_of: dict[tuple[int, tuple], int] = {}
        self.geoms: list[tuple[str, int, int]] = []  # (object id, geometry number, polygons) for error reports
        self.objects: list[dict] = []
        self.templates = templates

    def add_object(self, oid: str, obj) -> None:
        if not isinstance(obj, dict):
            raise SourceError(f"{self.path}: CityObject {oid!r} is not a JSON object")
        geometries = obj.get("geometry") or []
        if not isinstance(geometries, list):
            raise SourceError(f"{self.path}: CityObject {oid!r}: 'geometry' is not a list")
        kind = str(obj.get("type", ""))
        parents = obj.get("parents") or []
        info = {"id": oid, "type": kind, "cls": "terrain" if kind == "TINRelief" else kind.lstrip("+").lower(),
                "parent": parents[0] if isinstance(parents, list) and parents else None,
                "attributes": obj.get("attributes"), "notes": []}
        ifc = (info["attributes"] or {}).get("info") if isinstance(info["attributes"], dict) else None
        ifc = ifc if isinstance(ifc, dict) else {}
        info["colour"] = ifc_colour(ifc.get("type"), ifc.get("PredefinedType")) or class_colour(info["cls"])
        number = len(self.objects)
        self.objects.append(info)
        for g, geom in enumerate(geometries):
            self._add_geometry(oid, number, g, geom, info)

    def _add_geometry(self, oid: str, number: int, g: int, geom, info: dict) -> None:
        where = f"CityObject {oid!r} geometry #{g}"
        if not isinstance(geom, dict):
            raise SourceError(f"{self.path}: {where} is not a JSON object")
        gtype = geom.get("type")
        if gtype == "GeometryInstance":
            self._add_instance(oid, number, g, geom, info)
            return
        if gtype in _NO_SURFACES:
            info["notes"].append(f"geometry #{g} ({gtype}) has no surfaces; skipped")
            return
        if gtype not in _DEPTH:
            raise SourceError(f"{self.path}: {where} has unknown type {gtype!r} "
                              f"(known: {', '.join([*_DEPTH, *sorted(_NO_SURFACES), 'GeometryInstance'])})")
        polys, kept = self._surfaces(geom.get("boundaries"), _DEPTH[gtype], where, keep=True)
        slot = self._slot(number, geom.get("lod"))
        colours = self._colours(geom, _DEPTH[gtype], len(kept), info["colour"])
        self.poly_colour.extend(colours[i] for i in kept)
        self._texture_rings(geom, _DEPTH[gtype], kept, polys, where)
        self.polygons.extend(polys)
        self.poly_slot.extend([slot] * len(polys))
        self.geoms.append((oid, g, len(polys)))

    def _colours(self, geom: dict, depth: int, n: int, fallback: tuple) -> list:
        """Each of the geometry's n polygons' colour: texture, else material, else semantic surface, else
        ``fallback``."""
        out = [fallback] * n
        semantics = geom.get("semantics")
        if isinstance(semantics, dict) and isinstance(semantics.get("surfaces"), list):
            kinds = [surface_colour(s.get("type")) if isinstance(s, dict) else None for s in semantics["surfaces"]]
            for i, v in enumerate(_flat_values(semantics.get("values"), depth)[:n]):
                if isinstance(v, int) and 0 <= v < len(kinds) and kinds[v] is not None:
                    out[i] = kinds[v]
        themes = geom.get("material")
        if isinstance(themes, dict) and themes and self.materials:
            theme = next(iter(themes.values()))
            if isinstance(theme, dict):
                values = ([theme["value"]] * n if "value" in theme
                          else _flat_values(theme.get("values"), depth)[:n])
                for i, v in enumerate(values):
                    if isinstance(v, int) and 0 <= v < len(self.materials) and self.materials[v] is not None:
                        out[i] = self.materials[v]
        themes = geom.get("texture")
        if isinstance(themes, dict) and themes and self.textures:
            theme = next(iter(themes.values()))
            values = theme.get("values") if isinstance(theme, dict) else None
            # Per polygon a list of rings, each ring [texture, uv index, ...] or [null]: the outer ring's
            # texture is the polygon's.
            for i, rings in enumerate(_flat_values(values, depth)[:n]):
                v = rings[0][0] if (isinstance(rings, list) and rings and isinstance(rings[0], list)
                                    and rings[0]) else None
                colour = (self.images.colour(self.textures[v])
                          if isinstance(v, int) and 0 <= v < len(self.textures) else None)
                if colour is not None:
                    out[i] = colour
        return out

    def _texture_rings(self, geom: dict, depth: int, kept: list[int], polys: list, where: str) -> None:
        """Record each kept polygon's texture (the first theme's) and its ring corners' UV indices.

        A polygon is textured by its outer ring's texture; a ring given as ``[null]`` has no UVs, and the
        faces touching its corners are drawn in their colour. A textured ring must list one UV index per
        ring vertex, each in range of ``vertices-texture``.
        """
        themes = geom.get("texture")
        theme = next(iter(themes.values())) if isinstance(themes, dict) and themes else None
        values = _flat_values(theme.get("values"), depth) if isinstance(theme, dict) and self.textures else []
        for k, i in enumerate(kept):
            rings = values[i] if i < len(values) and isinstance(values[i], list) else []
            texture = -1
            for r, ring in enumerate(polys[k]):
                tex = rings[r] if r < len(rings) and isinstance(rings[r], list) else None
                if not tex or not isinstance(tex[0], int) or not 0 <= tex[0] < len(self.textures):
                    self.corner_uv.extend([-1] * len(ring))
                    continue
                uv = tex[1:]
                if len(uv) != len(ring) or not all(isinstance(j, int) and not isinstance(j, bool)
                                                   and 0 <= j < len(self.uv) for j in uv):
                    raise SourceError(f"{self.path}: {where}: texture values of polygon {i} ring {r} = {tex!r} "
                                      f"are not a texture and {len(ring)} indices into vertices-texture "
                                      f"(0..{len(self.uv) - 1})")
                self.corner_uv.extend(uv)
                if r == 0:
                    texture = tex[0]
            self.poly_texture.append(texture)

    def _surfaces(self, boundaries, depth: int, where: str, keep: bool = False):
        """The polygons (lists of rings) under ``depth`` list levels of boundaries (with ``keep``: and the
        positions of those polygons among all, empty ones included, as ``values`` arrays count them)."""
        level = boundaries
        try:
            if not isinstance(level, list):
                raise TypeError
            for _ in range(depth - 1):
                level = [x for sub in level for x in sub]
            if not all(isinstance(p, list) and all(isinstance(r, list) for r in p) for p in level):
                raise TypeError
        except TypeError:
            raise SourceError(f"{self.path}: {where}: 'boundaries' are not nested {depth + 2} levels deep "
                              f"as its type requires") from None
        kept = [i for i, p in enumerate(level) if p]  # a polygon without rings has nothing to draw
        polys = [level[i] for i in kept]
        return (polys, kept) if keep else polys

    def _slot(self, number: int, lod) -> int:
        key = (number, _lod_key(lod))
        if key not in self.slot_of:
            self.slot_of[key] = len(self.slots)
            self.slots.append((number, str(lod) if lod is not None else "?"))
        return self.slot_of[key]

    def _add_instance(self, oid: str, number: int, g: int, geom: dict, info: dict) -> None:
        """A GeometryInstance: the template's surfaces, transformed and moved to the reference point."""
        where = f"CityObject {oid!r} geometry #{g} (GeometryInstance)"
        t = self.templates
        if not (isinstance(t, dict) and isinstance(t.get("templates"), list)):
            raise SourceError(f"{self.path}: {where} but the file has no 'geometry-templates'")
        k = geom.get("template")
        if not isinstance(k, int) or not 0 <= k < len(t["templates"]):
            raise SourceError(f"{self.path}: {where}: template {k!r} out of range (0..{len(t['templates']) - 1})")
        template = t["templates"][k]
        ttype = template.get("type") if isinstance(template, dict) else None
        if ttype in _NO_SURFACES:
            info["notes"].append(f"geometry #{g} (instance of a {ttype}) has no surfaces; skipped")
            return
        if ttype not in _DEPTH:
            raise SourceError(f"{self.path}: {where}: template {k} has unknown type {ttype!r}")
        tv = _numeric_rows(self.path, "geometry-templates.vertices-templates", t.get("vertices-templates") or [])
        ref = geom.get("boundaries")
        if not (isinstance(ref, list) and len(ref) == 1 and isinstance(ref[0], int)
                and 0 <= ref[0] < self.vertices.shape[0]):
            raise SourceError(f"{self.path}: {where}: reference point {ref!r} is not one vertex index "
                              f"in 0..{self.vertices.shape[0] - 1}")
        matrix = geom.get("transformationMatrix", np.eye(4).ravel().tolist())
        try:
            m = np.asarray(matrix, np.float64).reshape(4, 4)
        except (ValueError, TypeError):
            raise SourceError(f"{self.path}: {where}: transformationMatrix is not 16 numbers") from None
        try:
            rings = flatten_polygons(self._surfaces(template.get("boundaries"), _DEPTH[ttype],
                                                    f"{where}: template {k}"))
        except ValueError as exc:
            raise SourceError(f"{self.path}: {where}: template {k}: {exc}") from None
        bad = (rings.index < 0) | (rings.index >= tv.shape[0])
        if bad.any():
            raise SourceError(f"{self.path}: {where}: template {k} vertex index {int(rings.index[bad][0])} "
                              f"out of range (0..{tv.shape[0] - 1})")
        placed = tv @ m[:3, :3].T + m[:3, 3] + self.vertices[ref[0]]
        if not np.isfinite(placed).all():
            raise SourceError(f"{self.path}: {where}: placed template vertices are not finite")
        rings.index = rings.index + self.n_total
        self.extra.append(placed)
        self.n_total += placed.shape[0]
        self.instance_rings.append((rings, self._slot(number, template.get("lod"))))
        self.instance_colour.extend([info["colour"]] * rings.n_polygons)
        info["notes"].append(f"geometry #{g} is an instance of template {k}")

    def build(self) -> list[SourceObject]:
        rings = self._flatten()
        vertices = np.concatenate([self.vertices, *self.extra]) if self.extra else self.vertices
        poly_slot = np.asarray(self.poly_slot + [s for r, s in self.instance_rings for _ in range(r.n_polygons)],
                               np.int64)
        poly_colour = np.asarray(self.poly_colour + self.instance_colour, np.uint8).reshape(-1, 3)
        # Triangulated by ring corner, so each face knows its corners' UVs as well as their vertices.
        corners, owner = triangulate_rings(vertices[rings.index],
                                           Rings(np.arange(rings.index.size), rings.length, rings.outer))
        n_instance = rings.index.size - len(self.corner_uv)
        uv_index = np.asarray(self.corner_uv + [-1] * n_instance, np.int64)
        poly_texture = np.asarray(self.poly_texture + [-1] * (poly_slot.size - len(self.poly_texture)), np.int64)
        face_slot = poly_slot[owner]
        order = np.argsort(face_slot, kind="stable")
        corners, owner, face_slot = corners[order], owner[order], face_slot[order]
        faces, face_colour = rings.index[corners], poly_colour[owner]
        corner_uv = np.full((uv_index.size, 2), np.nan)  # (N, 2): NaN where a corner has no UV
        corner_uv[uv_index >= 0] = self.uv[uv_index[uv_index >= 0]]
        bounds = np.searchsorted(face_slot, np.arange(len(self.slots) + 1))
        slots_of: dict[int, list[int]] = {}
        for s, (number, _) in enumerate(self.slots):
            if bounds[s + 1] > bounds[s]:
                slots_of.setdefault(number, []).append(s)
        levels: dict[int, list[tuple[str, Mesh]]] = {}
        for number, slots in slots_of.items():
            span = np.concatenate([np.arange(bounds[s], bounds[s + 1]) for s in slots])
            textured = self._object_texture(poly_texture[owner[span]], corner_uv[corners[span]], owner[span],
                                            face_colour[span])
            at = 0
            for s in slots:
                a, b = bounds[s], bounds[s + 1]
                f, colours = faces[a:b], face_colour[a:b]
                uv = None if textured is None else textured[1][at:at + b - a]
                at += b - a
                if uv is None or (poly_texture[owner[a:b]] < 0).all():
                    used, inverse = np.unique(f, return_inverse=True)
                    mesh = Mesh(vertices[used], inverse.reshape(-1, 3), face_colours=colours)
                else:
                    source, split, vertex_uv = split_by_uv(f, uv)
                    mesh = Mesh(vertices[source], split, face_colours=colours, uv=vertex_uv, texture=textured[0])
                levels.setdefault(number, []).append((self.slots[s][1], mesh))
        out = []
        for number, info in enumerate(self.objects):
            if number not in levels:
                continue
            chain = sorted(levels[number], key=lambda lm: _lod_key(lm[0]))
            attrs = {"id": info["id"], "type": info["type"], "lods": [lod for lod, _ in chain]}
            if info["parent"] is not None:
                attrs["parent"] = info["parent"]
            if info["attributes"]:
                attrs["attributes"] = info["attributes"]
            if info["notes"]:
                attrs["notes"] = info["notes"]
            out.append(SourceObject(info["id"], info["cls"], [m for _, m in chain], attrs))
        return out

    def _object_texture(self, face_texture: np.ndarray, face_uv: np.ndarray, face_polygon: np.ndarray,
                        face_colour: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """One object's atlas and its faces' UVs in it (``atlas.object_texture``), or None if it shows no image.

        face_texture : (m,) int texture of each face, −1 none; face_uv : (m, 3, 2) float; face_polygon : (m,)
        int; face_colour : (m, 3) uint8
        """
        if not (face_texture >= 0).any():
            return None
        used, image_of = np.unique(face_texture, return_inverse=True)
        images = [None if t < 0 else self.images.image(self.textures[t]) for t in used.tolist()]
        face_image = np.where(face_texture >= 0, image_of.reshape(-1), -1)
        return object_texture(face_image, face_uv, face_polygon, face_colour, images)

    def _flatten(self) -> Rings:
        """All polygons as one Rings, every index checked against the vertex count."""
        try:
            rings = flatten_polygons(self.polygons)
        except ValueError:
            rings = None
        n = self.vertices.shape[0]
        if rings is None or (rings.index.size and (rings.index.min() < 0 or rings.index.max() >= n)):
            self._locate_bad_index(n)
        parts = [rings] + [r for r, _ in self.instance_rings]
        return Rings(np.concatenate([p.index for p in parts]), np.concatenate([p.length for p in parts]),
                     np.concatenate([p.outer for p in parts]))

    def _locate_bad_index(self, n: int) -> None:
        """Error path only: find the geometry holding the first bad vertex index and name it."""
        first = 0
        for oid, g, count in self.geoms:
            polys = self.polygons[first:first + count]
            first += count
            try:
                idx = flatten_polygons(polys).index
            except ValueError as exc:
                raise SourceError(f"{self.path}: CityObject {oid!r} geometry #{g}: {exc}") from None
            bad = (idx < 0) | (idx >= n)
            if bad.any():
                raise SourceError(f"{self.path}: CityObject {oid!r} geometry #{g}: vertex index "
                                  f"{int(idx[bad][0])} out of range (the file has {n} vertices)")
        raise SourceError(f"{self.path}: bad vertex index in boundaries")
