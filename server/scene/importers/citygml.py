"""CityGML 2.0 (and 1.0): solitary trees as instanced prototypes, LoD2 buildings as meshes.

**Trees.** A ``SolitaryVegetationObject`` with an ``ImplicitGeometry`` names a
prototype (``relativeGMLGeometry``: defined inline once with a ``gml:id``,
referenced by ``xlink:href="#id"`` afterwards, possibly before its
definition), a 4×4 ``transformationMatrix`` (row-major) and a
``referencePoint``. The CityGML 2.0 spec (§10.3.6) puts a prototype vertex v
at ``referencePoint + M·v`` in world coordinates, so an instance's
model → world matrix is ``translate(referencePoint) @ M``. Prototypes become
``TreeModel`` s (one mesh each, so a renderer can instance them), trees become
one ``TreeInstances``; their height and crown diameter go to the model's
``attributes["instances"]`` lists, in instance order, since TreeInstances has
no per-instance attribute table. A tree's generic attribute ``tree_model``
(``gen:stringAttribute`` or ``gen:uriAttribute``) names a point-cloud file to
draw it with instead (``TreeInstances.model_file``; ``server.scene.scans``).

**Buildings.** Each ``Building`` and ``BuildingPart`` with polygons of its own
becomes a ``SourceObject`` ("building" / "buildingpart"); a part records its
building's id. Polygons are read once, where they are defined (solids that
``xlink`` them again are not followed), and ``ClosureSurface`` s are left
out: they are virtual faces closing a volume, not something one sees. Each
polygon takes the colour of the semantic surface it bounds (``RoofSurface``,
``WallSurface``, ``GroundSurface``, ``Window``, ``Door``…, ``server.scene.palette``),
its object's class colour where it bounds none — unless an appearance of the
file's first theme targets it: then its texture's mean colour or its
``X3DMaterial`` 's ``diffuseColor`` (``server.scene.importers.citygml_appearance``
says which wins, and why). A polygon whose ``ParameterizedTexture`` gives texture
coordinates for its rings is also drawn with its image: each object's images go into
one atlas (``server.scene.importers.atlas``), its vertices split where UVs differ.

The file is read with ``iterparse`` and each top-level city object is
cleared when done, so memory stays at one object; a file with appearances
is read twice, first for its CityModel-level ones, which may follow the
objects they target. Elements are matched by
local name, so CityGML 1.0 and 2.0 namespaces both work.

Polygons (with holes) are triangulated by
``server.scene.importers.polygons.triangulate_polygons`` when that module
exists, else by a fan over the exterior ring (holes dropped), which is exact
for convex faces.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from server.scene.palette import class_colour, surface_colour
from server.scene.scans import TREE_MODEL_ATTRIBUTE
from server.scene.source import Mesh, SourceError, SourceObject, SourceScene, TreeInstances, TreeModel

from .atlas import object_texture, split_by_uv
from .citygml_appearance import file_appearances
from .textures import TextureImages

__all__ = ["load_citygml"]

_GML_ID = "{http://www.opengis.net/gml}id"
_XLINK = "{http://www.w3.org/1999/xlink}href"


def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1]


def _numbers(text: str | None, path, where: str) -> np.ndarray:
    try:
        v = np.array((text or "").split(), np.float64)
    except ValueError:
        raise SourceError(f"{path}: {where}: non-numeric coordinates") from None
    if not np.isfinite(v).all():
        raise SourceError(f"{path}: {where}: NaN or infinite coordinate")
    return v


def _ring(ring: ET.Element, path, where: str) -> np.ndarray:
    """A LinearRing's points (k, 3), closing point dropped; posList or gml:pos children."""
    pl = next((e for e in ring if _local(e.tag) == "posList"), None)
    if pl is not None:
        dim = int(pl.get("srsDimension", "3"))
        v = _numbers(pl.text, path, where)
    else:
        dim = 3
        v = np.concatenate([_numbers(e.text, path, where) for e in ring if _local(e.tag) == "pos"] or [np.zeros(0)])
    if v.size % dim or dim not in (2, 3):
        raise SourceError(f"{path}: {where}: {v.size} coordinates do not make {dim}-D points")
    pts = v.reshape(-1, dim)
    if dim == 2:
        pts = np.column_stack([pts, np.zeros(len(pts))])
    if len(pts) > 1 and np.array_equal(pts[0], pts[-1]):
        pts = pts[:-1]
    if len(pts) < 3:
        raise SourceError(f"{path}: {where}: a ring needs 3 distinct points, has {len(pts)}")
    return pts


def _triangulator():
    try:  # another engineer's module: ear clipping with holes, vectorised over many polygons
        from server.scene.importers.polygons import triangulate_polygons
        return triangulate_polygons
    except ImportError:
        return None


def _fan(polys: list[list[np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Fan triangles over each exterior ring (holes dropped), indices into the concatenated rings,
    and the polygon of each triangle."""
    faces, owner, n = [], [], 0
    for i, rings in enumerate(polys):
        k = len(rings[0])
        faces.append(np.column_stack([np.full(k - 2, n), np.arange(n + 1, n + k - 1), np.arange(n + 2, n + k)]))
        owner.append(np.full(k - 2, i))
        n += sum(len(r) for r in rings)
    return np.concatenate(faces).astype(np.int64), np.concatenate(owner).astype(np.int64)


def _mesh(polys: list[list[np.ndarray]], tri, colours: list | None = None, cls: str = "",
          textures: list | None = None, images: TextureImages | None = None) -> Mesh:
    """One mesh from polygons (each a list of rings); exactly equal vertices are welded.

    colours  : per polygon, its RGB8 or None (then ``cls``'s colour); None: a mesh without colours
    textures : per polygon, (image reference, (k, 2) UVs of its ring points) or None
               (``FileAppearances.textures``), read from ``images``; with colours only
    """
    if not polys:
        return Mesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    pts = np.concatenate([r for rings in polys for r in rings])
    if tri is not None:
        from server.scene.importers.polygons import flatten_polygons, triangulate_rings

        index, n = [], 0
        for rings in polys:
            index.append([list(range(n + sum(len(q) for q in rings[:k]), n + sum(len(q) for q in rings[:k + 1])))
                          for k in range(len(rings))])
            n += sum(len(r) for r in rings)
        faces, owner = triangulate_rings(pts, flatten_polygons(index))
        faces = np.asarray(faces, np.int64).reshape(-1, 3)
    else:
        faces, owner = _fan(polys)
    pos, inv = np.unique(pts, axis=0, return_inverse=True)
    f = inv.reshape(-1)[faces]
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    if colours is None:
        return Mesh(pos, f[keep])
    fallback = class_colour(cls)
    poly_colour = np.array([fallback if c is None else c for c in colours], np.uint8).reshape(-1, 3)
    face_colours = poly_colour[owner[keep]]
    if textures is None or images is None or not any(t is not None for t in textures):
        return Mesh(pos, f[keep], face_colours=face_colours)
    uris = sorted({t[0] for t in textures if t is not None})
    corner_uv = np.full((pts.shape[0], 2), np.nan)  # (N, 2) per ring point, NaN where untextured
    poly_image = np.full(len(polys), -1, np.int64)
    n = 0
    for i, (rings, t) in enumerate(zip(polys, textures)):
        k = sum(len(r) for r in rings)
        if t is not None:
            corner_uv[n:n + k] = t[1]
            poly_image[i] = uris.index(t[0])
        n += k
    kept = faces[keep]
    made = object_texture(poly_image[owner[keep]], corner_uv[kept], owner[keep], face_colours,
                          [images.image(u) for u in uris])
    if made is None:
        return Mesh(pos, f[keep], face_colours=face_colours)
    source, split, uv = split_by_uv(f[keep], made[1])
    return Mesh(pos[source], split, face_colours=face_colours, uv=uv, texture=made[0])


def _polygons(elem: ET.Element, path, owner: str, stop=(), colours: list | None = None,
              ids: list | None = None, ring_ids: list | None = None) -> list[list[np.ndarray]]:
    """Every gml:Polygon below ``elem`` as rings, not descending into ``stop`` elements or ClosureSurfaces.

    colours : when given, receives each polygon's semantic surface colour (None where it bounds none)
    ids     : when given, receives each polygon's gml:ids an appearance may target: its own, its rings',
              then those of the elements around it below ``elem``, nearest first
    ring_ids : when given, receives each polygon's rings' gml:ids (None where a ring has none)
    """
    out = []

    def walk(e, colour, around):
        for c in e:
            name = _local(c.tag)
            if name in stop or name == "ClosureSurface":
                continue
            if name == "Polygon":
                where = f"{owner}, polygon {c.get(_GML_ID) or len(out) + 1}"
                boundary = [r for b in c if _local(b.tag) in ("exterior", "interior")
                            for r in b if _local(r.tag) == "LinearRing"]
                rings = [_ring(r, path, where) for r in boundary]
                if rings:
                    out.append(rings)
                    if colours is not None:
                        colours.append(colour)
                    if ids is not None:
                        own = [x for x in (c.get(_GML_ID), *(r.get(_GML_ID) for r in boundary)) if x]
                        ids.append(own + around)
                    if ring_ids is not None:
                        ring_ids.append([r.get(_GML_ID) for r in boundary])
            else:
                gid = c.get(_GML_ID)
                walk(c, surface_colour(name) or colour, [gid, *around] if ids is not None and gid else around)

    walk(elem, None, [])
    return out


def _child(e: ET.Element, name: str):
    return next((c for c in e if _local(c.tag) == name), None)


def _float_or_none(e):
    try:
        return float(e.text) if e is not None else None
    except (TypeError, ValueError):
        return None


def _generic(e: ET.Element, name: str) -> str | None:
    """The value of the generic (``gen:``) string or URI attribute ``name`` of a city object, if any."""
    for c in e:
        if _local(c.tag) in ("stringAttribute", "uriAttribute") and c.get("name") == name:
            value = _child(c, "value")
            return value.text.strip() if value is not None and value.text and value.text.strip() else None
    return None


def load_citygml(path) -> SourceScene:
    """Trees (instanced prototypes) and LoD2 buildings from a CityGML file; see the module docstring."""
    path = Path(path)
    if path.stat().st_size == 0:
        raise SourceError(f"{path}: empty file")
    tri = _triangulator()
    appearances = file_appearances(path)
    protos: dict[str, list] = {}  # gml:id → polygons
    proto_order: list[str] = []
    trees = []  # (name, href, matrix, height, crown, tree_model file)
    objects: list[SourceObject] = []
    crs = None
    depth = 0
    try:
        for event, e in ET.iterparse(path, events=("start", "end")):
            name = _local(e.tag)
            if event == "start":
                depth += 1
                if crs is None and e.get("srsName"):
                    crs = e.get("srsName")
                continue
            depth -= 1
            if name == "SolitaryVegetationObject":
                _tree(e, path, len(trees), protos, proto_order, trees, objects, tri)
                e.clear()
            elif name == "Building":
                bid = e.get(_GML_ID) or f"building{len(objects) + 1}"
                local = appearances.of_object(e, path, f"building {bid}")
                own = _building_mesh(e, path, f"building {bid}", ("BuildingPart",), appearances, local, tri)
                if own is not None:
                    objects.append(SourceObject(bid, "building", [own], {"id": bid}))
                for part in e.iter():
                    if _local(part.tag) == "BuildingPart":
                        pid = part.get(_GML_ID) or f"{bid}-part{len(objects) + 1}"
                        mesh = _building_mesh(part, path, f"building part {pid}", (), appearances, local, tri)
                        if mesh is not None:
                            objects.append(SourceObject(pid, "buildingpart", [mesh], {"id": pid, "building": bid}))
                e.clear()
            elif name == "cityObjectMember":
                e.clear()
    except ET.ParseError as err:
        line, col = err.position
        raise SourceError(f"{path}: line {line}, column {col}: not well-formed XML ({err})") from None
    if depth:
        raise SourceError(f"{path}: truncated XML")

    models, instances = [], None
    if trees:
        index = {}
        for pid in proto_order:
            index[pid] = len(models)
            models.append(TreeModel(pid, _mesh(protos[pid], tri), {"id": pid, "instances": {"height": [], "crown_diameter": []}}))
        idx = np.empty(len(trees), np.int32)
        mats = np.empty((len(trees), 4, 4))
        for i, (tname, href, m, height, crown, _) in enumerate(trees):
            if href not in index:
                raise SourceError(f"{path}: tree {i + 1} ({tname}) references unknown prototype '#{href}'")
            idx[i] = index[href]
            mats[i] = m
            inst = models[index[href]].attributes["instances"]
            inst["height"].append(height)
            inst["crown_diameter"].append(crown)
        instances = TreeInstances(idx, mats, [t[0] for t in trees], [t[5] for t in trees])
    if crs and "EPSG" in crs.upper():
        crs = "EPSG:" + crs.replace("::", ":").rsplit(":", 1)[-1]
    return SourceScene(objects=objects, tree_models=models, trees=instances, crs=crs, sources=[str(path)])


def _building_mesh(e: ET.Element, path, where: str, stop: tuple, appearances, local, tri) -> Mesh | None:
    """A building's (or part's) own polygons as one coloured mesh, textured where its appearances say; None
    if it has none."""
    colours: list = []
    ids: list | None = [] if appearances.any else None
    ring_ids: list | None = [] if appearances.any else None
    polys = _polygons(e, path, where, stop=stop, colours=colours, ids=ids, ring_ids=ring_ids)
    if not polys:
        return None
    textures = None
    if ids is not None:
        colours = appearances.colours(ids, colours, local)
        textures = appearances.textures(ids, ring_ids, [[len(r) for r in rings] for rings in polys], local)
    return _mesh(polys, tri, colours, "building", textures, appearances.images)


def _tree(e, path, i, protos, proto_order, trees, objects, tri) -> None:
    tname = e.get(_GML_ID) or f"tree{i + 1}"
    height = _float_or_none(_child(e, "height"))
    crown = _float_or_none(_child(e, "crownDiameter"))
    scan = _generic(e, TREE_MODEL_ATTRIBUTE)  # a point-cloud file for this tree (server.scene.scans)
    implicit = next((c for c in e.iter() if _local(c.tag) == "ImplicitGeometry"), None)
    if implicit is None:  # explicit geometry: an ordinary object
        polys = _polygons(e, path, f"tree {i + 1} ({tname})")
        if polys:
            objects.append(SourceObject(tname, "tree", [_mesh(polys, tri)], {"height": height, "crownDiameter": crown,
                                                                               TREE_MODEL_ATTRIBUTE: scan}))
        return
    where = f"tree {i + 1} ({tname})"
    tm = _child(implicit, "transformationMatrix")
    m = np.eye(4) if tm is None else _numbers(tm.text, path, where + ", transformationMatrix")
    if m.size != 16:
        raise SourceError(f"{path}: {where}: transformationMatrix has {m.size} numbers, needs 16")
    m = m.reshape(4, 4)
    ref = np.zeros(3)
    rp = _child(implicit, "referencePoint")
    if rp is not None:
        pos = next((c for c in rp.iter() if _local(c.tag) in ("pos", "coordinates")), None)
        ref = _numbers(pos.text if pos is not None else None, path, where + ", referencePoint")
        if ref.size != 3:
            raise SourceError(f"{path}: {where}: referencePoint has {ref.size} coordinates, needs 3")
    rel = _child(implicit, "relativeGMLGeometry")
    if rel is None:
        raise SourceError(f"{path}: {where}: ImplicitGeometry without relativeGMLGeometry")
    href = (rel.get(_XLINK) or "").lstrip("#")
    if not href:
        geom = next(iter(rel), None)
        if geom is None:
            raise SourceError(f"{path}: {where}: empty relativeGMLGeometry")
        href = geom.get(_GML_ID) or f"prototype-of-{tname}"
        if href in protos:
            raise SourceError(f"{path}: {where}: prototype id {href!r} defined twice")
        polys = _polygons(rel, path, f"prototype {href}")
        if not polys:
            raise SourceError(f"{path}: {where}: prototype {href!r} has no polygons")
        protos[href] = polys
        proto_order.append(href)
    t = np.eye(4)
    t[:3, 3] = ref
    trees.append((tname, href, t @ m, height, crown, scan))
