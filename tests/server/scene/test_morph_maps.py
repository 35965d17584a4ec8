"""Geomorph maps: collapse maps reproduce the coarser surface exactly, the nearest rule does not;
GPU order survives encoding; the morph-map codec round-trips and refuses defects."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from proto.errors import ProtocolError
from proto.geometry import MAX_VERTICES, decode_geometry, encode_geometry, order_for_gpu
from proto.morph import decode_morph, encode_morph
from server.scene.demo import build_object, generate_demo
from server.scene.lod import (
    Chain, build_chain, chain_from_levels, morph_faces_match, morph_positions, morph_surface_error,
    nearest_vertex_map,
)


def _bumpy_sphere(subdiv: int = 4, seed: int = 0, amount: float = 0.04) -> tuple[np.ndarray, np.ndarray]:
    m = trimesh.creation.icosphere(subdiv)
    v = m.vertices
    rng = np.random.default_rng(seed)
    a, b = rng.uniform(3, 11, 2)
    r = 1.0 + amount * np.sin(a * v[:, 0]) * np.cos(b * v[:, 1]) + amount / 2 * np.sin(23 * v[:, 2])
    return v * r[:, None], np.asarray(m.faces)


def _bumpy_grid(n: int, seed: int = 0, size: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """Open n × n heightfield with random bumps (an open border)."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, size, n + 1)
    x, y = np.meshgrid(t, t, indexing="ij")
    z = np.zeros_like(x)
    for cx, cy, h in rng.uniform([0, 0, -0.5], [size, size, 0.5], (4, 3)):
        z += h * np.exp(-((x - cx) ** 2 + (y - cy) ** 2))
    z += rng.normal(0, 0.005, z.shape)
    pos = np.stack([x.ravel(), y.ravel(), z.ravel()], -1)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a, b, c, d = i * (n + 1) + j, (i + 1) * (n + 1) + j, (i + 1) * (n + 1) + j + 1, i * (n + 1) + j + 1
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return pos, faces


def _rotated(faces: np.ndarray) -> np.ndarray:
    """Each face rotated to start at its least index (winding kept). meshopt's index codec
    may rotate a triangle's corners, never reorder triangles or vertices."""
    faces = np.asarray(faces, np.int64)
    r = np.argmin(faces, axis=1)
    return faces[np.arange(faces.shape[0])[:, None], (r[:, None] + np.arange(3)) % 3]


def _maps_are_valid(chain: Chain) -> None:
    assert chain.morph[0] is None
    assert len(chain.morph) == len(chain.levels)
    for k in range(1, len(chain.levels)):
        m = chain.morph[k]
        assert m.shape == (chain.vertices[k],) and np.issubdtype(m.dtype, np.integer)
        assert m.min() >= 0 and m.max() < chain.vertices[k - 1]


def _weight_zero_is_coarse(chain: Chain, k: int) -> bool:
    """The property in positions: fine faces at weight 0, less degenerate ones, are the coarse triangles."""
    (cp, cf), (fp, ff) = chain.levels[k - 1], chain.levels[k]
    moved = morph_positions(fp, cp, chain.morph[k], 0.0)
    tri = moved[ff]
    same = (tri[:, 0] == tri[:, 1]).all(1) | (tri[:, 1] == tri[:, 2]).all(1) | (tri[:, 0] == tri[:, 2]).all(1)

    def triangles(t: np.ndarray) -> set:
        # a triangle as its corners from the lexicographically least one, winding kept
        out = set()
        for corners in t.reshape(-1, 3, 3):
            rows = [tuple(c) for c in corners]
            r = rows.index(min(rows))
            out.add(tuple(rows[r:] + rows[:r]))
        return out

    return triangles(tri[~same]) == triangles(cp[cf])


# --------------------------------------------------------------------------- collapse versus nearest


@pytest.mark.parametrize("mesh", ["sphere", "grid"])
def test_collapse_maps_reproduce_the_coarser_level(mesh: str) -> None:
    pos, faces = _bumpy_sphere(4) if mesh == "sphere" else _bumpy_grid(40)
    chain = build_chain(pos, faces)
    assert len(chain) >= 3 and chain.morph_kind == "collapse"
    _maps_are_valid(chain)
    for k in range(1, len(chain)):
        assert morph_faces_match(chain, k), k
        assert _weight_zero_is_coarse(chain, k), k
        assert morph_surface_error(chain, k) == pytest.approx(0.0, abs=1e-9)


def test_nearest_rule_is_valid_but_not_exact() -> None:
    """Zach's rule gives valid maps whose weight-0 meshes leave the coarse surface (cut across it)."""
    pos, faces = _bumpy_sphere(4)
    nearest = build_chain(pos, faces, morph="nearest")
    collapse = build_chain(pos, faces)
    assert nearest.faces == collapse.faces  # the same levels, only the maps differ
    _maps_are_valid(nearest)
    assert nearest.morph_kind == "nearest"
    exact = [morph_faces_match(nearest, k) for k in range(1, len(nearest))]
    errors = [morph_surface_error(nearest, k) for k in range(1, len(nearest))]
    assert not all(exact)
    assert max(errors) > 0.005  # a sphere of radius ~1: visible
    finest = len(nearest) - 1
    assert not morph_faces_match(nearest, finest) and errors[-1] > 0.0


def test_nearest_vertex_map_matches_brute_force() -> None:
    rng = np.random.default_rng(1)
    fine, coarse = rng.normal(size=(500, 3)), rng.normal(size=(60, 3))
    m = nearest_vertex_map(fine, coarse)
    assert m.dtype == np.int64 and m.shape == (500,)
    brute = np.linalg.norm(fine[:, None] - coarse[None], axis=2).argmin(axis=1)
    np.testing.assert_array_equal(m, brute)
    with pytest.raises(ValueError):
        nearest_vertex_map(fine, np.zeros((0, 3)))


def test_morph_positions_blend() -> None:
    rng = np.random.default_rng(2)
    fine, coarse = rng.normal(size=(10, 3)), rng.normal(size=(4, 3))
    m = rng.integers(0, 4, 10)
    np.testing.assert_allclose(morph_positions(fine, coarse, m, 1.0), fine)
    np.testing.assert_allclose(morph_positions(fine, coarse, m, 0.0), coarse[m])
    np.testing.assert_allclose(morph_positions(fine, coarse, m, 0.25), 0.25 * fine + 0.75 * coarse[m])
    w = np.linspace(0, 1, 10)
    np.testing.assert_allclose(morph_positions(fine, coarse, m, w), w[:, None] * fine + (1 - w[:, None]) * coarse[m])


def test_no_morph() -> None:
    pos, faces = _bumpy_sphere(3)
    chain = build_chain(pos, faces, morph="none")
    assert chain.morph == [None] * len(chain) and chain.morph_kind == "none"
    assert not morph_faces_match(chain, 1)


def test_chain_from_source_levels() -> None:
    """Levels a source gives (no collapse history): GPU order, measured errors, nearest maps."""
    levels = [trimesh.creation.box((2.0, 2.0, 2.0)), trimesh.creation.icosphere(1), trimesh.creation.icosphere(3)]
    levels = [(m.vertices, m.faces) for m in levels]
    chain = chain_from_levels(levels)
    assert chain.faces == [12, 80, 1280]
    _maps_are_valid(chain)
    assert chain.morph_kind == "nearest"
    assert chain.errors[-1] == 0.0 and chain.errors[0] >= chain.errors[1] > 0.0
    for p, f in chain.levels:
        _, first = np.unique(f.ravel(), return_index=True)
        assert (np.diff(first) > 0).all()  # vertices in first-use order
    given = chain_from_levels(levels, errors=[3.0, 2.0, 0.0], morph="none")
    assert given.errors == [3.0, 2.0, 0.0] and given.morph == [None] * 3
    with pytest.raises(ValueError):
        chain_from_levels(levels, morph="collapse")
    with pytest.raises(ValueError):
        chain_from_levels(levels, errors=[1.0, 0.0])
    with pytest.raises(ValueError):
        chain_from_levels([])


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    kind=st.sampled_from(["sphere", "grid"]),
    size=st.integers(1, 3),
    seed=st.integers(0, 2**31 - 1),
    min_saving=st.sampled_from([0.4, 0.5]),
    preserve_border=st.booleans(),
)
def test_collapse_property_on_random_meshes(kind: str, size: int, seed: int, min_saving: float,
                                            preserve_border: bool) -> None:
    if kind == "sphere":
        pos, faces = _bumpy_sphere(size + 1, seed=seed, amount=0.1)
        pos = pos + np.random.default_rng(seed).normal(0, 0.01, pos.shape)
    else:
        pos, faces = _bumpy_grid(6 * size + 2, seed=seed)
    chain = build_chain(pos, faces, min_saving=min_saving, preserve_border=preserve_border)
    counts = chain.faces
    assert all(a <= (1 - min_saving) * b for a, b in zip(counts, counts[1:]))
    assert min(counts) >= 12 or len(chain) == 1
    assert all(a >= b for a, b in zip(chain.errors, chain.errors[1:])) and chain.errors[-1] == 0.0
    _maps_are_valid(chain)
    for k in range(1, len(chain)):
        assert morph_faces_match(chain, k), (k, counts)


# --------------------------------------------------------------------------- GPU order


def test_order_for_gpu_is_what_encode_does() -> None:
    m = trimesh.creation.icosphere(3)
    v = m.vertices * [1.0, 2.0, 0.5]
    p, f, new_of_old = order_for_gpu(v, m.faces)
    np.testing.assert_array_equal(p[new_of_old], v)
    same = lambda a: _rotated(a)[np.lexsort(_rotated(a).T[::-1])]  # noqa: E731
    np.testing.assert_array_equal(same(new_of_old[m.faces]), same(f))
    lo, hi = v.min(0), v.max(0)
    assert encode_geometry(p, f, lo, hi, reorder=False) == encode_geometry(v, m.faces)
    g = decode_geometry(encode_geometry(p, f, lo, hi, reorder=False))
    np.testing.assert_array_equal(_rotated(g.indices), _rotated(f))  # same faces, same order
    np.testing.assert_allclose(g.positions, p, atol=np.max(hi - lo) / 65535)


def test_unused_vertices() -> None:
    m = trimesh.creation.icosphere(1)
    v = np.vstack([[9.0, 9.0, 9.0], m.vertices])
    f = np.asarray(m.faces) + 1
    p, g, new_of_old = order_for_gpu(v, f)
    assert new_of_old[0] == -1 and p.shape[0] == v.shape[0] - 1
    assert decode_geometry(encode_geometry(v, f)).vertices == v.shape[0] - 1
    kept = decode_geometry(encode_geometry(v, f, reorder=False))  # exactly as given, unused included
    assert kept.vertices == v.shape[0]
    np.testing.assert_array_equal(_rotated(kept.indices), _rotated(f))
    np.testing.assert_allclose(kept.positions, v, atol=9.0 / 65535)


def test_stored_payloads_keep_the_morph_property() -> None:
    """build_object's payloads, decoded as a client sees them, still morph exactly."""
    obj = next(o for o in generate_demo(objects=2, seed=5).objects if o.cls != "ground")
    _, lo, hi, errors, blobs, morphs = build_object(obj)
    assert len(blobs) == len(morphs) == len(errors) >= 3 and morphs[0] is None
    geoms = [decode_geometry(b) for b in blobs]
    for k in range(1, len(blobs)):
        m = decode_morph(morphs[k], geoms[k].vertices, geoms[k - 1].vertices)
        g = m[geoms[k].indices]
        g = g[(g[:, 0] != g[:, 1]) & (g[:, 1] != g[:, 2]) & (g[:, 0] != g[:, 2])]
        np.testing.assert_array_equal(np.unique(_rotated(g), axis=0), np.unique(_rotated(geoms[k - 1].indices), axis=0))


# --------------------------------------------------------------------------- codec


@pytest.mark.parametrize("n, nc", [(1, 1), (7, 3), (5000, 1200), (70000, 70000)])
def test_morph_codec_round_trip(n: int, nc: int) -> None:
    m = np.random.default_rng(n).integers(0, nc, n)
    out = decode_morph(encode_morph(m, nc), n_fine=n, n_coarse=nc)
    assert out.dtype == np.uint32
    np.testing.assert_array_equal(out, m)
    np.testing.assert_array_equal(decode_morph(encode_morph(m.astype(np.uint16 if nc < 65536 else np.int32), nc)), m)


def test_morph_codec_is_compact_on_collapse_maps() -> None:
    pos, faces = _bumpy_sphere(5)
    chain = build_chain(pos, faces)
    m = chain.morph[-1]
    blob = encode_morph(m, chain.vertices[-2])
    assert len(blob) < 1.5 * m.size  # ≈ 8.5 bits per entry
    np.testing.assert_array_equal(decode_morph(blob), m)


def test_encode_morph_refuses_bad_maps() -> None:
    for m, nc in [(np.array([0, 3]), 3), (np.array([-1, 0]), 3), (np.array([], int), 3), (np.zeros((2, 2), int), 3),
                  (np.array([0.0, 1.0]), 3), (np.array([0]), 0), (np.array([0]), MAX_VERTICES + 1)]:
        with pytest.raises(ValueError):
            encode_morph(m, nc)


def _patched(**changes) -> bytes:
    payload = msgpack.unpackb(encode_morph(np.arange(10) % 4, 4), raw=False)
    payload.update(changes)
    return msgpack.packb({k: v for k, v in payload.items() if v is not None}, use_bin_type=True)


@pytest.mark.parametrize(
    "blob",
    [
        b"\xc1",  # never valid msgpack
        msgpack.packb([1, 2, 3]),
        _patched(enc="mm0"),
        _patched(enc=None),
        _patched(n=0),
        _patched(n=True),
        _patched(n=MAX_VERTICES + 1),
        _patched(n="10"),
        _patched(nc=0),
        _patched(nc=3),  # an entry is 3
        _patched(nc=None),
        _patched(n=11),  # data holds 10
        _patched(data="text"),
        _patched(data=b""),
        _patched(data=msgpack.unpackb(encode_morph(np.arange(10) % 4, 4))["data"][:-3]),
    ],
)
def test_decode_morph_refuses_defects(blob: bytes) -> None:
    with pytest.raises(ProtocolError) as info:
        decode_morph(blob)
    assert info.value.code == "bad_geometry"


def test_decode_morph_checks_the_levels() -> None:
    blob = encode_morph(np.arange(10) % 4, 4)
    decode_morph(blob, n_fine=10, n_coarse=4)
    with pytest.raises(ProtocolError):
        decode_morph(blob, n_fine=11)
    with pytest.raises(ProtocolError):
        decode_morph(blob, n_coarse=5)


def test_replay_fallback_gives_the_same_property(monkeypatch) -> None:
    """If the simplifier's vertex numbering ever differs from the expected one, the collapses are replayed."""
    import server.scene.lod as lod

    pos, faces = _bumpy_sphere(3)
    expected = build_chain(pos, faces)
    monkeypatch.setattr(lod, "_representatives", lambda n, collapses: np.arange(n))  # a wrong history
    chain = build_chain(pos, faces)
    assert chain.faces == expected.faces
    for k in range(1, len(chain)):
        assert morph_faces_match(chain, k)
        np.testing.assert_array_equal(chain.morph[k], expected.morph[k])


def test_collapse_maps_exact_on_the_auditorium_chair() -> None:
    """A regression: vertices whose survivor lost all its faces once went to different targets,
    reopening flattened faces at weight 0 (seen at the first, 248-triangle chair's 124 → 62 step)."""
    from server.scene.generate.auditorium import auditorium

    scene, _, _ = auditorium(seed=3)
    chair = next(o for o in scene.objects if o.cls == "chair").levels[0]
    chain = build_chain(chair.positions, chair.faces)
    assert len(chain) >= 4
    assert all(morph_faces_match(chain, k) for k in range(1, len(chain)))
