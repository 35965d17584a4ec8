"""LOD chains (levels, floor, savings) and their geometric error; geomorph maps are in test_morph_maps.py."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from server.scene.lod import Chain, build_chain, chain_errors, clean_mesh, geometric_error


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


def _first_use_order(faces: np.ndarray) -> bool:
    """Vertices are numbered in the order faces first use them (GPU order)."""
    _, first = np.unique(faces.ravel(), return_index=True)
    return bool((np.diff(first) > 0).all())


def test_chain_is_monotonic_and_clean() -> None:
    pos, faces = _bumpy_sphere()
    chain = build_chain(pos, faces)
    counts = chain.faces
    assert isinstance(chain, Chain) and chain.morph_kind == "collapse"
    assert 3 <= len(chain) <= 8
    assert all(a < b for a, b in zip(counts, counts[1:]))
    assert all(a <= 0.6 * b for a, b in zip(counts, counts[1:]))  # each level saves ≥ 40 %
    assert counts[-1] == faces.shape[0]
    assert chain.vertices == [p.shape[0] for p, _ in chain.levels]
    for p, f in chain.levels:
        assert p.dtype == np.float64 and f.dtype == np.int64
        assert f.min() >= 0 and f.max() == p.shape[0] - 1
        assert np.unique(f).size == p.shape[0]  # no unreferenced vertices
        assert ((f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])).all()
        assert _first_use_order(f)
    # the finest level is the input, reordered
    np.testing.assert_allclose(np.sort(chain.levels[-1][0], axis=0), np.sort(pos, axis=0))


def test_chain_respects_min_saving() -> None:
    pos, faces = _bumpy_sphere(4)
    chain = build_chain(pos, faces, min_saving=0.7, ratio=0.25)
    counts = chain.faces
    assert len(chain) >= 3
    assert all(a <= 0.3 * b for a, b in zip(counts, counts[1:]))
    with pytest.raises(ValueError):
        build_chain(pos, faces, min_saving=0.7)  # ratio 0.5 cannot save 70 %


def test_chain_stops_at_the_floor() -> None:
    m = trimesh.creation.icosphere(2)  # 320 faces → 160 → 80 → (48 < 64: stop)
    chain = build_chain(m.vertices, m.faces, floor_faces=64)
    assert chain.faces == [80, 160, 320]
    chain = build_chain(m.vertices, m.faces, floor_faces=12, max_levels=20)
    assert min(chain.faces) >= 12 and chain.faces[0] * 0.6 < 12  # went down to the floor
    assert len(build_chain(m.vertices, m.faces, max_levels=1)) == 1
    tetra = trimesh.creation.icosphere(0)  # 20 faces: 12 is a 40 % saving, then nothing
    assert build_chain(tetra.vertices, tetra.faces).faces == [12, 20]
    assert build_chain(tetra.vertices, tetra.faces, floor_faces=13).faces == [20]


def test_max_levels_and_its_former_name() -> None:
    pos, faces = _bumpy_sphere(4)
    assert len(build_chain(pos, faces, max_levels=3)) == 3
    assert build_chain(pos, faces, levels=3).faces == build_chain(pos, faces, max_levels=3).faces


def test_chain_rejects_bad_arguments() -> None:
    pos, faces = _bumpy_sphere(2)
    for kwargs in ({"max_levels": 0}, {"min_saving": 1.0}, {"min_saving": 0.0}, {"ratio": 0.0},
                   {"floor_faces": 0}, {"morph": "linear"}):
        with pytest.raises(ValueError):
            build_chain(pos, faces, **kwargs)


def test_chain_is_a_sequence_of_levels() -> None:
    """Code written for the former list-of-levels result still works."""
    pos, faces = _bumpy_sphere(3)
    chain = build_chain(pos, faces)
    assert len(chain) == len(chain.levels)
    assert chain[-1] is chain.levels[-1]
    assert [f.shape[0] for _, f in chain] == chain.faces
    assert len(chain + chain) == 2 * len(chain)
    assert chain_errors(chain) == chain.errors


def test_open_border_is_kept() -> None:
    pos, faces = _grid(48)
    chain = build_chain(pos, faces, max_levels=3)
    assert len(chain) == 3
    for p, _ in chain.levels:
        np.testing.assert_allclose(p.min(0)[:2], [0.0, 0.0])
        np.testing.assert_allclose(p.max(0)[:2], [10.0, 10.0])
    assert chain.errors[0] < 0.1


def test_pinned_border_stops_the_chain() -> None:
    """A small open grid is mostly border: once the border dominates, a step cannot save 40 %."""
    pos, faces = _grid(12)  # 288 faces, 48 border vertices
    pinned = build_chain(pos, faces, max_levels=20)
    free = build_chain(pos, faces, max_levels=20, preserve_border=False)
    assert len(pinned) < len(free)
    assert pinned.faces[0] >= 0.6 * 48  # a pinned border of 48 vertices needs ≥ 46 faces
    assert all(a <= 0.6 * b for a, b in zip(pinned.faces, pinned.faces[1:]))


def test_errors_non_increasing_toward_full_detail() -> None:
    pos, faces = _bumpy_sphere()
    chain = build_chain(pos, faces)
    errors = chain.errors
    assert errors == chain_errors(chain.levels)
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
    """Against every point × every triangle, closest points by trimesh (an independent implementation)."""
    pos, faces = _bumpy_sphere(4)
    chain = build_chain(pos, faces)
    fine = chain.levels[-1][0]
    pick = np.sort(np.random.default_rng(3).choice(fine.shape[0], 300, replace=False))
    for p, f in chain.levels[:-1]:
        tri = p[f]
        pts = np.repeat(fine[pick], len(f), axis=0)
        q = trimesh.triangles.closest_point(np.tile(tri, (len(pick), 1, 1)), pts)
        exact = np.linalg.norm(pts - q, axis=1).reshape(len(pick), -1).min(axis=1).max()
        assert geometric_error(fine, p, f, samples=300, seed=3) == pytest.approx(exact, rel=1e-9)


def test_error_is_deterministic() -> None:
    pos, faces = _bumpy_sphere()
    chain = build_chain(pos, faces)
    assert chain_errors(chain.levels) == chain_errors(chain.levels) == chain.errors
    assert build_chain(pos, faces).faces == chain.faces


def test_clean_mesh_drops_degenerate_and_unused() -> None:
    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5], [2, 0, 0]], float)
    faces = np.array([[0, 1, 2], [0, 0, 1], [0, 1, 4]])  # repeated index; zero area
    p, f = clean_mesh(pos, faces)
    assert f.tolist() == [[0, 1, 2]]
    np.testing.assert_array_equal(p, pos[:3])
