"""CityJSON import: the real Den Haag, multi-LoD and interior files, and malformed variants."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from server.scene.data import data_file
from server.scene.importers import load_source
from server.scene.importers.cityjson import load_cityjson, normalise_crs
from server.scene.source import SourceError


@pytest.fixture(scope="module")
def denhaag():
    return load_cityjson(data_file("city/DenHaag_01.city.json"))


def _signed_volume(mesh) -> float:
    t = mesh.positions[mesh.faces] - mesh.positions.mean(axis=0)
    return float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6)


def test_denhaag_objects_terrain_and_coordinates(denhaag):
    scene = denhaag
    assert scene.crs == "EPSG:7415"
    assert scene.sources == [str(data_file("city/DenHaag_01.city.json"))]
    classes = Counter(o.cls for o in scene.objects)
    # 1,653 parts all carry geometry; of the 844 Buildings, the 507 that only group parts have none.
    assert classes == {"buildingpart": 1653, "building": 337, "terrain": 1}
    total = sum(m.n_faces for o in scene.objects for m in o.levels)
    assert 40_000 <= total <= 42_000
    terrain = next(o for o in scene.objects if o.cls == "terrain")
    assert terrain.levels[0].n_faces == 5595 and terrain.attributes["type"] == "TINRelief"
    xyz = np.concatenate([m.positions for o in scene.objects for m in o.levels])
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    # Decoded metres (scale 0.001 + translate) in EPSG:7415 (RD New + NAP).
    assert 78_000 < lo[0] and hi[0] < 81_000 and 457_000 < lo[1] and hi[1] < 459_000
    assert -10 < lo[2] and hi[2] < 100
    assert 700 < hi[0] - lo[0] < 900 and 600 < hi[1] - lo[1] < 750


def test_denhaag_meshes_are_compact_closed_outward_solids(denhaag):
    scene = denhaag
    parts = [o for o in scene.objects if o.cls == "buildingpart"]
    assert all(len(o.levels) == 1 and o.attributes["lods"] == ["2"] for o in scene.objects)
    assert all(isinstance(o.attributes.get("parent"), str) for o in parts)
    names = {o.name for o in scene.objects}
    assert len(names) == len(scene.objects)
    for o in scene.objects:
        m = o.levels[0]
        used = np.zeros(m.n_vertices, bool)
        used[m.faces.ravel()] = True
        assert used.all(), o.name  # no vertex unused by the object
    # Solids keep their outward orientation through triangulation: positive volume.
    volumes = np.array([_signed_volume(o.levels[0]) for o in scene.objects if o.cls != "terrain"])
    assert (volumes > 0).all()


def test_multi_lod_levels_are_ordered_coarse_to_fine():
    scene = load_cityjson(data_file("city/multi_lod.city.json"))
    assert len(scene.objects) == 10
    for o in scene.objects:
        assert o.cls == "building"
        assert o.attributes["lods"] == ["1.2", "1.3", "2.2"]
        faces = [m.n_faces for m in o.levels]
        assert len(faces) == 3 and faces == sorted(faces) and faces[0] > 0
        assert "identificatie" in o.attributes["attributes"]


def test_interior_house_imports_every_object_with_geometry():
    path = data_file("interior/AC20-FZK-Haus.city.json")
    scene = load_source(path)
    n_with_geometry = sum(1 for o in json.loads(path.read_text())["CityObjects"].values() if o.get("geometry"))
    assert len(scene.objects) == n_with_geometry == 107  # 108 CityObjects; the root "Building" has none
    total = sum(m.n_faces for o in scene.objects for m in o.levels)
    assert 23_000 <= total <= 24_500  # 24,154 input triangles, a few hundred of them zero-area
    xyz = np.concatenate([o.levels[0].positions for o in scene.objects])
    assert np.ptp(xyz, axis=0) == pytest.approx([18, 16, 7.3], abs=1.0)
    assert {o.attributes["attributes"]["info"]["type"] for o in scene.objects} >= {"IfcWallStandardCase", "IfcWindow"}


def test_crs_normalisation():
    assert normalise_crs("urn:ogc:def:crs:EPSG::7415") == "EPSG:7415"
    assert normalise_crs("https://www.opengis.net/def/crs/EPSG/0/7415") == "EPSG:7415"
    assert normalise_crs("EPSG:25833") == "EPSG:25833"
    assert normalise_crs(None) is None


# --- small synthetic files -------------------------------------------------------------------------------

def _cube(version: str = "2.0", **extra) -> dict:
    """A 1 m cube with a window hole in one face, integer vertices and a transform."""
    v = [[0, 0, 0], [1000, 0, 0], [1000, 1000, 0], [0, 1000, 0],
         [0, 0, 1000], [1000, 0, 1000], [1000, 1000, 1000], [0, 1000, 1000],
         [250, 0, 250], [750, 0, 250], [750, 0, 750], [250, 0, 750]]
    shell = [[[0, 3, 2, 1]], [[4, 5, 6, 7]], [[0, 1, 5, 4], [8, 11, 10, 9]], [[1, 2, 6, 5]],
             [[2, 3, 7, 6]], [[3, 0, 4, 7]]]
    doc = {"type": "CityJSON", "version": version,
           "transform": {"scale": [0.001, 0.001, 0.001], "translate": [100.0, 200.0, 3.0]},
           "metadata": {"referenceSystem": "https://www.opengis.net/def/crs/EPSG/0/7415"},
           "CityObjects": {"b1": {"type": "Building", "geometry": [
               {"type": "Solid", "lod": "2.2", "boundaries": [shell]},
               {"type": "MultiSurface", "lod": "1.0", "boundaries": [[[0, 3, 2, 1]]]}]}},
           "vertices": v}
    doc.update(extra)
    return doc


def _write(tmp_path: Path, doc, name: str = "broken.city.json") -> Path:
    path = tmp_path / name
    path.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    return path


@pytest.mark.parametrize("version", ["1.0", "1.1", "2.0"])
def test_synthetic_cube_with_window_hole(tmp_path, version):
    scene = load_source(_write(tmp_path, _cube(version), "cube.json"))
    (obj,) = scene.objects
    assert obj.attributes["lods"] == ["1.0", "2.2"]
    coarse, fine = obj.levels
    assert coarse.n_faces == 2 and coarse.n_vertices == 4  # compacted to the vertices it uses
    assert fine.n_faces == 5 * 2 + 8
    t = fine.positions[fine.faces]
    area = 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum()
    assert area == pytest.approx(6 - 0.25)  # six faces less the window
    assert _signed_volume(fine) > 0.9  # outward (open at the window, so not exactly 1)
    assert fine.positions.min(axis=0) == pytest.approx([100, 200, 3])
    assert scene.crs == "EPSG:7415"


def test_untransformed_float_vertices_and_geometry_instance(tmp_path):
    doc = _cube()
    del doc["transform"]
    doc["vertices"] = [[float(c) / 1000 for c in p] for p in doc["vertices"]]
    doc["geometry-templates"] = {
        "templates": [{"type": "MultiSurface", "lod": "1", "boundaries": [[[0, 1, 2]]]}],
        "vertices-templates": [[0, 0, 0], [2, 0, 0], [0, 2, 0]]}
    doc["CityObjects"]["tree"] = {"type": "SolitaryVegetationObject", "geometry": [
        {"type": "GeometryInstance", "template": 0, "boundaries": [6],
         "transformationMatrix": [1, 0, 0, 5, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]}]}
    scene = load_cityjson(_write(tmp_path, doc))
    cube, tree = scene.objects
    assert cube.levels[-1].positions.max(axis=0) == pytest.approx([1, 1, 1])
    assert tree.cls == "solitaryvegetationobject"
    assert tree.levels[0].positions.tolist() == [[6, 1, 1], [8, 1, 1], [6, 3, 1]]
    assert "template 0" in tree.attributes["notes"][0]


def _broken(tmp_path, mutate) -> tuple[Path, str]:
    doc = _cube()
    mutate(doc)
    path = _write(tmp_path, doc)
    with pytest.raises(SourceError) as err:
        load_cityjson(path)
    message = str(err.value)
    assert str(path) in message
    return path, message


def test_truncated_json_names_line_and_column(tmp_path):
    text = json.dumps(_cube(), indent=1)
    path = _write(tmp_path, text[: len(text) // 2])
    with pytest.raises(SourceError, match=r"broken\.city\.json: invalid JSON at line \d+, column \d+"):
        load_cityjson(path)


def test_wrong_type_and_unsupported_version(tmp_path):
    _, msg = _broken(tmp_path, lambda d: d.update(type="FeatureCollection"))
    assert "'FeatureCollection'" in msg and "'CityJSON'" in msg
    _, msg = _broken(tmp_path, lambda d: d.update(version="0.9"))
    assert "'0.9'" in msg and "1.0, 1.1, 2.0" in msg


def test_missing_vertices(tmp_path):
    _, msg = _broken(tmp_path, lambda d: d.pop("vertices"))
    assert "'vertices' is missing" in msg


def test_index_out_of_range_names_object_and_index(tmp_path):
    def mutate(d):
        d["CityObjects"]["b1"]["geometry"][0]["boundaries"][0][3][0][2] = 99

    _, msg = _broken(tmp_path, mutate)
    assert "'b1'" in msg and "geometry #0" in msg and "99" in msg and "out of range" in msg


@pytest.mark.parametrize("bad", [float("nan"), "12", None])
def test_non_finite_or_non_numeric_vertex(tmp_path, bad):
    def mutate(d):
        d["vertices"][5][1] = bad

    _, msg = _broken(tmp_path, mutate)
    assert "vertices[5]" in msg


def test_unknown_geometry_type_names_object(tmp_path):
    def mutate(d):
        d["CityObjects"]["b1"]["geometry"][1]["type"] = "Blob"

    _, msg = _broken(tmp_path, mutate)
    assert "'b1'" in msg and "geometry #1" in msg and "'Blob'" in msg


def test_wrongly_nested_boundaries_and_missing_file(tmp_path):
    def mutate(d):
        d["CityObjects"]["b1"]["geometry"][0]["type"] = "MultiSolid"  # one level too few for a MultiSolid

    _, msg = _broken(tmp_path, mutate)
    assert "'b1'" in msg and "boundaries" in msg
    with pytest.raises(SourceError, match="nothing.city.json"):
        load_cityjson(tmp_path / "nothing.city.json")


def test_dispatcher_rejects_unknown_suffix(tmp_path):
    path = tmp_path / "scene.xyz"
    path.write_text("")
    with pytest.raises(SourceError, match=r"scene\.xyz.*\.city\.json.*\.glb.*\.gml"):
        load_source(path)
