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

ROOT = Path(__file__).resolve().parents[2]


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


# ----------------------------------------------------------------------------- budget, digest, tree groups

from proto.manifest import digest  # noqa: E402
from proto.messages import ModelAdd  # noqa: E402
from proto.points import encode_instances, encode_points  # noqa: E402


def _held_ids(cache: ResidentCache) -> np.ndarray:
    return np.asarray(sorted(cache.resident) + sorted(cache.groups), np.int64)


def _consistent(cache: ResidentCache) -> None:
    """held, held_bytes and digest describe exactly what is held (the ack's numbers)."""
    ids = _held_ids(cache)
    assert cache.held == len(cache) == ids.size
    assert cache.digest == digest(ids)
    assert cache.holds(ids).all()


def test_over_budget_adds_are_refused_never_evicting() -> None:
    (g0, _, _), (g1, _, _), (g2, _, _) = _payload(0), _payload(1), _payload(2)
    cache = ResidentCache(budget_bytes=len(g0) + len(g1))
    ch = cache.apply(Delta(seq=0, t0=0, t1=0.5, add=[_add(1, 1, 0, g0), _add(2, 2, 0, g1), _add(3, 3, 0, g2)],
                           selection=[1, 2, 3]))
    assert ch.rejected == [3] and cache.last_rejected == [3] and cache.refused_full == 1
    assert cache.rejected == []  # a refusal for room is no bad payload
    assert cache.held_bytes == len(g0) + len(g1) and 3 not in cache and cache.selection.tolist() == [1, 2]
    _consistent(cache)
    # Nothing held is ever evicted to make room: the server decides that.
    ch = cache.apply(Delta(seq=1, t0=0.5, t1=1, add=[_add(4, 4, 0, g0)], selection=[1, 2, 4]))
    assert ch.rejected == [4] and sorted(cache.resident) == [1, 2] and cache.refused_full == 2
    _consistent(cache)


def test_a_deltas_drops_make_room_for_its_adds() -> None:
    (g0, _, _), (g1, _, _) = _payload(1), _payload(1)
    cache = ResidentCache(budget_bytes=len(g0) + 10)
    cache.apply(Delta(seq=0, t0=0, t1=0.5, add=[_add(1, 1, 0, g0)], selection=[1]))
    up, free = cache.apply(Delta(seq=1, t0=0.5, t1=1, add=[_add(2, 2, 0, g1)], drop=[1], selection=[2]))
    assert [r for r, _ in up] == [2] and free == [1] and cache.held_bytes == len(g1) and cache.last_rejected == []
    _consistent(cache)


def test_digest_bytes_and_count_follow_every_change() -> None:
    payloads = [_payload(k % 3)[0] for k in range(8)]
    cache = ResidentCache()
    cache.apply(Delta(seq=0, t0=0, t1=0.5, add=[_add(r, r, 0, payloads[r]) for r in range(6)], selection=[]))
    _consistent(cache)
    assert cache.held_bytes == sum(len(p) for p in payloads[:6])
    cache.apply(Delta(seq=1, t0=0.5, t1=1, add=[_add(6, 6, 0, payloads[6]), _add(2, 2, 0, payloads[1])],
                      drop=[0, 5, 99], selection=[]))  # a replacement, adds, drops and an unknown drop
    _consistent(cache)
    assert cache.held_bytes == sum(len(payloads[r]) for r in (1, 3, 4, 6)) + len(payloads[1])
    assert cache.discard(3) and not cache.discard(3)
    _consistent(cache)
    assert cache.digest == digest(np.asarray([1, 2, 4, 6]))


def test_tree_groups_and_models_decode_for_the_splat_layer() -> None:
    rng = np.random.default_rng(0)
    pts = encode_points(positions=rng.random((50, 3)), normals=rng.normal(size=(50, 3)),
                        colors=rng.integers(0, 255, (50, 3)).astype(np.uint8), radius=np.full(50, 0.1))
    matrices = np.repeat(np.eye(4)[None], 3, axis=0)
    group = encode_instances(np.array([0, 1, 1]), matrices)
    stray = encode_instances(np.array([0, 7]), matrices[:2])  # names a model the client never got
    mesh, _, _ = _payload(0)
    cache = ResidentCache()
    ch = cache.apply(Delta(
        seq=0, t0=0, t1=0.5, models=[ModelAdd(model=0, points=pts), ModelAdd(model=1, points=pts)],
        add=[_add(5, 5, 0, mesh), RepresentationAdd(rep=9, object=9, level=0, geometry=group, kind="trees"),
             RepresentationAdd(rep=10, object=10, level=0, geometry=stray, kind="trees"),
             RepresentationAdd(rep=11, object=11, level=0, geometry=mesh, kind="trees")],  # a mesh is no group
        selection=[5], vegetation=[9], resolution=[0.5],
    ))
    assert [m for m, _ in ch.models] == [0, 1] and len(ch.models[0][1]) == 50 and sorted(cache.models) == [0, 1]
    assert [r for r, _ in ch.groups] == [9] and len(ch.groups[0][1]) == 3 and cache.groups[9].instances == 3
    assert [r for r, _ in ch.uploads] == [5] and sorted(ch.rejected) == [10, 11]
    assert cache.held_bytes == len(mesh) + len(group) and 9 in cache
    _consistent(cache)
    ch = cache.apply(Delta(seq=1, t0=0.5, t1=1, drop=[9, 5], selection=[]))
    assert ch.group_frees == [9] and ch.frees == [5] and len(cache) == 0 and cache.digest == 0
