"""The semantic palette: the colours a scene is drawn in where its data names what a surface is, not its colour.

City models carry semantics more often than appearances: CityJSON and CityGML
say which surface is a ``RoofSurface``, a ``WallSurface`` or a ``GroundSurface``
(and, in LoD3, which is a ``Window`` or a ``Door``), and an IFC model converted
to CityJSON says which object is a wall, a slab or a window. Viewers of city
models draw them in one convention — dark red roofs, light walls, grey ground —
and so does walkstream, from this table and nowhere else.

Which colour a surface gets, first match wins (``server.scene.importers``):

1. the data's own appearance — a CityJSON material's ``diffuseColor`` (its first
   theme), a glTF material's base colour factor (its texture's mean colour when it
   has one), OBJ/PLY vertex or face colours;
2. the surface's semantic type (``SURFACES``);
3. the object's IFC class (``IFC``, from the ``info.type`` attribute of CityJSON
   converted from IFC);
4. the object's class (``CLASSES``: a building without surface semantics is
   drawn in the wall colour, terrain in ``TERRAIN``);
5. ``DEFAULT``, a neutral clay.

Objects of generated scenes carry no colours: the client draws them in
per-object tints, as it draws any colourless payload.

Colours are sRGB, 8 bits a channel (``proto.geometry``'s ``cb``).
"""

from __future__ import annotations

from typing import Iterable

import numpy as np

__all__ = ["RGB", "SURFACES", "IFC", "CLASSES", "TERRAIN", "GROUND", "DEFAULT", "surface_colour", "class_colour",
           "ifc_colour", "rgb8"]

RGB = tuple[int, int, int]

ROOF: RGB = (160, 58, 48)
WALL: RGB = (232, 226, 214)
#: TIN reliefs, DEM terrain and IFC sites.
TERRAIN: RGB = (138, 152, 102)
#: The ground the builder lays under a city that has no terrain (``server.scene.ground``).
GROUND: RGB = (150, 152, 128)
#: Anything the data says nothing about.
DEFAULT: RGB = (204, 198, 188)

#: CityJSON / CityGML semantic surface types (CityGML 2.0 building, bridge, tunnel, water and
#: transportation modules; CityJSON uses the same names).
SURFACES: dict[str, RGB] = {
    "RoofSurface": ROOF,
    "WallSurface": WALL,
    "GroundSurface": (120, 114, 106),
    "ClosureSurface": (198, 200, 206),
    "OuterCeilingSurface": (214, 208, 198),
    "OuterFloorSurface": (158, 150, 138),
    "FloorSurface": (176, 156, 124),
    "InteriorWallSurface": (238, 234, 226),
    "CeilingSurface": (242, 240, 234),
    "Window": (92, 132, 168),
    "Door": (122, 84, 58),
    "WaterSurface": (84, 132, 180),
    "WaterGroundSurface": (96, 110, 120),
    "WaterClosureSurface": (120, 160, 196),
    "TrafficArea": (116, 116, 118),
    "AuxiliaryTrafficArea": (154, 152, 140),
}

#: IFC classes (``info.type`` of CityJSON converted from IFC); a slab whose PredefinedType is ROOF is a roof.
IFC: dict[str, RGB] = {
    "IfcWall": WALL,
    "IfcWallStandardCase": WALL,
    "IfcCurtainWall": (150, 176, 196),
    "IfcRoof": ROOF,
    "IfcSlab": SURFACES["FloorSurface"],
    "IfcWindow": SURFACES["Window"],
    "IfcOpeningElement": SURFACES["Window"],
    "IfcDoor": SURFACES["Door"],
    "IfcMember": (150, 110, 72),
    "IfcBeam": (150, 110, 72),
    "IfcColumn": (190, 186, 178),
    "IfcStair": (170, 164, 156),
    "IfcStairFlight": (170, 164, 156),
    "IfcRailing": (120, 120, 126),
    "IfcSpace": (236, 232, 222),
    "IfcCovering": (214, 208, 198),
    "IfcFurnishingElement": (160, 120, 84),
    "IfcSite": TERRAIN,
}

#: Object classes (``SourceObject.cls``, lower case) drawn in one colour when their surfaces have none.
CLASSES: dict[str, RGB] = {
    "building": WALL,
    "buildingpart": WALL,
    "buildinginstallation": WALL,
    "terrain": TERRAIN,
    "tinrelief": TERRAIN,
    "ground": GROUND,
    "waterbody": SURFACES["WaterSurface"],
    "road": SURFACES["TrafficArea"],
    "railway": SURFACES["TrafficArea"],
    "transportsquare": SURFACES["AuxiliaryTrafficArea"],
    "plantcover": (96, 140, 72),
    "solitaryvegetationobject": (86, 130, 64),
    "tree": (86, 130, 64),
    "landuse": (150, 164, 112),
    "bridge": (182, 178, 170),
    "bridgepart": (182, 178, 170),
    "tunnel": (150, 146, 140),
    "cityfurniture": (120, 120, 126),
}


def surface_colour(kind: str | None) -> RGB | None:
    """The palette colour of a semantic surface type (``"RoofSurface"``…), or None if the palette lacks it."""
    if not kind:
        return None
    return SURFACES.get(str(kind).lstrip("+"))


def ifc_colour(ifc_type: str | None, predefined: str | None = None) -> RGB | None:
    """The colour of an IFC class (a ``ROOF`` slab is a roof), or None if the palette lacks it."""
    if not ifc_type:
        return None
    if ifc_type == "IfcSlab" and str(predefined or "").upper() == "ROOF":
        return ROOF
    return IFC.get(ifc_type)


def class_colour(cls: str) -> RGB:
    """The colour of an object class (``CLASSES``), ``DEFAULT`` for classes the palette does not know."""
    return CLASSES.get(cls.lower(), DEFAULT)


def rgb8(colour: Iterable[float]) -> RGB:
    """A colour of three floats in [0, 1] (CityJSON ``diffuseColor``, glTF ``baseColorFactor``) as RGB8.

    Raises ValueError when it is not three finite numbers.
    """
    c = np.asarray(list(colour)[:3], np.float64)
    if c.shape != (3,) or not np.isfinite(c).all():
        raise ValueError(f"a colour needs three finite numbers, got {colour!r}")
    r, g, b = (int(v) for v in np.rint(np.clip(c, 0.0, 1.0) * 255.0))
    return (r, g, b)
