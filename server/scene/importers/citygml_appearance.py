"""CityGML appearances (``app:``): which polygons an ``X3DMaterial`` or a ``ParameterizedTexture`` colours.

**Theory of operation.** An ``app:Appearance`` groups surface data under a theme;
it sits inside a city object (``app:appearance``) or at the CityModel level
(``app:appearanceMember``), before or after the objects it targets. Surface data
name their targets by ``gml:id``: an ``X3DMaterial``'s ``app:target`` holds
``#polygonId``, a ``ParameterizedTexture``'s ``app:target`` carries it in its
``uri`` attribute, with ``textureCoordinates`` naming the polygon's rings
(``ring="#ringId"``). The CityGML importer clears each city object after reading
it, so memory stays at one object; the CityModel-level targets are therefore
collected first, in a pass over the file that keeps nothing but appearances
(``file_appearances``), and an object's own targets as it is read
(``Targets.read``).

**One theme.** A file may carry several themes (a photo-textured one, a
thematic one); only the first theme the file names, in document order, is drawn
(an appearance without ``app:theme`` belongs to the unnamed theme) — as the
CityJSON importer draws its geometries' first material theme.

**Texture coordinates.** A ``ParameterizedTexture`` 's ``app:TexCoordList`` gives,
per ring (``ring="#ringId"``), u v pairs in ring order with the closing point
repeated (v = 0 at the image's bottom). A polygon is drawn with its image when every
one of its rings has coordinates from the same texture, one pair per ring point
(``FileAppearances.textures``); else — a count that does not match, a ring left out —
it keeps its colour, warned once per file. The CityGML importer packs an object's
images into one atlas (``server.scene.importers.atlas``).

**What colours a polygon.** Its texture's mean colour
(``server.scene.importers.textures``), else its material's ``diffuseColor``,
else its semantic surface's colour. The spec lets a surface carry both per theme
and side — the material as a constant approximation, the texture as the
measurement — and leaves mixing to the application; X3D's lighting, which
CityGML's materials are adopted from, replaces the diffuse colour by an RGB
texture's colour, so the texture wins here too, and the material stands in
where the image cannot be read. A target is looked up by the polygon's own id,
its rings' ids, then the ids of the geometries around it (a ``MultiSurface`` or
``CompositeSurface`` may be targeted whole), nearest first; an object's own
appearances before the CityModel's. Only front-side surface data
(``isFront``, true by default) is read: one colour per face is drawn, and the
back side of a building's surface faces its inside. A material without a
``diffuseColor`` leaves its polygons' colour alone, as in the CityJSON importer.
A target naming no polygon the file has is ignored: files often carry
appearances for geometry left out of them. ``GeoreferencedTexture`` s (aerial
images mapped by position) are not read.
"""

from __future__ import annotations

import logging
import mmap
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from server.scene.palette import rgb8
from server.scene.source import SourceError

from .textures import TextureImages

__all__ = ["FileAppearances", "Targets", "file_appearances"]

log = logging.getLogger(__name__)

_GML_ID = "{http://www.opengis.net/gml}id"

RGB = tuple[int, int, int]


def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1]


def _text(e: ET.Element, name: str) -> str | None:
    c = next((c for c in e if _local(c.tag) == name), None)
    return c.text.strip() if c is not None and c.text and c.text.strip() else None


def _theme(appearance: ET.Element) -> str | None:
    return _text(appearance, "theme")


def _id(ref: str | None) -> str:
    """``#poly1`` → ``poly1`` (a target is a local reference)."""
    return (ref or "").strip().lstrip("#")


@dataclass
class Targets:
    """The surface data of one theme that target polygons: gml:id → RGB8 material, gml:id → image reference,
    ring gml:id → (image reference, (k, 2) float64 texture coordinates in ring order)."""

    materials: dict[str, RGB] = field(default_factory=dict)
    textures: dict[str, str] = field(default_factory=dict)
    coords: dict[str, tuple[str, np.ndarray]] = field(default_factory=dict)

    def __bool__(self) -> bool:
        return bool(self.materials or self.textures)

    def read(self, appearance: ET.Element, theme: str | None, path: Path, where: str) -> None:
        """Add the targets of one ``app:Appearance`` if it belongs to ``theme``; ``SourceError`` for a
        malformed material or texture (``where`` names the object or "CityModel")."""
        if _theme(appearance) != theme:
            return
        for member in appearance:
            if _local(member.tag) != "surfaceDataMember":
                continue
            for data in member:
                kind = _local(data.tag)
                if kind not in ("X3DMaterial", "ParameterizedTexture") or not _front(data, path, where):
                    continue
                name = f"{where}, {kind} {data.get(_GML_ID) or '(no gml:id)'}"
                if kind == "X3DMaterial":
                    colour = _diffuse(data, path, name)
                    if colour is not None:
                        for t in data:
                            if _local(t.tag) == "target" and _id(t.text):
                                self.materials[_id(t.text)] = colour
                else:
                    image = _text(data, "imageURI")
                    if image is None:
                        raise SourceError(f"{path}: {name}: no imageURI")
                    for t in data:
                        if _local(t.tag) != "target":
                            continue
                        if _id(t.get("uri")):
                            self.textures[_id(t.get("uri"))] = image
                        for coords in t.iter():
                            if _local(coords.tag) == "textureCoordinates" and _id(coords.get("ring")):
                                ring = _id(coords.get("ring"))
                                self.textures[ring] = image
                                self.coords[ring] = (image, _pairs(coords.text, path, f"{name}, ring {ring}"))


def _pairs(text: str | None, path: Path, where: str) -> np.ndarray:
    """``textureCoordinates`` text as (k, 2) float64 u v pairs; ``SourceError`` naming ``where`` if it is not."""
    try:
        v = np.array((text or "").split(), np.float64)
    except ValueError:
        v = None
    if v is None or v.size % 2 or not np.isfinite(v).all():
        raise SourceError(f"{path}: {where}: textureCoordinates {(text or '').strip()[:60]!r} "
                          "are not u v pairs of finite numbers")
    return v.reshape(-1, 2)


def _front(data: ET.Element, path: Path, where: str) -> bool:
    value = _text(data, "isFront")
    if value is None or value in ("true", "1"):
        return True
    if value in ("false", "0"):
        return False
    raise SourceError(f"{path}: {where}: isFront {value!r} is not a boolean")


def _diffuse(material: ET.Element, path: Path, where: str) -> RGB | None:
    """A material's ``diffuseColor`` as RGB8 (None where it has none); it must be three numbers in [0, 1]."""
    text = _text(material, "diffuseColor")
    if text is None:
        return None
    try:
        v = np.array(text.split(), np.float64)
    except ValueError:
        v = None
    if v is None or v.shape != (3,) or not (np.isfinite(v).all() and (v >= 0).all() and (v <= 1).all()):
        raise SourceError(f"{path}: {where}: diffuseColor {text!r} is not three numbers in [0, 1]")
    return rgb8(v.tolist())


@dataclass
class FileAppearances:
    """What a file's appearances mean for the buildings read after this: the theme drawn, the
    CityModel-level targets of that theme, and the images' colours (read on first use)."""

    theme: str | None
    targets: Targets
    images: TextureImages
    any: bool  # whether the file has appearances at all; False: nothing below needs a look
    _warned: bool = False  # a polygon's coordinates did not fit its rings (warned once per file)

    def colours(self, ids: Sequence[Sequence[str]], semantic: list, local: Targets) -> list:
        """Each polygon's colour: texture, else material, else its ``semantic`` one (RGB8 or None).

        ids      : per polygon, the gml:ids a target may name — its own, its rings', then its enclosing
                   geometries', nearest first
        semantic : per polygon, its semantic surface's colour or None
        local    : the object's own targets, looked up before the CityModel's
        """
        if not (local or self.targets):
            return semantic
        out = list(semantic)
        layers = [t for t in (local, self.targets) if t]
        for i, names in enumerate(ids):
            image = next((t.textures[n] for n in names for t in layers if n in t.textures), None)
            colour = self.images.colour(image) if image is not None else None
            if colour is None:
                colour = next((t.materials[n] for n in names for t in layers if n in t.materials), None)
            if colour is not None:
                out[i] = colour
        return out

    def textures(self, ids: Sequence[Sequence[str]], ring_ids: Sequence[Sequence[str | None]],
                 ring_sizes: Sequence[Sequence[int]], local: Targets) -> list:
        """Each polygon's (image reference, (k, 2) float64 UVs of its ring points, rings concatenated), or None.

        ids        : as ``colours``
        ring_ids   : per polygon, the gml:id of each ring (None where it has none)
        ring_sizes : per polygon, each ring's point count, its closing point not repeated
        A polygon is textured when its image is readable and each ring has coordinates of that image, one
        pair per point (the closing pair, repeated in the file, dropped); else None (module docstring).
        """
        out: list = [None] * len(ids)
        layers = [t for t in (local, self.targets) if t.coords]
        if not layers:
            return out
        for i, names in enumerate(ids):
            image = next((t.textures[n] for n in names for t in (local, self.targets) if n in t.textures), None)
            if image is None:
                continue
            parts = []
            for ring, k in zip(ring_ids[i], ring_sizes[i]):
                found = next((t.coords[ring] for t in layers if ring in t.coords), None) if ring else None
                uv = found[1] if found is not None and found[0] == image else None
                if uv is not None and len(uv) == k + 1:
                    uv = uv[:k]
                if uv is None or len(uv) != k:
                    if not self._warned:
                        self._warned = True
                        log.warning("%s: polygon %s: ring %s has %s texture coordinates for its %d points; "
                                    "such polygons keep their colour", self.images.source, names[0] if names else "?",
                                    ring, "no" if uv is None else len(uv), k)
                    break
                parts.append(uv)
            else:
                if self.images.image(image) is not None:
                    out[i] = (image, np.concatenate(parts))
        return out

    def of_object(self, obj: ET.Element, path: Path, where: str) -> Targets:
        """The targets of the appearances inside one city object (its parts' included)."""
        local = Targets()
        if self.any:
            for e in obj.iter():
                if _local(e.tag) == "Appearance":
                    local.read(e, self.theme, path, where)
        return local


def _mentions_appearances(path: Path) -> bool:
    """Whether the bytes ``Appearance`` occur in the file at all: a plain scan, so a file without
    appearances costs no second parse."""
    with open(path, "rb") as f:
        try:
            with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as m:
                return m.find(b"Appearance") >= 0
        except ValueError:  # an empty file cannot be mapped
            return False


def file_appearances(path: Path) -> FileAppearances:
    """The first pass: the first theme the file names and the CityModel-level targets of that theme.

    Every top-level member is cleared when it ends, so memory holds one object at a time and the
    CityModel-level appearances. Malformed XML is left to the main pass to report with its position.
    """
    images = TextureImages(path)
    if not _mentions_appearances(path):
        return FileAppearances(None, Targets(), images, any=False)
    theme, seen, targets = None, False, Targets()
    depth = 0
    try:
        for event, e in ET.iterparse(path, events=("start", "end")):
            if event == "start":
                depth += 1
                continue
            depth -= 1
            name = _local(e.tag)
            if name == "Appearance" and not seen:
                theme, seen = _theme(e), True
            if depth == 1:  # a child of the CityModel: read it if it holds appearances, then drop it
                if name == "appearanceMember":
                    for a in e.iter():
                        if _local(a.tag) == "Appearance":
                            targets.read(a, theme, path, "CityModel appearance")
                e.clear()
    except ET.ParseError:
        pass
    return FileAppearances(theme, targets, images, any=seen)
