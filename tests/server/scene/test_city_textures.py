"""CityJSON and CityGML textures drawn as textures: a box building whose walls use two PNGs of bold, distinct
patterns and whose roof has a material. The CityJSON one is built into a store and its full level drawn by the
real renderer (EGL) with the textured algorithm: both patterns show on the walls. The CityGML one is checked
on the importer's mesh: UVs and an atlas, a targeted polygon's UVs landing on its image's pixels."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from proto.geometry import decode_geometry
from server.scene.catalog import build_path
from server.scene.importers import load_source
from server.scene.store import SceneStore

W, H = 200, 150
RED, GREEN = (230, 20, 20), (20, 210, 30)  # south wall: vertical stripes
BLUE, YELLOW = (20, 40, 230), (235, 225, 20)  # east wall: horizontal stripes
ROOF = (1.0, 0.0, 1.0)  # the roof's material: magenta
ORIGIN = np.array([390000.0, 5810000.0, 30.0])
_BOX = {  # corners counter-clockwise seen from outside
    "roof": [(0, 0, 6), (10, 0, 6), (10, 8, 6), (0, 8, 6)],
    "ground": [(0, 0, 0), (0, 8, 0), (10, 8, 0), (10, 0, 0)],
    "south": [(0, 0, 0), (10, 0, 0), (10, 0, 6), (0, 0, 6)],
    "east": [(10, 0, 0), (10, 8, 0), (10, 8, 6), (10, 0, 6)],
    "north": [(10, 8, 0), (0, 8, 0), (0, 8, 6), (10, 8, 6)],
    "west": [(0, 8, 0), (0, 0, 0), (0, 0, 6), (0, 8, 6)],
}


def _stripes(a, b, vertical: bool, side: int = 64, n: int = 4) -> np.ndarray:
    img = np.zeros((side, side, 3), np.uint8)
    band = (np.indices((side, side))[1 if vertical else 0] // (side // n)) % 2 == 1
    img[~band], img[band] = a, b
    return img


def _write_images(folder: Path) -> None:
    Image.fromarray(_stripes(RED, GREEN, True)).save(folder / "south.png")
    Image.fromarray(_stripes(BLUE, YELLOW, False)).save(folder / "east.png")


def _cityjson(folder: Path) -> Path:
    sides = list(_BOX)
    tex_of = {"south": 0, "east": 1}
    doc = {
        "type": "CityJSON", "version": "2.0",
        "transform": {"scale": [1, 1, 1], "translate": ORIGIN.tolist()},
        "vertices": [list(p) for s in sides for p in _BOX[s]],
        "appearance": {
            "materials": [{"name": "roof", "diffuseColor": list(ROOF)}],
            "textures": [{"type": "PNG", "image": "south.png"}, {"type": "PNG", "image": "east.png"}],
            # the east wall tiles its image once, one unit off: wrapped back onto the image
            "vertices-texture": [[0, 0], [1, 0], [1, 1], [0, 1], [1, 0], [2, 0], [2, 1], [1, 1]],
        },
        "CityObjects": {"house": {"type": "Building", "geometry": [{
            "type": "MultiSurface", "lod": "2",
            "boundaries": [[[4 * k + j for j in range(4)]] for k in range(len(sides))],
            "semantics": {"surfaces": [{"type": "RoofSurface"}, {"type": "GroundSurface"}, {"type": "WallSurface"}],
                          "values": [0 if s == "roof" else 1 if s == "ground" else 2 for s in sides]},
            "material": {"rgb": {"values": [0 if s == "roof" else None for s in sides]}},
            "texture": {"rgb": {"values": [[[0, 0, 1, 2, 3]] if s == "south" else [[1, 4, 5, 6, 7]] if s == "east"
                                           else [[None]] for s in sides]}},
        }]}},
    }
    path = folder / "house.city.json"
    path.write_text(json.dumps(doc))
    return path


def _kind(pixels: np.ndarray) -> np.ndarray:
    """Per pixel (…, 3): 0 red, 1 green, 2 blue, 3 yellow, −1 none of them (by dominant channels)."""
    p = pixels.astype(int)
    r, g, b = p[..., 0], p[..., 1], p[..., 2]
    out = np.full(r.shape, -1)
    out[(r > 1.8 * g) & (r > 1.8 * b)] = 0
    out[(g > 1.8 * r) & (g > 1.8 * b)] = 1
    out[(b > 1.8 * r) & (b > 1.8 * g)] = 2
    out[(r > 1.8 * b) & (g > 1.8 * b) & (np.abs(r - g) < 0.3 * r)] = 3
    return out


@pytest.fixture(scope="module")
def level(tmp_path_factory):
    """The built store's full level of the CityJSON house, decoded."""
    folder = tmp_path_factory.mktemp("citytex")
    _write_images(folder)
    out = folder / "house.db"
    build_path(_cityjson(folder), out, workers=1)
    with SceneStore.open(out) as store:
        idx = store.index
        o = store.object_names().index("house")
        return decode_geometry(store.geometry(int(idx.rep_first[o] + idx.rep_count[o] - 1)))


def test_cityjson_full_level_carries_uvs_and_an_atlas_of_both_images(level) -> None:
    assert level.uv is not None and level.texture is not None
    assert level.uv.shape == (level.vertices, 2)
    kinds = _kind(level.texture)
    assert all((kinds == k).sum() > 20 for k in range(4))  # both images' colours are in the atlas
    # the roof samples its material's colour, not an image
    tri = level.positions[level.indices.astype(np.int64)].astype(np.float64)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    roof = n[:, 2] / np.linalg.norm(n, axis=1) > 0.99
    uv = level.uv[level.indices[roof].astype(np.int64)].reshape(-1, 2)
    t = level.texture
    texel = t[np.clip(((1 - uv[:, 1]) * t.shape[0]).astype(int), 0, t.shape[0] - 1),
              np.clip((uv[:, 0] * t.shape[1]).astype(int), 0, t.shape[1] - 1)]
    assert (np.abs(texel.astype(int) - (255, 0, 255)).max(axis=1) <= 8).all()


def test_cityjson_walls_drawn_with_both_patterns(level) -> None:
    from client.renderer import Renderer

    lo, hi = level.positions.min(axis=0), level.positions.max(axis=0)
    centre = (lo + hi) / 2
    eye = centre + np.array([14.0, -14.0, 0.0])  # off the south-east corner, at mid height: both walls
    forward = (centre - eye) / np.linalg.norm(centre - eye)
    with Renderer(W, H, fov_y=60.0) as renderer:
        renderer.upload(1, level)
        renderer.draw(np.array([1]), eye, forward, np.array([0.0, 0.0, 1.0]), 0.1, 200.0,
                      algorithms=np.array([2]))
        image = renderer.read_image()
        kinds = _kind(image[H // 4: 3 * H // 4])
        left, right = kinds[:, : W // 2 - 5], kinds[:, W // 2 + 15:]  # the corner stands a little right of centre
        # the south wall (left of the corner): red and green stripes alternating along a row
        assert (left == 0).sum() > 100 and (left == 1).sum() > 100 and not np.isin(left, (2, 3)).any()
        row = left[left.shape[0] // 2]
        assert np.count_nonzero(np.diff(row[row >= 0])) >= 3
        # the east wall (right of it): blue and yellow bands, alternating down a column
        assert (right == 2).sum() > 100 and (right == 3).sum() > 100 and not np.isin(right, (0, 1)).any()
        column = right[:, np.argmax((right >= 0).sum(axis=0))]
        assert np.count_nonzero(np.diff(column[column >= 0])) >= 2
        # the flat algorithm draws the surfaces' colours (the images' means: olive, grey), no stripes
        renderer.draw(np.array([1]), eye, forward, np.array([0.0, 0.0, 1.0]), 0.1, 200.0,
                      algorithms=np.array([0]))
        flat = _kind(renderer.read_image()[H // 4: 3 * H // 4])
        assert not np.isin(flat, (0, 1, 2)).any()


# ---- CityGML ----

def _citygml(folder: Path, coords: str) -> Path:
    def polygon(side: str) -> str:
        pts = " ".join(f"{x + ORIGIN[0]} {y + ORIGIN[1]} {z + ORIGIN[2]}" for x, y, z in [*_BOX[side], _BOX[side][0]])
        return (f'<gml:surfaceMember><gml:Polygon gml:id="{side}"><gml:exterior><gml:LinearRing gml:id="{side}-ring">'
                f'<gml:posList srsDimension="3">{pts}</gml:posList></gml:LinearRing></gml:exterior></gml:Polygon>'
                f'</gml:surfaceMember>')

    def texture(image: str, side: str) -> str:
        return (f"<app:surfaceDataMember><app:ParameterizedTexture><app:imageURI>{image}</app:imageURI>"
                f'<app:target uri="#{side}"><app:TexCoordList><app:textureCoordinates ring="#{side}-ring">'
                f"{coords}</app:textureCoordinates></app:TexCoordList></app:target>"
                "</app:ParameterizedTexture></app:surfaceDataMember>")

    surfaces = {"roof": "RoofSurface", "ground": "GroundSurface"}
    walls = "".join(f'<bldg:boundedBy><bldg:{surfaces.get(s, "WallSurface")}><bldg:lod2MultiSurface>'
                    f"<gml:MultiSurface>{polygon(s)}</gml:MultiSurface></bldg:lod2MultiSurface>"
                    f"</bldg:{surfaces.get(s, 'WallSurface')}></bldg:boundedBy>" for s in _BOX)
    material = ("<app:surfaceDataMember><app:X3DMaterial><app:diffuseColor>1 0 1</app:diffuseColor>"
                "<app:target>#roof</app:target></app:X3DMaterial></app:surfaceDataMember>")
    path = folder / "house.gml"
    path.write_text(f"""<?xml version="1.0" encoding="UTF-8"?>
<core:CityModel xmlns:core="http://www.opengis.net/citygml/2.0" xmlns:gml="http://www.opengis.net/gml"
  xmlns:bldg="http://www.opengis.net/citygml/building/2.0" xmlns:app="http://www.opengis.net/citygml/appearance/2.0">
<core:cityObjectMember><bldg:Building gml:id="house">
<core:appearance><app:Appearance><app:theme>rgb</app:theme>{texture("south.png", "south")}{texture("east.png", "east")}
{material}</app:Appearance></core:appearance>
{walls}
</bldg:Building></core:cityObjectMember>
</core:CityModel>""")
    return path


def _sample(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """The texels (k, 3) under UVs (k, 2) (OpenGL's v up)."""
    h, w = texture.shape[:2]
    return texture[np.clip(((1 - uv[:, 1]) * h).astype(int), 0, h - 1), np.clip((uv[:, 0] * w).astype(int), 0, w - 1)]


def test_citygml_parameterized_texture_maps_its_polygon_onto_the_image(tmp_path) -> None:
    _write_images(tmp_path)
    # the ring's four corners and its closing point, (0, 0) at the image's bottom left
    (obj,) = load_source(_citygml(tmp_path, "0 0 1 0 1 1 0 1 0 0")).objects
    (mesh,) = obj.levels
    assert mesh.uv is not None and mesh.texture is not None
    p = mesh.positions - ORIGIN
    south = _stripes(RED, GREEN, True)
    for side, image in (("south", south), ("east", _stripes(BLUE, YELLOW, False))):
        corners = np.array(_BOX[side], float)
        # each corner of the polygon, where the mesh has it: the UV lands on the image's corner texel
        for k, c in enumerate(corners):
            on = np.flatnonzero(np.abs(p - c).max(axis=1) < 1e-6)
            tri_normal = None
            for v in on:
                faces = np.flatnonzero((mesh.faces == v).any(axis=1))
                t = mesh.positions[mesh.faces[faces[0]]]
                n = np.cross(t[1] - t[0], t[2] - t[0])
                d = np.cross(corners[1] - corners[0], corners[2] - corners[0])
                if np.dot(n, d) > 0.99 * np.linalg.norm(n) * np.linalg.norm(d):
                    tri_normal = v
            assert tri_normal is not None, (side, k)
            want = image[[-1, -1, 0, 0][k], [0, -1, -1, 0][k]]  # (0,0) bottom-left, (1,0), (1,1), (0,1)
            np.testing.assert_array_equal(_sample(mesh.texture, mesh.uv[[tri_normal]])[0], want)
    # the roof (its material) points at a patch of magenta; the ground at its semantic colour's
    roof = np.flatnonzero(np.abs(p[:, 2] - 6) < 1e-6)
    roof_uv = np.unique(mesh.uv[roof], axis=0)
    assert (np.abs(_sample(mesh.texture, roof_uv).astype(int) - (255, 0, 255)).max(axis=1) <= 8).any()


def test_citygml_coordinates_that_do_not_fit_the_ring_leave_the_mean_colour(tmp_path, caplog) -> None:
    _write_images(tmp_path)
    (obj,) = load_source(_citygml(tmp_path, "0 0 1 0 1 1")).objects  # three pairs for a four-point ring
    (mesh,) = obj.levels
    assert mesh.uv is None and mesh.texture is None
    assert any("texture coordinates" in r.getMessage() for r in caplog.records)


def test_cityjson_texture_values_that_miss_a_ring_vertex_are_an_error_naming_the_polygon(tmp_path) -> None:
    from server.scene.source import SourceError

    _write_images(tmp_path)
    path = _cityjson(tmp_path)
    doc = json.loads(path.read_text())
    values = doc["CityObjects"]["house"]["geometry"][0]["texture"]["rgb"]["values"]
    first = next(i for i, v in enumerate(values) if v != [[None]])
    values[first] = [values[first][0][:-1]]  # one uv index short of the ring's four vertices
    path.write_text(json.dumps(doc))
    with pytest.raises(SourceError, match=rf"house\.city\.json.*polygon {first}"):
        load_source(path)
