"""CityGML: instanced trees (ImplicitGeometry) and LoD2 buildings, real files and malformed ones."""

from __future__ import annotations

import re

import numpy as np
import pytest

from server.scene.data import data_file
from server.scene.importers.citygml import load_citygml
from server.scene.source import SourceError

TREES = data_file("trees/berlin_trees.gml")
BUILDINGS = data_file("trees/berlin_buildings_lod2.gml")


@pytest.fixture(scope="module")
def trees():
    return load_citygml(TREES)


def test_tree_instances(trees):
    assert trees.crs == "EPSG:25833"
    assert len(trees.trees) == 288 and len(trees.tree_models) == 10
    assert len(trees.trees.names) == 288 and len(set(trees.trees.names)) == 288
    assert np.bincount(trees.trees.model, minlength=10).min() >= 1
    assert np.isfinite(trees.trees.matrix).all()
    assert (trees.trees.matrix[:, 3] == [0, 0, 0, 1]).all()
    for m in trees.tree_models:
        mesh = m.mesh
        assert mesh.n_faces > 50 and np.isfinite(mesh.positions).all()
        assert mesh.faces.min() >= 0 and mesh.faces.max() < mesh.n_vertices
        assert abs(mesh.positions[:, 2].min()) < 0.005  # base at the origin (two prototypes dip 4 mm / 2 mm)


def test_tree_world_positions(trees):
    text = TREES.read_text()
    refs = np.array([[float(v) for v in p.split()] for p in re.findall(
        r"<core:referencePoint>\s*<gml:Point[^>]*>\s*<gml:pos>([^<]+)</gml:pos>", text)])
    assert refs.shape == (288, 3)
    heights = []
    for m in trees.tree_models:
        heights += m.attributes["instances"]["height"]
    order = np.concatenate([np.flatnonzero(trees.trees.model == k) for k in range(10)])
    height = np.empty(288)
    height[order] = heights
    for i in range(288):
        mesh = trees.tree_models[trees.trees.model[i]].mesh
        world = mesh.positions @ trees.trees.matrix[i][:3, :3].T + trees.trees.matrix[i][:3, 3]
        base = world[world[:, 2] <= world[:, 2].min() + 1e-6]
        assert np.allclose(trees.trees.matrix[i][:3, 3], refs[i])
        assert abs(world[:, 2].min() - refs[i, 2]) <= 0.005 * height[i]
        assert np.linalg.norm(base[:, :2].mean(0) - refs[i, :2]) < 1.0  # trunk foot under the reference point
        assert world[:, 2].max() - world[:, 2].min() == pytest.approx(height[i], rel=0.01)
    x0, y0 = 396800.04, 5819400.54  # the file's envelope
    assert (refs[:, 0] > x0 - 1).all() and (refs[:, 1] > y0 - 1).all()


def test_buildings():
    s = load_citygml(BUILDINGS)
    assert s.crs == "EPSG:25833" and s.trees is None
    parts = [o for o in s.objects if o.cls == "buildingpart"]
    whole = [o for o in s.objects if o.cls == "building"]
    assert len(parts) == 35
    assert len({p.attributes["building"] for p in parts}) + len(whole) >= 17
    assert len({p.attributes["building"] for p in parts} | {o.name for o in whole}) == 17
    for o in s.objects:
        (m,) = o.levels
        assert m.n_faces >= 4 and np.isfinite(m.positions).all() and m.faces.max() < m.n_vertices
        lo, hi = m.positions.min(0), m.positions.max(0)
        assert 396700 < lo[0] and hi[0] < 397100 and 30 < lo[2] < hi[2] < 120
        assert hi[2] - lo[2] > 2


_TREE = """<?xml version="1.0"?>
<CityModel xmlns="http://www.opengis.net/citygml/2.0" xmlns:gml="http://www.opengis.net/gml"
  xmlns:veg="http://www.opengis.net/citygml/vegetation/2.0" xmlns:xlink="http://www.w3.org/1999/xlink">
<cityObjectMember><veg:SolitaryVegetationObject gml:id="t1"><veg:lod2ImplicitRepresentation><ImplicitGeometry>
 <transformationMatrix>{matrix}</transformationMatrix>
 <relativeGMLGeometry><gml:Polygon gml:id="p1"><gml:exterior><gml:LinearRing>
  <gml:posList>0 0 0 1 0 0 1 1 {z} 0 1 1 0 0 0</gml:posList></gml:LinearRing></gml:exterior></gml:Polygon>
 </relativeGMLGeometry>
 <referencePoint><gml:Point><gml:pos>10 20 30</gml:pos></gml:Point></referencePoint>
</ImplicitGeometry></veg:lod2ImplicitRepresentation></veg:SolitaryVegetationObject></cityObjectMember>
<cityObjectMember><veg:SolitaryVegetationObject gml:id="t2"><veg:lod2ImplicitRepresentation><ImplicitGeometry>
 <transformationMatrix>2 0 0 0 0 2 0 0 0 0 2 0 0 0 0 1</transformationMatrix>
 <relativeGMLGeometry xlink:href="#{href}"/>
 <referencePoint><gml:Point><gml:pos>1 2 3</gml:pos></gml:Point></referencePoint>
</ImplicitGeometry></veg:lod2ImplicitRepresentation></veg:SolitaryVegetationObject></cityObjectMember>
</CityModel>
"""
_GOOD = dict(matrix="1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1", z="1", href="p1")


def test_small_file(tmp_path):
    p = tmp_path / "t.gml"
    p.write_text(_TREE.format(**_GOOD))
    s = load_citygml(p)
    assert len(s.trees) == 2 and len(s.tree_models) == 1 and list(s.trees.model) == [0, 0]
    assert s.trees.names == ["t1", "t2"]
    assert np.allclose(s.trees.matrix[1] @ [1, 1, 1, 1], [3, 4, 5, 1])  # ref + M·v
    assert s.tree_models[0].mesh.n_faces == 2


@pytest.mark.parametrize("change, message", [
    (dict(href="nope"), "tree 2 .*unknown prototype '#nope'"),
    (dict(matrix="1 0 0 0 0 1 0 0 0 0 1 0 0 0 0"), "tree 1 .*15 numbers"),
    (dict(z="nan"), "prototype p1.*NaN"),
    (dict(z="abc"), "non-numeric"),
])
def test_malformed(tmp_path, change, message):
    p = tmp_path / "bad.gml"
    p.write_text(_TREE.format(**{**_GOOD, **change}))
    with pytest.raises(SourceError, match=message) as e:
        load_citygml(p)
    assert "bad.gml" in str(e.value)


def test_not_xml(tmp_path):
    p = tmp_path / "bad.gml"
    p.write_text(_TREE.format(**_GOOD).replace("</cityObjectMember>\n<cityObjectMember>", "</cityObjectMember>\n<<"))
    with pytest.raises(SourceError, match=r"bad.gml: line 1[0-9]"):
        load_citygml(p)
    p.write_text("")
    with pytest.raises(SourceError, match="empty"):
        load_citygml(p)
    p.write_text(_TREE.format(**_GOOD)[:600])
    with pytest.raises(SourceError, match="bad.gml"):
        load_citygml(p)
