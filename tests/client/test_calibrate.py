"""The client's measure of its renderer before the hello, with the real renderer (headless EGL)."""

from __future__ import annotations

import numpy as np

from client.calibrate import VERTICES, renderer_c_vertex, sphere
from client.renderer import Renderer


def test_the_calibration_sphere_is_closed_and_about_the_size_asked():
    mesh = sphere(10_000)
    assert 9_000 <= mesh.positions.shape[0] <= 10_000
    edges = np.sort(np.concatenate([mesh.indices[:, [0, 1]], mesh.indices[:, [1, 2]], mesh.indices[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    # Closed but for the poles' degenerate rings (the UV sphere's first and last rings are points).
    assert np.mean(counts == 2) > 0.95
    assert np.allclose(np.linalg.norm(mesh.positions, axis=1), 1.0, atol=1e-5)


def test_the_renderer_is_measured_and_left_as_it_was():
    renderer = Renderer(320, 180)
    try:
        c = renderer_c_vertex(renderer, vertices=VERTICES // 4, repeats=2)
        assert c is not None and 1e-11 < c < 1e-4  # a second per 10 k vertices would be no renderer at all
        stats = renderer.draw(np.array([(1 << 31) - 2]), np.zeros(3), np.array([0.0, 1.0, 0.0]),
                              np.array([0.0, 0.0, 1.0]), 0.1, 10.0)
        assert stats.vertices == 0 and renderer.missing == 1  # the calibration mesh is gone
    finally:
        renderer.release()
