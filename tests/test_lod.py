"""LOD chains and their geometric error."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from server.scene.lod import _closest_on_triangles, build_chain, chain_errors, clean_mesh, geometric_error


def _bumpy_sphere(subdiv: int = 5) -> tuple[np.ndarray, np.ndarray]:
    m = trimesh.creation.icosphere(subdiv)
    v = m.vertices
    r = 1.0 + 0.04 * np.sin(9 * v[:, 0]) * np.cos(7 * v[:, 1]) + 0.02 * np.sin(23 * v[:, 2])
    return v * r[:, None], np.asarray(m.faces)


def _grid(n: int, size: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """Open square heightfield of n × n quads with a bump in the middle."""
    t = np.linspace(0.0, size, n + 1)
    x, y = np.meshgrid(t, t, indexing="ij")
    z = 0.3 * np.exp(-((x - size / 2) ** 2 + (y - size / 2) ** 2))
    pos = np.stack([x.ravel(), y.ravel(), z.ravel()], -1)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a, b, c, d = i * (n + 1) + j, (i + 1) * (n + 1) + j, (i + 1) * (n + 1) + j + 1, i * (n + 1) + j + 1
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return pos, faces


def test_chain_is_monotonic_and_clean() -> None:
    pos, faces = _bumpy_sphere()
    chain = build_chain(pos, faces, levels=4, ratio=0.25)
    counts = [f.shape[0] for _, f in chain]
    assert len(chain) == 4
    assert all(a < b for a, b in zip(counts, counts[1:]))
    assert counts[-1] == faces.shape[0]
    for p, f in chain:
        assert f.min() >= 0 and f.max() == p.shape[0] - 1
        assert np.unique(f).size == p.shape[0]  # no unreferenced vertices
        assert ((f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])).all()
    for (_, coarse), (_, fine) in zip(chain, chain[1:]):
        assert coarse.shape[0] <= fine.shape[0] * 0.3  # about ratio 0.25 per step


def test_chain_stops_at_min_faces() -> None:
    m = trimesh.creation.icosphere(2)  # 320 faces → 80 → (20 < 64: stop)
    chain = build_chain(m.vertices, m.faces, levels=4, min_faces=64)
    assert [f.shape[0] for _, f in chain] == [80, 320]
    assert len(build_chain(m.vertices, m.faces, levels=1)) == 1


def test_chain_rejects_bad_arguments() -> None:
    pos, faces = _bumpy_sphere(2)
    with pytest.raises(ValueError):
        build_chain(pos, faces, levels=0)
    with pytest.raises(ValueError):
        build_chain(pos, faces, ratio=1.0)


def test_open_border_is_kept() -> None:
    pos, faces = _grid(48)
    chain = build_chain(pos, faces, levels=3)
    assert len(chain) == 3
    for p, _ in chain:
        np.testing.assert_allclose(p.min(0)[:2], [0.0, 0.0])
        np.testing.assert_allclose(p.max(0)[:2], [10.0, 10.0])
    assert chain_errors(chain)[0] < 0.1


def test_errors_non_increasing_toward_full_detail() -> None:
    pos, faces = _bumpy_sphere()
    chain = build_chain(pos, faces)
    errors = chain_errors(chain)
    assert len(errors) == len(chain)
    assert errors[-1] == 0.0
    assert errors[0] > 0.0
    assert all(a >= b for a, b in zip(errors, errors[1:]))
    assert errors[0] < 0.2  # a coarse sphere of radius ~1 stays close to it


def test_error_of_a_flattened_bump() -> None:
    pos, faces = _grid(32)
    flat = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [10.0, 10.0, 0.0], [0.0, 10.0, 0.0]])
    quad = np.array([[0, 1, 2], [0, 2, 3]])
    assert geometric_error(pos, flat, quad, samples=10_000) == pytest.approx(pos[:, 2].max())
    assert geometric_error(pos, pos, faces) == pytest.approx(0.0, abs=1e-12)


def test_error_matches_brute_force() -> None:
    pos, faces = _bumpy_sphere(4)
    chain = build_chain(pos, faces)
    fine = chain[-1][0]
    pick = np.sort(np.random.default_rng(3).choice(fine.shape[0], 300, replace=False))
    for p, f in chain[:-1]:
        tri = p[f]
        pts = np.repeat(fine[pick], len(f), axis=0)
        t = np.tile(tri, (len(pick), 1, 1))
        q = _closest_on_triangles(pts, t[:, 0], t[:, 1], t[:, 2])
        exact = np.linalg.norm(pts - q, axis=1).reshape(len(pick), -1).min(axis=1).max()
        assert geometric_error(fine, p, f, samples=300, seed=3) == pytest.approx(exact, rel=1e-9)


def test_closest_point_matches_trimesh() -> None:
    rng = np.random.default_rng(0)
    tri = rng.normal(size=(5000, 3, 3))
    p = rng.normal(size=(5000, 3)) * 2
    q = _closest_on_triangles(p, tri[:, 0], tri[:, 1], tri[:, 2])
    np.testing.assert_allclose(q, trimesh.triangles.closest_point(tri, p), atol=1e-9)


def test_error_is_deterministic() -> None:
    pos, faces = _bumpy_sphere()
    chain = build_chain(pos, faces)
    assert chain_errors(chain) == chain_errors(chain)


def test_clean_mesh_drops_degenerate_and_unused() -> None:
    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5], [2, 0, 0]], float)
    faces = np.array([[0, 1, 2], [0, 0, 1], [0, 1, 4]])  # repeated index; zero area
    p, f = clean_mesh(pos, faces)
    assert f.tolist() == [[0, 1, 2]]
    np.testing.assert_array_equal(p, pos[:3])
