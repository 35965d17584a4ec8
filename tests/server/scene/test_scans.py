"""Scanned trees as tree models: model space, prefix order, splat attributes, and a scene's trees drawn with them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from server.scene.catalog import load_tree_model, with_tree_models
from server.scene.data import data_file
from server.scene.importers import load_source
from server.scene.importers.pointcloud import read_xyz
from server.scene.points import point_model
from server.scene.scans import scan_tree_model, use_tree_models
from server.scene.source import PointCloud, SourceError, SourceScene, TreeInstances
from server.scene.vegetation import broadleaf, conifer


def _synthetic(height: float, crown: float, n: int = 3000, seed: int = 0, at=(0.0, 0.0, 0.0)) -> PointCloud:
    """A trunk (a thin cylinder to 40 % of the height) under an ellipsoid crown of the given width, as a scan."""
    rng = np.random.default_rng(seed)
    k = n // 5
    t = rng.uniform(0, 2 * np.pi, k)
    trunk = np.column_stack([0.2 * np.cos(t), 0.2 * np.sin(t), rng.uniform(0, 0.4 * height, k)])
    d = rng.normal(size=(n - k, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    semi = np.array([crown / 2, crown / 2, 0.3 * height])
    crown_pts = d * semi + [0, 0, 0.7 * height]
    return PointCloud(np.concatenate([trunk, crown_pts]) + at)


@pytest.fixture(scope="module")
def tree13():
    return load_tree_model(data_file("trees/tree13.xyz"))


def test_a_real_scan_stands_on_the_origin(tree13):
    raw = read_xyz(data_file("trees/tree13.xyz")).positions
    p = tree13.points.positions
    assert tree13.mesh is None and len(tree13.points) == raw.shape[0]
    assert p[:, 2].min() == 0.0 and tree13.attributes["height"] == pytest.approx(np.ptp(raw[:, 2]))
    foot = p[:, 2] <= 0.1 * tree13.attributes["height"]
    assert np.abs(np.median(p[foot, :2], axis=0)).max() < 1e-9  # the trunk's axis is the z axis
    assert np.allclose(p + tree13.attributes["offset"], raw)
    assert np.allclose(np.linalg.norm(tree13.points.normals, axis=1), 1.0)
    assert 0.01 < tree13.attributes["spacing"] < 0.5
    assert tree13.attributes["source"].endswith("tree13.xyz")
    # Bark low on the axis, foliage above: the colours of the generated models.
    c = tree13.points.colors.astype(float)
    low = (p[:, 2] < 1.0) & (np.hypot(p[:, 0], p[:, 1]) < 0.5)
    high = p[:, 2] > 0.6 * tree13.attributes["height"]
    assert (c[low, 0] > c[low, 2]).all() and (c[high, 1] > c[high, 0]).all() and (c[high, 1] > c[high, 2]).all()


@settings(max_examples=10, deadline=None)
@given(st.tuples(st.floats(-1e6, 1e6), st.floats(-1e6, 1e6), st.floats(-100, 3000)))
def test_where_a_scan_was_taken_does_not_change_its_model(shift):
    cloud = _synthetic(12.0, 6.0, n=600, seed=2)
    moved = PointCloud(cloud.positions + np.array(shift))
    a, b = scan_tree_model(cloud, "a", "a"), scan_tree_model(moved, "b", "b")
    assert np.allclose(a.points.positions, b.points.positions, atol=1e-6)


def test_a_scan_s_prefixes_cover_it(tree13):
    pm = point_model(tree13, n_points=4096)
    assert len(pm) == 4096
    assert (np.diff(pm.radius) <= 1e-12).all()
    assert pm.radius[-1] >= tree13.attributes["spacing"]
    every = cKDTree(tree13.points.positions)
    for n in (1, 8, 64, 512, 4096):
        reach = cKDTree(pm.positions[:n]).query(tree13.points.positions)[0].max()
        assert reach <= pm.radius[n - 1] + 1e-9, n
    # The prefix is the scan's own points, not resampled ones.
    assert (every.query(pm.positions)[0] == 0).all()
    # Whole: every point kept when the budget allows it.
    assert len(point_model(tree13, n_points=10_000)) == len(tree13.points)


def test_a_huge_scan_is_thinned_evenly():
    cloud = _synthetic(20.0, 10.0, n=60_000, seed=3)
    m = scan_tree_model(cloud, "big", "big", max_points=5000)
    n = len(m.points)
    assert 4000 <= n <= 5000 and m.attributes["scan_points"] == 60_000
    assert m.attributes["height"] == pytest.approx(20.0, rel=0.05)
    # Even: no point of the scan is far from a kept one.
    gap = cKDTree(m.points.positions + m.attributes["offset"]).query(cloud.positions)[0].max()
    assert gap < 1.5


def test_normals_point_out_of_the_crown():
    m = scan_tree_model(_synthetic(12.0, 8.0, n=4000, seed=4), "s", "s")
    p, nrm = m.points.positions, m.points.normals
    crown = p[:, 2] > 0.75 * 12.0  # upper crown: outward is away from its centre
    out = p[crown] - [0, 0, 0.7 * 12.0]
    assert (np.einsum("ij,ij->i", nrm[crown], out) > 0).mean() > 0.95


def _forest(models) -> SourceScene:
    k = 40
    rng = np.random.default_rng(5)
    m = np.tile(np.eye(4), (k, 1, 1))
    yaw = rng.uniform(0, 2 * np.pi, k)
    s = rng.uniform(0.8, 1.2, k)
    m[:, 0, 0] = m[:, 1, 1] = np.cos(yaw) * s
    m[:, 0, 1], m[:, 1, 0] = -np.sin(yaw) * s, np.sin(yaw) * s
    m[:, 2, 2] = s
    m[:, :3, 3] = rng.uniform(-100, 100, (k, 3))
    return SourceScene(tree_models=models, trees=TreeInstances(np.arange(k) % 2, m), sources=["forest"])


def test_scans_replace_generated_trees_by_shape_keeping_foot_yaw_and_height():
    scene = _forest([conifer(1), broadleaf(2)])
    old = scene.trees.matrix.copy()
    heights = np.array([np.ptp(t.mesh.positions[:, 2]) for t in scene.tree_models])[scene.trees.model] * old[:, 2, 2]
    was = scene.trees.model.copy()
    slender = scan_tree_model(_synthetic(20.0, 4.0, seed=6), "slender", "slender.xyz")
    round_ = scan_tree_model(_synthetic(10.0, 10.0, seed=7), "round", "round.xyz")
    assert use_tree_models(scene, [round_, slender]) == 40
    names = [m.name for m in scene.tree_models]
    assert sorted(names) == ["round", "slender"]
    got = np.array([names[i] for i in scene.trees.model])
    assert (got[was == 0] == "slender").all() and (got[was == 1] == "round").all()  # conifers are the slender ones
    m = scene.trees.matrix
    scan_h = np.array([scene.tree_models[i].attributes["height"] for i in scene.trees.model])
    assert np.allclose(m[:, 2, 2] * scan_h, heights)  # every tree keeps its height
    assert np.allclose(m[:, :3, 3], old[:, :3, 3])  # and its foot
    assert np.allclose(np.arctan2(m[:, 1, 0], m[:, 0, 0]), np.arctan2(old[:, 1, 0], old[:, 0, 0]))  # and its yaw
    assert np.allclose(m[:, 0, 0] ** 2 + m[:, 1, 0] ** 2, m[:, 2, 2] ** 2)  # uniform scale: proportions kept
    scene.check()


def test_every_scan_is_used_when_trees_are_many():
    scene = _forest([broadleaf(3)])
    scene.trees.model[:] = 0
    scans = [scan_tree_model(_synthetic(10.0 + i, 6.0, n=500, seed=i), f"s{i}", f"s{i}") for i in range(3)]
    use_tree_models(scene, scans)
    assert sorted(np.bincount(scene.trees.model).tolist()) == [13, 13, 14]


def test_a_scene_without_trees_refuses_tree_models(tree13):
    scene = SourceScene(sources=["city.json"])
    with pytest.raises(SourceError, match="city.json: it has no trees"):
        use_tree_models(scene, [tree13])


_GML = """<?xml version="1.0" encoding="UTF-8"?>
<core:CityModel xmlns:core="http://www.opengis.net/citygml/2.0" xmlns:veg="http://www.opengis.net/citygml/vegetation/2.0"
 xmlns:gml="http://www.opengis.net/gml" xmlns:gen="http://www.opengis.net/citygml/generics/2.0"
 xmlns:xlink="http://www.w3.org/1999/xlink">
 <core:cityObjectMember><veg:SolitaryVegetationObject gml:id="oak">
  {attribute}
  <veg:height uom="m">{height}</veg:height>
  <veg:lod2ImplicitRepresentation><core:ImplicitGeometry>
   <core:transformationMatrix>3 0 0 0 0 3 0 0 0 0 {height} 0 0 0 0 1</core:transformationMatrix>
   <core:relativeGMLGeometry><gml:MultiSurface gml:id="proto"><gml:surfaceMember><gml:Polygon><gml:exterior>
    <gml:LinearRing><gml:posList>-0.5 0 0 0.5 0 0 0 0 1 -0.5 0 0</gml:posList></gml:LinearRing>
   </gml:exterior></gml:Polygon></gml:surfaceMember></gml:MultiSurface></core:relativeGMLGeometry>
   <core:referencePoint><gml:Point><gml:pos>1000 2000 30</gml:pos></gml:Point></core:referencePoint>
  </core:ImplicitGeometry></veg:lod2ImplicitRepresentation>
 </veg:SolitaryVegetationObject></core:cityObjectMember>
 <core:cityObjectMember><veg:SolitaryVegetationObject gml:id="lime">
  <veg:lod2ImplicitRepresentation><core:ImplicitGeometry>
   <core:transformationMatrix>2 0 0 0 0 2 0 0 0 0 6 0 0 0 0 1</core:transformationMatrix>
   <core:relativeGMLGeometry xlink:href="#proto"/>
   <core:referencePoint><gml:Point><gml:pos>1010 2000 30</gml:pos></gml:Point></core:referencePoint>
  </core:ImplicitGeometry></veg:lod2ImplicitRepresentation>
 </veg:SolitaryVegetationObject></core:cityObjectMember>
</core:CityModel>
"""


def test_a_citygml_tree_names_its_scan(tmp_path):
    (tmp_path / "scans").mkdir()
    (tmp_path / "scans" / "oak.xyz").write_text(data_file("trees/ahn3_delft.xyz").read_text())
    attribute = '<gen:stringAttribute name="tree_model"><gen:value>scans/oak.xyz</gen:value></gen:stringAttribute>'
    gml = tmp_path / "trees.gml"
    gml.write_text(_GML.format(attribute=attribute, height=9.5))
    scene = load_source(gml)
    assert scene.trees.model_file == ["scans/oak.xyz", None]
    with_tree_models(scene, [], gml.parent)
    names = [scene.tree_models[i].name for i in scene.trees.model]
    assert names == ["oak", "proto"]  # the other tree keeps its prototype
    oak = scene.tree_models[scene.trees.model[0]]
    assert oak.attributes["source"] == str(tmp_path / "scans" / "oak.xyz")
    m = scene.trees.matrix[0]
    assert m[2, 2] * oak.attributes["height"] == pytest.approx(9.5)
    assert np.allclose(m[:3, 3], [1000, 2000, 30])
    # Named but missing: the error names the file.
    gml.write_text(_GML.format(attribute=attribute.replace("oak.xyz", "elm.xyz"), height=9.5))
    with pytest.raises(SourceError, match="'scans/elm.xyz', which is not a file"):
        with_tree_models(load_source(gml), [], gml.parent)


def test_cityjson_vegetation_objects_become_scanned_trees(tmp_path, tree13):
    box = [[[0, 1, 2, 3]], [[4, 7, 6, 5]], [[0, 4, 5, 1]], [[1, 5, 6, 2]], [[2, 6, 7, 3]], [[3, 7, 4, 0]]]

    def cube(base: int) -> list:
        return [[[i + base for i in ring] for ring in face] for face in box]

    corners = [[0, 0, 0], [2, 0, 0], [2, 2, 0], [0, 2, 0], [0, 0, 8], [2, 0, 8], [2, 2, 8], [0, 2, 8]]
    doc = {
        "type": "CityJSON", "version": "2.0", "transform": {"scale": [1, 1, 1], "translate": [500, 600, 10]},
        "vertices": corners + [[x + 20, y, z] for x, y, z in corners] + [[x + 40, y, z * 2] for x, y, z in corners],
        "CityObjects": {
            "house": {"type": "Building", "geometry": [{"type": "MultiSurface", "lod": "1", "boundaries": cube(0)}]},
            "named": {"type": "SolitaryVegetationObject", "attributes": {"tree_model": str(data_file("trees/tree13.xyz"))},
                      "geometry": [{"type": "MultiSurface", "lod": "1", "boundaries": cube(8)}]},
            "plain": {"type": "SolitaryVegetationObject",
                      "geometry": [{"type": "MultiSurface", "lod": "1", "boundaries": cube(16)}]},
        },
    }
    f = tmp_path / "trees.city.json"
    f.write_text(json.dumps(doc))
    scene = with_tree_models(load_source(f), [], f.parent)  # only the tree that names a scan changes
    assert [o.name for o in scene.objects] == ["house", "plain"]
    assert len(scene.trees) == 1 and scene.trees.names == ["named"]
    m = scene.trees.matrix[0]
    assert np.allclose(m[:3, 3], [521, 601, 10]) and m[2, 2] * tree13.attributes["height"] == pytest.approx(8.0)
    scene = with_tree_models(load_source(f), [data_file("trees/ahn3_delft.xyz")], f.parent)  # now every tree does
    assert [o.name for o in scene.objects] == ["house"]
    assert scene.trees.names == ["named", "plain"]
    assert [scene.tree_models[i].name for i in scene.trees.model] == ["tree13", "ahn3_delft"]
    plain = scene.tree_models[scene.trees.model[1]]
    assert scene.trees.matrix[1, 2, 2] * plain.attributes["height"] == pytest.approx(16.0)
    assert Path(plain.attributes["source"]).name == "ahn3_delft.xyz"


def test_inspect_names_where_each_model_came_from(tree13, tmp_path):
    from server.scene.scans import model_source

    assert model_source(conifer(4)) == "generated (conifer, seed 4)"
    assert model_source(tree13).endswith("tree13.xyz")
    gml = tmp_path / "t.gml"
    gml.write_text(_GML.format(attribute="", height=7))
    assert model_source(load_source(gml).tree_models[0]) == "prototype proto"
