"""Appearances that target polygons: CityGML X3DMaterials and ParameterizedTextures, CityJSON textures.

A hand-written CityGML 2.0 box building (roof, four walls, ground, each polygon with a gml:id) and a
CityJSON twin, with small PNGs written here; checked on the importer's meshes and on the full level
a built store streams.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from proto.geometry import decode_geometry
from server.scene import palette
from server.scene.catalog import build_path
from server.scene.importers import load_source
from server.scene.importers.textures import mean_colour
from server.scene.source import SourceError
from server.scene.store import SceneStore

ROOF, WALL, GROUND = palette.ROOF, palette.WALL, palette.SURFACES["GroundSurface"]
BLUE, GREEN = (0, 0, 255), (51, 204, 51)
# tex/east.png: two columns (200, 100, 50), one (100, 50, 250), one transparent: the mean of what shows.
EAST_MEAN = (167, 83, 117)
# tex/north.png: plain (10, 20, 30).
NORTH = (10, 20, 30)

# The box's polygons by the outward direction of their normals (x, y, z), and their gml:ids.
SIDES = {"roof": (0, 0, 1), "ground": (0, 0, -1), "south": (0, -1, 0), "east": (1, 0, 0), "north": (0, 1, 0),
         "west": (-1, 0, 0)}
_BOX = {  # corners counter-clockwise seen from outside
    "roof": [(0, 0, 6), (10, 0, 6), (10, 8, 6), (0, 8, 6)],
    "ground": [(0, 0, 0), (0, 8, 0), (10, 8, 0), (10, 0, 0)],
    "south": [(0, 0, 0), (10, 0, 0), (10, 0, 6), (0, 0, 6)],
    "east": [(10, 0, 0), (10, 8, 0), (10, 8, 6), (10, 0, 6)],
    "north": [(10, 8, 0), (0, 8, 0), (0, 8, 6), (10, 8, 6)],
    "west": [(0, 8, 0), (0, 0, 0), (0, 0, 6), (0, 8, 6)],
}
_SURFACE = {"roof": "RoofSurface", "ground": "GroundSurface"}
ORIGIN = np.array([390000.0, 5810000.0, 30.0])  # map coordinates, as real files have them


def _write_images(folder: Path) -> None:
    (folder / "tex").mkdir(exist_ok=True)
    east = np.zeros((4, 4, 4), np.uint8)
    east[:, :2] = (200, 100, 50, 255)
    east[:, 2] = (100, 50, 250, 255)
    east[:, 3] = (0, 0, 0, 0)
    Image.fromarray(east, "RGBA").save(folder / "tex" / "east.png")
    Image.new("RGB", (8, 8), NORTH).save(folder / "tex" / "north.png")


def _polygon(side: str) -> str:
    pts = " ".join(f"{x + ORIGIN[0]} {y + ORIGIN[1]} {z + ORIGIN[2]}"
                   for x, y, z in [*_BOX[side], _BOX[side][0]])
    return (f'<gml:surfaceMember><gml:Polygon gml:id="{side}"><gml:exterior><gml:LinearRing gml:id="{side}-ring">'
            f'<gml:posList srsDimension="3">{pts}</gml:posList></gml:LinearRing></gml:exterior></gml:Polygon>'
            f'</gml:surfaceMember>')


def _material(colour: str, *targets: str, front: str | None = None) -> str:
    side = f"<app:isFront>{front}</app:isFront>" if front is not None else ""
    return (f"<app:surfaceDataMember><app:X3DMaterial>{side}<app:diffuseColor>{colour}</app:diffuseColor>"
            + "".join(f"<app:target>#{t}</app:target>" for t in targets) + "</app:X3DMaterial></app:surfaceDataMember>")


def _texture(image: str, *targets: str) -> str:
    return (f"<app:surfaceDataMember><app:ParameterizedTexture><app:imageURI>{image}</app:imageURI>"
            + "".join(f'<app:target uri="#{t}"><app:TexCoordList><app:textureCoordinates ring="#{t}-ring">'
                      f"0 0 1 0 1 1 0 1 0 0</app:textureCoordinates></app:TexCoordList></app:target>" for t in targets)
            + "</app:ParameterizedTexture></app:surfaceDataMember>")


def _appearance(theme: str | None, *data: str) -> str:
    named = f"<app:theme>{theme}</app:theme>" if theme is not None else ""
    return f"<app:Appearance>{named}{''.join(data)}</app:Appearance>"


def citygml(folder: Path, *, local: str, model: str, name: str = "box.gml") -> Path:
    """The box building with ``local`` appearances inside it and ``model`` ones after it, at the CityModel level."""
    walls = "".join(f'<bldg:boundedBy><bldg:{_SURFACE.get(s, "WallSurface")} gml:id="{s}-surface"><bldg:lod2MultiSurface>'
                    f"<gml:MultiSurface>{_polygon(s)}</gml:MultiSurface></bldg:lod2MultiSurface>"
                    f"</bldg:{_SURFACE.get(s, 'WallSurface')}></bldg:boundedBy>" for s in _BOX)
    text = f"""<?xml version="1.0" encoding="UTF-8"?>
<core:CityModel xmlns:core="http://www.opengis.net/citygml/2.0" xmlns:gml="http://www.opengis.net/gml"
  xmlns:bldg="http://www.opengis.net/citygml/building/2.0" xmlns:app="http://www.opengis.net/citygml/appearance/2.0"
  xmlns:xlink="http://www.w3.org/1999/xlink">
<core:cityObjectMember><bldg:Building gml:id="house">
<core:appearance>{local}</core:appearance>
{walls}
</bldg:Building></core:cityObjectMember>
<app:appearanceMember>{model}</app:appearanceMember>
</core:CityModel>"""
    path = folder / name
    path.write_text(text)
    return path


def _rich(folder: Path) -> Path:
    """Every rule at once: a local material (south), a CityModel-level material after the building (roof),
    a texture (east), a texture and a material on one polygon (north: the texture wins), a back-side
    material (west: not drawn), an unknown target, and a second theme that is not drawn."""
    local = _appearance("rgb", _material("0 0 1", "south"), _material("1 0 0", "west", front="false"))
    model = (_appearance("rgb", _material("0.2 0.8 0.2", "roof", "no-such-polygon"), _texture("tex/east.png", "east"),
                         _material("1 1 0", "north"), _texture("tex/north.png", "north"))
             + _appearance("winter", _material("1 1 1", "roof", "south", "ground")))
    return citygml(folder, local=local, model=model)


EXPECTED = {"roof": GREEN, "ground": GROUND, "south": BLUE, "east": EAST_MEAN, "north": NORTH, "west": WALL}


def _by_side(positions: np.ndarray, faces: np.ndarray, colours: np.ndarray) -> dict[str, set]:
    """Colours of each side's faces, the side found by the face's normal; colours (m, 3) per face."""
    tri = positions[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    out = {}
    for side, d in SIDES.items():
        on = n @ np.asarray(d, float) > 0.99
        assert on.any(), side
        out[side] = {tuple(c) for c in colours[on].tolist()}
    return out


def _mesh_sides(path: Path) -> dict[str, set]:
    (obj,) = load_source(path).objects
    (mesh,) = obj.levels
    return _by_side(mesh.positions, mesh.faces, mesh.face_colours)


def _store_sides(source: Path, tmp_path: Path, name: str) -> dict[str, set]:
    """The colours of each side on the full level of object ``name`` in a store built from ``source``."""
    out = tmp_path / f"{source.stem}.db"
    build_path(source, out, workers=1)
    with SceneStore.open(out) as store:
        idx = store.index
        o = store.object_names().index(name)
        g = decode_geometry(store.geometry(int(idx.rep_first[o] + idx.rep_count[o] - 1)))
    assert g.colours is not None
    corners = g.colours[g.indices.astype(np.int64)]
    assert (corners == corners[:, :1]).all()  # split where colours meet: each face one colour
    return _by_side(g.positions.astype(np.float64), g.indices.astype(np.int64), corners[:, 0])


def test_citygml_materials_and_textures_colour_their_polygons_in_the_built_store(tmp_path) -> None:
    _write_images(tmp_path)
    path = _rich(tmp_path)
    assert _mesh_sides(path) == {s: {c} for s, c in EXPECTED.items()}
    assert _store_sides(path, tmp_path, "house") == {s: {c} for s, c in EXPECTED.items()}


def test_citygml_missing_image_warns_once_and_builds(tmp_path, caplog) -> None:
    # north.png and east.png are not written: east keeps its wall colour, north its material (yellow).
    local = _appearance("rgb", _material("0 0 1", "south"))
    model = _appearance("rgb", _texture("tex/east.png", "east", "west"), _material("1 1 0", "north"),
                        _texture("tex/north.png", "north"))
    path = citygml(tmp_path, local=local, model=model)
    with caplog.at_level(logging.WARNING, logger="server.scene.importers.textures"):
        sides = _store_sides(path, tmp_path, "house")
    assert sides == {"roof": {ROOF}, "ground": {GROUND}, "south": {BLUE}, "east": {WALL}, "west": {WALL},
                     "north": {(255, 255, 0)}}
    warned = [r.getMessage() for r in caplog.records if r.name == "server.scene.importers.textures"]
    assert len(warned) == 2  # one per image, though east.png has two polygons
    assert any("tex/east.png" in w and "no such file" in w for w in warned)


def test_citygml_the_first_theme_named_is_drawn_wherever_it_sits(tmp_path) -> None:
    # The first Appearance (inside the building) is "winter": the CityModel's "rgb" one, after it, is not drawn.
    path = citygml(tmp_path, local=_appearance("winter", _material("0 0 1", "south")),
                   model=_appearance("rgb", _material("0.2 0.8 0.2", "roof")))
    sides = _mesh_sides(path)
    assert sides["south"] == {BLUE} and sides["roof"] == {ROOF}
    # No theme element: the unnamed theme, and it is the first.
    path = citygml(tmp_path, local=_appearance(None, _material("0 0 1", "roof")),
                   model=_appearance("rgb", _material("0.2 0.8 0.2", "south")), name="unnamed.gml")
    sides = _mesh_sides(path)
    assert sides["roof"] == {BLUE} and sides["south"] == {WALL}


def test_citygml_a_target_on_a_surface_or_ring_colours_its_polygons(tmp_path) -> None:
    # An X3DMaterial on the WallSurface's id (an enclosing element), a texture named only by its ring.
    _write_images(tmp_path)
    tex = ('<app:surfaceDataMember><app:ParameterizedTexture><app:imageURI>tex/north.png</app:imageURI>'
           '<app:target uri="#elsewhere"><app:TexCoordList><app:textureCoordinates ring="#east-ring">0 0 1 0 1 1 0 0'
           '</app:textureCoordinates></app:TexCoordList></app:target></app:ParameterizedTexture></app:surfaceDataMember>')
    path = citygml(tmp_path, local="", model=_appearance("rgb", _material("0 0 1", "south-surface"), tex))
    sides = _mesh_sides(path)
    assert sides["south"] == {BLUE} and sides["east"] == {NORTH} and sides["west"] == {WALL}


def test_citygml_an_objects_own_material_wins_over_the_city_models(tmp_path) -> None:
    path = citygml(tmp_path, local=_appearance("rgb", _material("0 0 1", "roof")),
                   model=_appearance("rgb", _material("0.2 0.8 0.2", "roof", "south")))
    sides = _mesh_sides(path)
    assert sides["roof"] == {BLUE} and sides["south"] == {GREEN}


@pytest.mark.parametrize("colour", ["0.5 0.5", "0.1 0.2 1.5", "-0.1 0 0", "nan 0 0", "red green blue", "0 0 0 0"])
def test_citygml_a_bad_diffuse_colour_names_file_and_element(tmp_path, colour) -> None:
    path = citygml(tmp_path, local="", model=_appearance("rgb", _material(colour, "roof")))
    with pytest.raises(SourceError) as err:
        load_source(path)
    message = str(err.value)
    assert str(path) in message and "X3DMaterial" in message and "CityModel" in message
    assert "diffuseColor" in message and colour in message


def test_citygml_a_bad_local_material_names_its_building(tmp_path) -> None:
    path = citygml(tmp_path, local=_appearance("rgb", _material("2 2 2", "roof")), model="")
    with pytest.raises(SourceError, match=r"building house.*X3DMaterial.*diffuseColor '2 2 2'"):
        load_source(path)


def test_citygml_without_appearances_keeps_the_semantic_colours(tmp_path) -> None:
    path = citygml(tmp_path, local="", model="")
    assert _mesh_sides(path) == {s: {ROOF if s == "roof" else GROUND if s == "ground" else WALL} for s in SIDES}


# ---- CityJSON ----

def cityjson(folder: Path, image: str = "tex/east.png") -> Path:
    """The box as a CityJSON MultiSurface: textures on east (image) and north (tex/north.png, which also has
    a material), a material alone on south; the other sides semantic."""
    sides = list(_BOX)
    vertices = [list(p) for s in sides for p in _BOX[s]]
    boundaries = [[[4 * k + j for j in range(4)]] for k in range(len(sides))]
    tex_of = {"east": 0, "north": 1}
    mat_of = {"north": 0, "south": 1}
    doc = {
        "type": "CityJSON", "version": "2.0",
        "transform": {"scale": [1, 1, 1], "translate": ORIGIN.tolist()},
        "vertices": vertices,
        "appearance": {
            "materials": [{"name": "yellow", "diffuseColor": [1, 1, 0]}, {"name": "blue", "diffuseColor": [0, 0, 1]}],
            "textures": [{"type": "PNG", "image": image}, {"type": "PNG", "image": "tex/north.png"}],
            "vertices-texture": [[0, 0], [1, 0], [1, 1], [0, 1]],
        },
        "CityObjects": {"house": {"type": "Building", "geometry": [{
            "type": "MultiSurface", "lod": "2", "boundaries": boundaries,
            "semantics": {"surfaces": [{"type": "RoofSurface"}, {"type": "GroundSurface"}, {"type": "WallSurface"}],
                          "values": [0 if s == "roof" else 1 if s == "ground" else 2 for s in sides]},
            "material": {"rgb": {"values": [mat_of.get(s) for s in sides]}},
            "texture": {"rgb": {"values": [[[tex_of[s], 0, 1, 2, 3]] if s in tex_of else [[None]] for s in sides]}},
        }]}},
    }
    path = folder / "box.city.json"
    path.write_text(json.dumps(doc))
    return path


def test_cityjson_textures_colour_their_polygons_in_the_built_store(tmp_path) -> None:
    _write_images(tmp_path)
    path = cityjson(tmp_path)
    expected = {"roof": {ROOF}, "ground": {GROUND}, "south": {BLUE}, "east": {EAST_MEAN}, "north": {NORTH},
                "west": {WALL}}
    assert _mesh_sides(path) == expected
    assert _store_sides(path, tmp_path, "house") == expected


def test_cityjson_missing_image_warns_once_and_keeps_the_other_colours(tmp_path, caplog) -> None:
    _write_images(tmp_path)
    (tmp_path / "tex" / "north.png").write_bytes(b"not a png")  # unreadable: north falls back to its material
    path = cityjson(tmp_path, image="tex/gone.png")
    with caplog.at_level(logging.WARNING, logger="server.scene.importers.textures"):
        sides = _mesh_sides(path)
    assert sides["east"] == {WALL} and sides["north"] == {(255, 255, 0)} and sides["south"] == {BLUE}
    warned = [r.getMessage() for r in caplog.records if r.name == "server.scene.importers.textures"]
    assert len(warned) == 2 and any("gone.png" in w for w in warned) and any("north.png" in w for w in warned)


def test_cityjson_a_texture_without_an_image_names_it(tmp_path) -> None:
    path = cityjson(tmp_path)
    doc = json.loads(path.read_text())
    doc["appearance"]["textures"][1] = {"type": "PNG"}
    path.write_text(json.dumps(doc))
    with pytest.raises(SourceError, match=r"box\.city\.json: appearance\.textures\[1\]\.image = None"):
        load_source(path)


@settings(max_examples=30, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 255), st.integers(0, 255), st.integers(0, 255), st.integers(0, 255)),
                min_size=1, max_size=64))
def test_mean_colour_is_the_alpha_weighted_mean(pixels) -> None:
    rgba = np.array(pixels, np.uint8).reshape(1, -1, 4)
    got = np.array(mean_colour(Image.fromarray(rgba, "RGBA")))
    w = rgba[0, :, 3].astype(float)
    want = (rgba[0, :, :3] * w[:, None]).sum(0) / w.sum() if w.sum() else rgba[0, :, :3].mean(0)
    assert np.abs(got - want).max() <= 0.5 + 1e-9
    assert ((got >= rgba[0, :, :3].min(0)) & (got <= rgba[0, :, :3].max(0))).all()  # within the pixels' range
