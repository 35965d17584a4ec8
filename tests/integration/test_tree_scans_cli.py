"""``walkstream build --tree-model`` and ``inspect`` as a user runs them, on the shared Berlin trees and scans."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from proto.points import decode_instances, decode_points
from server.scene.catalog import load_tree_model
from server.scene.data import data_file
from server.scene.importers import load_source
from server.scene.importers.pointcloud import read_xyz
from server.scene.index import TREES
from server.scene.points import point_model
from server.scene.store import SceneStore


def _walkstream(*args: str, timeout: float = 240) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "walkstream", *args], capture_output=True, text=True, timeout=timeout)


def test_build_with_tree_models_draws_the_scans(tmp_path):
    tree13, ahn3 = data_file("trees/tree13.xyz"), data_file("trees/ahn3_delft.xyz")
    out = tmp_path / "berlin.db"
    done = _walkstream("build", str(data_file("trees/berlin_trees.gml")), "-o", str(out), "-q",
                       "--tree-model", str(tree13), "--tree-model", str(ahn3))
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout.strip().splitlines()[-1])["tree_instances"] == 288
    with SceneStore.open(out) as store:
        idx = store.index
        assert idx.model_points.shape[0] == 2
        stored = [decode_points(b) for b in store.model_geometries([0, 1])]
        groups = np.flatnonzero(idx.object_kind == TREES)
        reps = idx.rep_first[groups]
        instances = [decode_instances(b, 2) for b in store.geometries(reps)]
    # The stored models are the scans' prefix-ordered points (to the payload's 16-bit quantization).
    for points, path in zip(stored, (tree13, ahn3)):
        expected = point_model(load_tree_model(path), n_points=4096)
        assert len(points) == len(expected)
        step = (expected.hi - expected.lo) / 65535
        assert (np.abs(points.positions - expected.positions) <= step + 1e-4).all()
    used = np.concatenate([i.model for i in instances])
    assert used.size == 288 and set(used.tolist()) == {0, 1}
    scan_height = np.array([np.ptp(read_xyz(path).positions[:, 2]) for path in (tree13, ahn3)])
    heights = np.concatenate([i.matrix[:, 2, 2] for i in instances]) * scan_height[used]
    # Every tree keeps its height: the file's veg:height (the prototypes are 1 m tall, two 0.4 % more).
    source = load_source(data_file("trees/berlin_trees.gml"))
    measured = [h for m in source.tree_models for h in m.attributes["instances"]["height"]]
    assert np.allclose(np.sort(heights), np.sort(measured), rtol=5e-3)

    done = _walkstream("inspect", str(out), "--json")
    report = json.loads(done.stdout)
    assert [(m["name"], m["source"], m["points"]) for m in report["tree_model_sources"]] == [
        ("tree13", str(tree13), 4096), ("ahn3_delft", str(ahn3), 2488)]
    text = _walkstream("inspect", str(out)).stdout
    assert f"model 0: tree13  4096 points  from {tree13}" in text and "ahn3_delft" in text


def test_a_malformed_scan_fails_in_one_line_and_leaves_nothing(tmp_path):
    gml = str(data_file("trees/berlin_trees.gml"))
    out = tmp_path / "store" / "x.db"
    bad = tmp_path / "bad.xyz"
    for body, needle in (("1 2 3\n4 5 nan\n", "bad.xyz: line 2: '4 5 nan' is not finite"),
                         ("1 2 3\n4 5 6\n7 8\n", "bad.xyz: line 3: 2 columns, expected 3"),
                         ("", "bad.xyz: no points")):
        bad.write_text(body)
        done = _walkstream("build", gml, "-o", str(out), "--tree-model", str(bad), "-q")
        assert done.returncode == 2 and needle in done.stderr, done.stderr
        assert len(done.stderr.strip().splitlines()) == 1 and "Traceback" not in done.stderr
        assert not out.exists() and not list(out.parent.glob("*"))  # no store, no temporary file
    truncated = tmp_path / "cut.ply"
    truncated.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\n"
                          b"property float y\nproperty float z\nend_header\n" + bytes(12 * 7 + 5))
    done = _walkstream("build", gml, "-o", str(out), "--tree-model", str(truncated), "-q")
    assert done.returncode == 2 and "cut.ply: truncated" in done.stderr and "vertex 8" in done.stderr
    done = _walkstream("build", "demo", "-o", str(out), "--tree-model", str(data_file("trees/tree13.xyz")), "-q")
    assert done.returncode == 2 and "no trees" in done.stderr and not out.exists()
    done = _walkstream("build", gml, "-o", str(out), "--tree-model", str(tmp_path / "none.las"), "-q")
    said = " ".join(done.stderr.replace("│", " ").split())
    assert done.returncode == 2 and "--tree-model" in said and "is not a file" in said
    assert not Path(out).exists()
