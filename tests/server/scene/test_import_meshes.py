"""glTF / GLB / OBJ / PLY import through trimesh: nodes, transforms, up axis, errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from trimesh.transformations import rotation_matrix, scale_matrix, translation_matrix

from server.scene.importers import load_source
from server.scene.importers.meshes import Y_UP_TO_Z_UP, load_mesh_file
from server.scene.source import SourceError


def _volume(mesh) -> float:
    t = mesh.positions[mesh.faces] - mesh.positions.mean(axis=0)
    return float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6)


def _scene() -> trimesh.Scene:
    """Three nodes in glTF's y-up frame: two instances of one box (one rotated), a sphere, a mirrored box."""
    s = trimesh.Scene()
    box = trimesh.creation.box(extents=(1, 2, 3))
    s.add_geometry(box, node_name="chair_01", geom_name="box", transform=translation_matrix([10, 0, 0]))
    s.add_geometry(box, node_name="chair_02", geom_name="box",
                   transform=translation_matrix([0, 0, 7]) @ rotation_matrix(np.pi / 2, [0, 1, 0]))
    s.add_geometry(trimesh.creation.icosphere(subdivisions=1), node_name="lamp", geom_name="sphere",
                   transform=translation_matrix([0, 5, 0]))
    s.add_geometry(box, node_name="Mirror.001", geom_name="box",
                   transform=translation_matrix([-4, 0, 0]) @ scale_matrix(-1, direction=[1, 0, 0]))
    return s


@pytest.fixture(params=["glb", "gltf"])
def gltf_file(request, tmp_path) -> Path:
    path = tmp_path / f"room.{request.param}"
    _scene().export(path)
    return path


def test_gltf_nodes_transforms_and_up_axis(gltf_file):
    scene = load_source(gltf_file)
    assert scene.sources == [str(gltf_file)] and scene.crs is None
    objects = {o.name: o for o in scene.objects}
    assert sorted(objects) == ["Mirror.001", "chair_01", "chair_02", "lamp"]
    assert objects["chair_01"].cls == "chair" and objects["lamp"].cls == "lamp"
    assert objects["Mirror.001"].cls == "mirror"
    box = objects["chair_01"].levels[0]
    assert box.n_faces == 12 and box.n_vertices == 8
    # y-up (10, 0, 0) ± (0.5, 1, 1.5) → z-up: x stays, y → z, z → −y.
    assert box.positions.min(axis=0) == pytest.approx([9.5, -1.5, -1])
    assert box.positions.max(axis=0) == pytest.approx([10.5, 1.5, 1])
    # Rotated 90° about y-up, then moved +7 along glTF z (→ −7 along walkstream y): extents swap x ↔ z(gltf).
    rotated = objects["chair_02"].levels[0].positions
    assert rotated.min(axis=0) == pytest.approx([-1.5, -7.5, -1])
    assert rotated.max(axis=0) == pytest.approx([1.5, -6.5, 1])
    assert objects["lamp"].levels[0].positions.mean(axis=0) == pytest.approx([0, 0, 5], abs=1e-6)
    # Every mesh, the mirrored one included, stays outward-facing.
    for o in scene.objects:
        assert _volume(o.levels[0]) > 0, o.name
    assert _volume(objects["chair_01"].levels[0]) == pytest.approx(6)


def test_y_up_rotation_is_proper():
    r = Y_UP_TO_Z_UP[:3, :3]
    assert np.linalg.det(r) == pytest.approx(1)
    assert r @ [0, 1, 0] == pytest.approx([0, 0, 1]) and r @ [0, 0, 1] == pytest.approx([0, -1, 0])


def test_ply_single_mesh_keeps_z_up(tmp_path):
    path = tmp_path / "statue.ply"
    mesh = trimesh.creation.box(extents=(1, 2, 3))
    mesh.apply_translation([0, 0, 1.5])
    mesh.export(path)
    (obj,) = load_mesh_file(path).objects
    assert obj.name == "statue" and obj.cls == "statue"
    assert obj.levels[0].positions.max(axis=0) == pytest.approx([0.5, 1, 3])  # no up-axis change
    assert obj.levels[0].n_faces == 12


def test_obj_exported_scene_and_objects_split(tmp_path):
    path = tmp_path / "room.obj"
    _scene().export(path)
    scene = load_mesh_file(path)
    assert sum(m.n_faces for o in scene.objects for m in o.levels) == 12 * 3 + 80
    assert all(o.attributes["format"] == "obj" for o in scene.objects)
    two = tmp_path / "two.obj"
    two.write_text("o table_1\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n"
                   "o lamp\nv 0 0 2\nv 1 0 2\nv 0 1 2\nf 5 6 7\n")
    objects = {o.name: o for o in load_source(two).objects}
    assert sorted(objects) == ["lamp", "table_1"]
    assert objects["table_1"].cls == "table" and objects["table_1"].levels[0].n_faces == 2
    assert objects["lamp"].levels[0].positions[:, 2] == pytest.approx([2, 2, 2])  # OBJ is taken as z-up


_PLY = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n{v}\n3 {f}\n")


@pytest.mark.parametrize("name, text, expected", [
    ("nan.ply", _PLY.format(v="0 0 0\n1 0 nan\n0 1 0", f="0 1 2"), r"node 'nan\.ply'.*vertex 1 .*not finite"),
    ("range.ply", _PLY.format(v="0 0 0\n1 0 0\n0 1 0", f="0 1 7"), r"face 0 = \[0, 1, 7\].*3 vertices"),
    ("garbage.glb", "not a glb at all", r"garbage\.glb: cannot read as GLB"),
    ("points.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n", r"points\.obj: no triangle geometry"),
])
def test_errors_name_the_file_and_node(tmp_path, name, text, expected):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(SourceError, match=expected) as err:
        load_source(path)
    assert str(path) in str(err.value)


def test_missing_file(tmp_path):
    with pytest.raises(SourceError, match=r"absent\.glb: file not found"):
        load_source(tmp_path / "absent.glb")
