"""ResidentCache: adds before drops before selection, only resident reps selected, bad payloads isolated."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import msgpack
import numpy as np
import trimesh

from client.cache import ResidentCache
from proto.geometry import encode_geometry
from proto.messages import Delta, RepresentationAdd

ROOT = Path(__file__).resolve().parents[1]


def _payload(subdivisions: int) -> tuple[bytes, int, int]:
    mesh = trimesh.creation.icosphere(subdivisions)
    return encode_geometry(mesh.vertices, mesh.faces), len(mesh.faces), len(mesh.vertices)


def _add(rep: int, obj: int, level: int, geometry: bytes) -> RepresentationAdd:
    return RepresentationAdd(rep=rep, object=obj, level=level, geometry=geometry)


def test_cache_module_is_gl_free() -> None:
    code = "import sys, client.cache; sys.exit('moderngl' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], cwd=ROOT).returncode == 0


def test_apply_adds_drops_and_selects() -> None:
    (g0, f0, v0), (g1, f1, v1) = _payload(0), _payload(1)
    cache = ResidentCache()
    up, free = cache.apply(Delta(seq=0, t0=0, t1=0.5, add=[_add(10, 1, 0, g0), _add(11, 1, 1, g1)], selection=[11]))
    assert [rep for rep, _ in up] == [10, 11] and free == []
    assert up[1][1].faces == f1 and up[1][1].indices.shape == (f1, 3)
    assert cache.resident[10].object == 1 and cache.resident[11].level == 1
    assert cache.selection.tolist() == [11] and cache.seq == 0
    assert (cache.triangles, cache.vertices) == (f1, v1)

    up, free = cache.apply(Delta(seq=1, t0=0.5, t1=1.0, drop=[11, 99], selection=[10, 11]))
    assert up == [] and free == [11]  # unknown drop 99 ignored
    assert cache.selection.tolist() == [10] and cache.skipped == 1  # 11 no longer resident
    assert (cache.triangles, cache.vertices) == (f0, v0)
    assert 10 in cache and 11 not in cache and len(cache) == 1


def test_add_then_drop_in_one_delta_never_uploads() -> None:
    g0, _, _ = _payload(0)
    cache = ResidentCache()
    up, free = cache.apply(Delta(seq=0, t0=0, t1=0.5, add=[_add(1, 1, 0, g0)], drop=[1], selection=[1]))
    assert up == [] and free == [1] and cache.selection.size == 0 and cache.skipped == 1


def test_corrupt_payload_refused_rest_kept() -> None:
    good, faces, _ = _payload(1)
    doc = msgpack.unpackb(good, raw=False)
    doc["ib"] = doc["ib"][: len(doc["ib"]) // 2]  # truncated index buffer
    truncated = msgpack.packb(doc, use_bin_type=True)
    cache = ResidentCache()
    delta = Delta(
        seq=3, t0=0, t1=0.5,
        add=[_add(1, 1, 0, b"\xc1garbage"), _add(2, 2, 0, good), _add(3, 3, 0, truncated)],
        selection=[1, 2, 3],
    )
    up, _ = cache.apply(delta)
    assert [rep for rep, _ in up] == [2]
    assert [e.code for e in cache.rejected] == ["bad_geometry", "bad_geometry"]
    assert "rep 1" in cache.rejected[0].message and "rep 3" in cache.rejected[1].message
    assert cache.selection.tolist() == [2] and cache.skipped == 2 and cache.triangles == faces
    assert cache.selection.dtype == np.int64
