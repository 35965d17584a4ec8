"""What each format brings as appearance: materials, semantic surfaces, IFC classes, base colours, vertex colours."""

from __future__ import annotations

import json

import numpy as np
import trimesh
from trimesh.visual.material import PBRMaterial

from server.scene import palette
from server.scene.data import data_file
from server.scene.importers import load_source

ROOF, WALL, GROUND = (np.array(c, np.uint8) for c in (palette.ROOF, palette.WALL, palette.SURFACES["GroundSurface"]))


def _normals(mesh) -> np.ndarray:
    tri = mesh.positions[mesh.faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def _share(mask: np.ndarray, colours: np.ndarray, colour) -> float:
    return float((colours[mask] == np.asarray(colour, np.uint8)).all(axis=1).mean())


def test_cityjson_semantic_surfaces_take_the_palette() -> None:
    scene = load_source(data_file("city/multi_lod.city.json"))
    finest = [o.levels[-1] for o in scene.objects]
    n = np.concatenate([_normals(m) for m in finest])
    c = np.concatenate([m.face_colours for m in finest])
    assert _share(n[:, 2] > 0.2, c, ROOF) > 0.95
    assert _share(np.abs(n[:, 2]) < 0.05, c, WALL) > 0.95
    assert _share(n[:, 2] < -0.99, c, GROUND) > 0.95


def test_cityjson_materials_win_over_semantics() -> None:
    scene = load_source(data_file("city/DenHaag_01.city.json"))
    buildings = [o.levels[-1] for o in scene.objects if o.cls != "terrain"]
    n = np.concatenate([_normals(m) for m in buildings])
    c = np.concatenate([m.face_colours for m in buildings])
    # The file's materials: roofs (0.502, 0, 0), walls 0.922 grey, ground 0.502 grey.
    assert _share(n[:, 2] > 0.2, c, (128, 0, 0)) > 0.9
    assert _share(np.abs(n[:, 2]) < 0.05, c, (235, 235, 235)) > 0.9
    terrain = next(o for o in scene.objects if o.cls == "terrain").levels[-1]
    assert (terrain.face_colours == np.array(palette.TERRAIN, np.uint8)).all()


def test_ifc_classes_colour_a_house_converted_from_ifc() -> None:
    scene = load_source(data_file("interior/AC20-FZK-Haus.city.json"))
    by_name = {o.attributes["attributes"]["info"].get("Name"): o for o in scene.objects
               if "attributes" in o.attributes and "info" in o.attributes["attributes"]}
    assert (by_name["Dach-1"].levels[-1].face_colours == ROOF).all()
    assert (by_name["Bodenplatte"].levels[-1].face_colours != ROOF).any(axis=1).all()
    walls = [o for o in scene.objects if o.attributes.get("attributes", {}).get("info", {}).get("type")
             == "IfcWallStandardCase"]
    assert walls and all((o.levels[-1].face_colours == WALL).all() for o in walls)


def test_a_small_cityjson_with_a_material_theme_null_values_and_a_plain_object(tmp_path) -> None:
    square = [[[0, 1, 2, 3]], [[4, 5, 6, 7]]]
    doc = {
        "type": "CityJSON", "version": "2.0", "transform": {"scale": [1, 1, 1], "translate": [0, 0, 0]},
        "vertices": [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]],
        "appearance": {"materials": [{"name": "red", "diffuseColor": [1.0, 0.0, 0.0]}, {"name": "none"}]},
        "CityObjects": {
            "a": {"type": "Building", "geometry": [{
                "type": "MultiSurface", "lod": "2", "boundaries": square,
                "semantics": {"surfaces": [{"type": "RoofSurface"}, {"type": "WallSurface"}], "values": [0, 1]},
                "material": {"theme": {"values": [None, 0]}}}]},
            "b": {"type": "Bridge", "geometry": [{"type": "MultiSurface", "lod": "1", "boundaries": square}]},
        },
    }
    path = tmp_path / "small.city.json"
    path.write_text(json.dumps(doc))
    a, b = load_source(path).objects
    # Polygon 0: no material, its semantics (roof); polygon 1: the material wins over "WallSurface".
    np.testing.assert_array_equal(a.levels[0].face_colours, [palette.ROOF] * 2 + [(255, 0, 0)] * 2)
    assert (b.levels[0].face_colours == np.array(palette.CLASSES["bridge"], np.uint8)).all()


def test_citygml_faces_take_the_surface_they_bound() -> None:
    scene = load_source(data_file("trees/berlin_buildings_lod2.gml"))
    n = np.concatenate([_normals(o.levels[-1]) for o in scene.objects])
    c = np.concatenate([o.levels[-1].face_colours for o in scene.objects])
    assert _share(n[:, 2] > 0.2, c, ROOF) > 0.95
    assert _share(np.abs(n[:, 2]) < 0.05, c, WALL) > 0.95


def test_gltf_base_colour_factor_and_ply_colours(tmp_path) -> None:
    box = trimesh.creation.box()
    box.visual = trimesh.visual.TextureVisuals(material=PBRMaterial(baseColorFactor=[200, 30, 40, 255]))
    trimesh.Scene(box).export(tmp_path / "box.glb")
    (obj,) = load_source(tmp_path / "box.glb").objects
    assert (obj.levels[0].face_colours == [200, 30, 40]).all()

    faces = trimesh.creation.box()
    faces.visual.face_colors = np.tile([10, 200, 10, 255], (12, 1))
    faces.export(tmp_path / "faces.ply")
    assert (load_source(tmp_path / "faces.ply").objects[0].levels[0].face_colours == [10, 200, 10]).all()

    painted = trimesh.creation.icosphere(1)
    rgb = np.column_stack([np.arange(42) * 6, np.full(42, 50), np.full(42, 90)]).astype(np.uint8)
    painted.visual.vertex_colors = np.column_stack([rgb, np.full(42, 255, np.uint8)])
    painted.export(tmp_path / "painted.ply")
    mesh = load_source(tmp_path / "painted.ply").objects[0].levels[0]
    assert mesh.face_colours is None
    np.testing.assert_array_equal(mesh.vertex_colours, rgb)

    plain = trimesh.creation.box()
    plain.export(tmp_path / "chair_1.ply")  # no colours: the class colour (here: the default)
    assert (load_source(tmp_path / "chair_1.ply").objects[0].levels[0].face_colours == palette.DEFAULT).all()
