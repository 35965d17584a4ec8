"""Point-cloud readers: XYZ, PLY (ASCII and binary), LAS/LAZ — real scans, small files, malformed files."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from server.scene.data import data_file
from server.scene.importers.pointcloud import (
    read_las,
    read_ply,
    read_point_cloud,
    read_xyz,
)
from server.scene.source import SourceError


def _shared(name: str) -> Path:
    return data_file(f"trees/{name}")


def _fails(path: Path, *needles: str) -> str:
    with pytest.raises(SourceError) as err:
        read_point_cloud(path)
    message = str(err.value)
    assert message.startswith(str(path)) and "\n" not in message, message
    for needle in needles:
        assert needle in message, message
    return message


# -- the real scans -----------------------------------------------------------------------------


def test_the_shared_scans_read_every_line():
    tree13 = _shared("tree13.xyz")
    cloud = read_xyz(tree13)
    lines = [line.split() for line in tree13.read_text().splitlines() if line.strip()]
    assert len(cloud) == len(lines) and cloud.colors is None
    assert np.allclose(cloud.positions[0], [float(v) for v in lines[0]])
    assert np.allclose(cloud.positions[-1], [float(v) for v in lines[-1]])
    ahn = read_point_cloud(_shared("ahn3_delft.xyz"))
    assert len(ahn) == 2488 and np.isfinite(ahn.positions).all()
    assert np.ptp(ahn.positions[:, 2]) > 10  # a tree, metres tall


# -- XYZ ---------------------------------------------------------------------------------------


def test_xyz_with_colours_comments_and_blank_lines(tmp_path):
    f = tmp_path / "c.xyz"
    f.write_text("# x y z r g b\n1 2 3 255 0 10\n\n4 5 6 0 128 255\n")
    cloud = read_xyz(f)
    assert cloud.positions.tolist() == [[1, 2, 3], [4, 5, 6]]
    assert cloud.colors.tolist() == [[255, 0, 10], [0, 128, 255]]


@settings(max_examples=40, deadline=None)
@given(arrays(np.float64, st.tuples(st.integers(1, 40), st.just(3)),
              elements=st.floats(-1e7, 1e7, allow_nan=False, allow_infinity=False)))
def test_xyz_round_trips_exactly(tmp_path_factory, points):
    f = tmp_path_factory.mktemp("xyz") / "p.xyz"
    f.write_text("".join(" ".join(repr(float(v)) for v in row) + "\n" for row in points))
    assert np.array_equal(read_xyz(f).positions, points)


@pytest.mark.parametrize("body, line, needle", [
    ("1 2 3\n4 5 nan\n", 2, "not finite"),
    ("1 2 3\n4 5 inf\n", 2, "not finite"),
    ("1 2 3\n4 5 6\n7 8\n", 3, "2 columns, expected 3"),
    ("1 2 3 4\n", 1, "4 columns, expected 3 or 6"),
    ("1 2 3\n4 5 6 7 8 9\n", 2, "6 columns, expected 3"),
    ("# header\n1 2 3\n4 five 6\n", 3, "'five' is not a number"),
    ("1 2 3 0 0 300\n", 1, "outside 0..255"),
    ("1 2 3\n4 5", 2, "2 columns"),  # a file cut in its last line
])
def test_malformed_xyz_names_the_line(tmp_path, body, line, needle):
    f = tmp_path / "bad.xyz"
    f.write_text(body)
    _fails(f, f"line {line}:", needle)


def test_empty_and_non_text_xyz(tmp_path):
    empty = tmp_path / "empty.xyz"
    empty.write_text("")
    _fails(empty, "no points")
    only_comments = tmp_path / "comments.xyz"
    only_comments.write_text("# nothing\n\n")
    _fails(only_comments, "no points")
    binary = tmp_path / "binary.xyz"
    binary.write_bytes(b"1 2 3\n4 5 6\n\xff\xfe\x00\x01\n")
    _fails(binary, "line 3:", "not text")
    _fails(tmp_path / "missing.xyz", "no such file")
    _fails(tmp_path / "points.csv", "not a point-cloud file")


# -- PLY ---------------------------------------------------------------------------------------


def _ply(points: np.ndarray, colors: np.ndarray | None, encoding: str) -> bytes:
    rgba = None if colors is None else np.column_stack([colors, np.full(len(colors), 255)]).astype(np.uint8)
    return trimesh.exchange.ply.export_ply(trimesh.PointCloud(points, colors=rgba), encoding=encoding)


@pytest.mark.parametrize("encoding", ["ascii", "binary"])
def test_ply_points_and_colours(tmp_path, encoding):
    rng = np.random.default_rng(1)
    p = rng.uniform(-5, 5, (50, 3)).astype(np.float32).astype(np.float64)
    c = rng.integers(0, 256, (50, 3)).astype(np.uint8)
    f = tmp_path / "p.ply"
    f.write_bytes(_ply(p, c, encoding))
    cloud = read_ply(f)
    assert np.allclose(cloud.positions, p, atol=1e-6) and np.array_equal(cloud.colors, c)


def test_ply_normals_and_a_mesh_s_vertices(tmp_path):
    f = tmp_path / "n.ply"
    f.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                 "property float nx\nproperty float ny\nproperty float nz\nelement face 1\n"
                 "property list uchar int vertex_indices\nend_header\n"
                 "0 0 0 0 0 2\n1 0 0 0 3 0\n0 1 0 4 0 0\n3 0 1 2\n")
    cloud = read_ply(f)
    assert cloud.positions.tolist() == [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
    assert cloud.normals.tolist() == [[0, 0, 1], [0, 1, 0], [1, 0, 0]]  # normalised


_HEADER = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n"


@pytest.mark.parametrize("body, line, needle", [
    ("0 0 0\n1 nan 0\n2 2 2\n", 9, "not finite"),
    ("0 0 0\n1 1\n2 2 2\n", 9, "2 columns, expected 3"),
    ("0 0 0\n1 1 1 1\n2 2 2\n", 9, "4 columns, expected 3"),
    ("0 0 0\n1 1 1\n", 9, "truncated"),
])
def test_malformed_ascii_ply_names_the_line(tmp_path, body, line, needle):
    f = tmp_path / "bad.ply"
    f.write_text(_HEADER + body)
    _fails(f, f"line {line}:", needle)


def test_malformed_ply_headers_and_binary_bodies(tmp_path):
    f = tmp_path / "bad.ply"
    f.write_text("plx\n")
    _fails(f, "line 1:", "not a PLY file")
    f.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n")
    _fails(f, "end_header")
    f.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty wobbly y\nend_header\n1 2\n")
    _fails(f, "line 5:", "not a PLY header line")
    f.write_text(_HEADER.replace("vertex 3", "vertex 0"))
    _fails(f, "no points")
    f.write_bytes(b"")
    _fails(f, "no points")
    p = np.random.default_rng(2).uniform(0, 1, (40, 3))
    whole = _ply(p, None, "binary")
    f.write_bytes(whole[:-30])
    _fails(f, "truncated", "40 vertices", "vertex 38")
    p[7, 1] = np.nan
    f.write_bytes(_ply(p, None, "binary"))
    _fails(f, "vertex 8:", "not finite")


# -- LAS / LAZ ---------------------------------------------------------------------------------


def _las(path: Path, points: np.ndarray, classes: np.ndarray | None = None, rgb: np.ndarray | None = None) -> None:
    import laspy

    header = laspy.LasHeader(point_format=3 if rgb is not None else 1, version="1.2")
    header.scales = [0.001] * 3
    header.offsets = np.floor(points.min(axis=0))
    las = laspy.LasData(header)
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    if classes is not None:
        las.classification = classes
    if rgb is not None:
        las.red, las.green, las.blue = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    las.write(path)


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_points_colours_and_ground_left_out(tmp_path, suffix):
    rng = np.random.default_rng(3)
    p = rng.uniform(0, 10, (200, 3)) + [85_000.0, 446_000.0, 0.0]  # georeferenced, as a survey is
    classes = np.where(np.arange(200) % 10 == 0, 2, 1).astype(np.uint8)  # every tenth point is ground
    classes[5] = 7  # noise
    rgb = rng.integers(0, 65536, (200, 3)).astype(np.uint16)
    f = tmp_path / f"t{suffix}"
    _las(f, p, classes, rgb)
    cloud = read_point_cloud(f)
    keep = ~np.isin(classes, (2, 7))
    assert len(cloud) == keep.sum() == 179
    assert np.allclose(cloud.positions, p[keep], atol=1e-3)
    assert np.array_equal(cloud.colors, (rgb[keep] >> 8).astype(np.uint8))


def test_las_of_the_real_scan_keeps_its_points(tmp_path):
    p = read_xyz(_shared("ahn3_delft.xyz")).positions + [85_000.0, 446_000.0, 0.0]
    f = tmp_path / "ahn3.laz"
    _las(f, p)
    cloud = read_las(f)
    assert len(cloud) == 2488 and cloud.colors is None
    assert np.abs(cloud.positions - p).max() <= 0.0005 + 1e-9  # the file's millimetre scale


def test_malformed_las_and_laz(tmp_path):
    p = np.random.default_rng(4).uniform(0, 10, (100, 3))
    las, laz = tmp_path / "t.las", tmp_path / "t.laz"
    _las(las, p)
    _las(laz, p)
    whole = las.read_bytes()
    las.write_bytes(whole[: len(whole) - 50])
    stride = (len(whole) - 227) // 100  # LAS 1.2's header is 227 bytes
    message = _fails(las, "truncated", "100 points")
    assert int(re.search(r"point (\d+)", message.split("ends in")[1]).group(1)) == (100 * stride - 50) // stride + 1
    las.write_bytes(whole[:100])
    _fails(las, "not a readable LAS/LAZ file")
    las.write_bytes(b"")
    _fails(las, "no points")
    squeezed = laz.read_bytes()
    laz.write_bytes(squeezed[: len(squeezed) - 200])
    _fails(laz, "not a readable LAS/LAZ file")
    ground = tmp_path / "ground.las"
    _las(ground, p, np.full(100, 2, np.uint8))
    _fails(ground, "ground or noise")


def test_binary_ply_read_by_trimesh_matches_the_ascii_reading(tmp_path):
    """The two PLY paths agree on the same points (one is ours, one is trimesh's)."""
    p = np.random.default_rng(5).uniform(-1, 1, (30, 3)).astype(np.float32).astype(np.float64)
    a, b = tmp_path / "a.ply", tmp_path / "b.ply"
    a.write_bytes(_ply(p, None, "ascii"))
    b.write_bytes(_ply(p, None, "binary"))
    assert np.allclose(read_ply(a).positions, read_ply(b).positions, atol=1e-6)
