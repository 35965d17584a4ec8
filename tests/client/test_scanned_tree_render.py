"""A scanned tree, built into a store and drawn by the real client renderer (EGL): its splats cover its points' silhouette."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import ndimage

from client.renderer import Renderer
from client.splats import SIZE_RANGE, SplatLayer
from proto.camera import projection_matrix, view_matrix
from proto.points import decode_instances, decode_points
from server.scene.catalog import build_path
from server.scene.data import data_file
from server.scene.index import TREES
from server.scene.store import SceneStore

W, H, FOV, NEAR, FAR = 320, 240, 60.0, 0.5, 500.0
HEIGHT = 12.0

_GML = """<?xml version="1.0" encoding="UTF-8"?>
<core:CityModel xmlns:core="http://www.opengis.net/citygml/2.0" xmlns:veg="http://www.opengis.net/citygml/vegetation/2.0"
 xmlns:gml="http://www.opengis.net/gml" xmlns:gen="http://www.opengis.net/citygml/generics/2.0">
 <core:cityObjectMember><veg:SolitaryVegetationObject gml:id="scanned">
  <gen:stringAttribute name="tree_model"><gen:value>{scan}</gen:value></gen:stringAttribute>
  <veg:lod2ImplicitRepresentation><core:ImplicitGeometry>
   <core:transformationMatrix>0.8 -0.6 0 0 0.6 0.8 0 0 0 0 {height} 0 0 0 0 1</core:transformationMatrix>
   <core:relativeGMLGeometry><gml:MultiSurface gml:id="stick"><gml:surfaceMember><gml:Polygon><gml:exterior>
    <gml:LinearRing><gml:posList>-0.1 0 0 0.1 0 0 0 0 1 -0.1 0 0</gml:posList></gml:LinearRing>
   </gml:exterior></gml:Polygon></gml:surfaceMember></gml:MultiSurface></core:relativeGMLGeometry>
   <core:referencePoint><gml:Point><gml:pos>396900 5819500 40</gml:pos></gml:Point></core:referencePoint>
  </core:ImplicitGeometry></veg:lod2ImplicitRepresentation>
 </veg:SolitaryVegetationObject></core:cityObjectMember>
</core:CityModel>
"""


@pytest.fixture(scope="module")
def scanned(tmp_path_factory):
    """The store's one tree model (tree13, named by the tree's tree_model attribute) and its instance list."""
    folder = tmp_path_factory.mktemp("scanned")
    gml = folder / "tree.gml"
    gml.write_text(_GML.format(scan=data_file("trees/tree13.xyz"), height=HEIGHT))
    store = folder / "tree.db"
    build_path(gml, store)
    with SceneStore.open(store) as s:
        idx = s.index
        group = int(np.flatnonzero(idx.object_kind == TREES)[0])
        rep = int(idx.rep_first[group])
        points = decode_points(s.model_geometries([0])[0])
        instances = decode_instances(s.geometries([rep])[0], 1)
    return rep, points, instances


@pytest.fixture(scope="module")
def renderer():
    r = Renderer(W, H, fov_y=FOV, backend="egl")
    yield r
    r.release()


def test_a_scanned_tree_covers_where_its_points_project(scanned, renderer):
    rep, points, instances = scanned
    m = instances.matrix[0].astype(np.float64)
    world = points.positions.astype(np.float64) @ m[:3, :3].T + m[:3, 3]
    assert np.ptp(world[:, 2]) == pytest.approx(HEIGHT, rel=0.02)  # the scan, scaled to the tree's height
    foot = m[:3, 3]
    distance = (HEIGHT / 2) / math.tan(math.radians(FOV / 2)) / 0.7  # the tree fills 70 % of the frame's height
    eye = foot + np.array([0.0, -distance, HEIGHT / 2])
    forward, up = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])

    layer = SplatLayer(renderer.ctx)
    try:
        layer.add_model(0, points)
        layer.add_group(rep, instances)
        layer.set_resolutions(np.array([rep]), np.array([1.0]))
        empty = np.zeros(0, np.int64)
        renderer.draw(empty, eye, forward, up, NEAR, FAR)
        background = renderer.read_image()
        stats = renderer.draw(empty, eye, forward, up, NEAR, FAR, layers=[layer])
        image = renderer.read_image()
    finally:
        layer.release()
    assert stats.splats == len(points)

    vp = projection_matrix(FOV, W / H, NEAR, FAR) @ view_matrix(eye, forward, up)
    clip = np.c_[world, np.ones(len(world))] @ vp.T
    ndc = clip[:, :3] / clip[:, 3:]
    assert (np.abs(ndc[:, :2]) < 0.95).all()  # the whole tree is in view, as placed
    px = np.floor((ndc[:, 0] + 1) / 2 * W).astype(int)
    py = np.floor((1 - ndc[:, 1]) / 2 * H).astype(int)
    changed = np.abs(image.astype(int) - background.astype(int)).max(axis=2) > 0
    assert changed[py, px].mean() > 0.95  # the points' pixels are covered

    # Far from every point (beyond the largest splat), the frame is the background it was without the tree.
    scale = float(np.cbrt(abs(np.linalg.det(m[:3, :3]))))
    pixel_scale = H / math.tan(math.radians(FOV / 2))
    diameter = np.clip(float(points.radius[-1]) * scale * pixel_scale / clip[:, 3], *SIZE_RANGE)
    projected = np.zeros((H, W), bool)
    projected[py, px] = True
    far = ndimage.distance_transform_edt(~projected) > diameter.max() / 2 + 2
    assert far.mean() > 0.5 and not changed[far].any()
    assert changed.sum() > 0.02 * W * H
    # Foliage green above, over the sky-blue background.
    top = changed & (np.arange(H)[:, None] < np.percentile(py, 30))
    colour = image[top].astype(float).mean(axis=0)
    assert colour[1] > colour[2] and colour[1] > colour[0]
