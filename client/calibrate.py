"""The client's first measure of its own renderer, taken before the session opens.

The server's cost model starts from a guess of the seconds a vertex costs
(``serve --c-vertex``) and learns the machine from the frame reports. Until it
has, its first selections are priced by the guess — and the first selection of
a session is the one that fills the empty cache, the largest of all. A guess
three times too low made the first two seconds of a session draw frames of
three times the target. The client holds the renderer the selection is for, so
it measures it: a sphere of ``VERTICES`` vertices, lit, filling a third of the
viewport's height, drawn ``REPEATS`` times with the renderer's own fenced
timing; the median frame's seconds per vertex (Zach's c_vertex: the frame's
whole time over its vertices, as the session's vertex model counts it) go in
the hello (``Hello.c_vertex``) as the cost model's prior.
"""

from __future__ import annotations

import numpy as np

from proto.geometry import Geometry
from proto.messages import ALGORITHMS

__all__ = ["renderer_c_vertex", "sphere", "VERTICES", "REPEATS"]

#: Vertices of the calibration mesh: a frame's worth of geometry at an interactive target on a software
#: rasterizer, so the measured price holds where budgets bind.
VERTICES = 64_000
REPEATS = 3
#: Representation id the calibration mesh borrows (freed afterwards): no scene has this many.
_REP = (1 << 31) - 2


def sphere(vertices: int = VERTICES) -> Geometry:
    """A closed UV sphere of radius 1 at the origin with about ``vertices`` vertices."""
    rings = max(int(np.sqrt(vertices / 2)), 3)
    segments = max(vertices // rings, 3)
    theta = np.linspace(0.0, np.pi, rings)
    phi = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    pos = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(rings - 1), np.arange(segments), indexing="ij")
    a = i * segments + j
    b = i * segments + (j + 1) % segments
    c, d = a + segments, b + segments
    faces = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    return Geometry(pos.astype(np.float32), faces.astype(np.uint32))


def renderer_c_vertex(renderer, vertices: int = VERTICES, repeats: int = REPEATS) -> float | None:
    """Seconds per vertex of ``renderer`` (a ``client.renderer.Renderer``) on a lit sphere: the median of
    ``repeats`` fenced frames over the vertices drawn; None if nothing could be measured."""
    mesh = sphere(vertices)
    # A third of the viewport's height: the sphere's radius 1 at the distance where it spans that.
    distance = 3.0 / np.tan(np.radians(renderer.fov_y) / 2)
    renderer.upload(_REP, mesh)
    try:
        times = []
        lit = np.array([ALGORITHMS.index("lit")])
        for _ in range(repeats):
            stats = renderer.draw(np.array([_REP]), np.array([0.0, -distance, 0.0]), np.array([0.0, 1.0, 0.0]),
                                  np.array([0.0, 0.0, 1.0]), 0.1, 2 * distance, algorithms=lit)
            if stats.vertices > 0 and stats.time > 0:
                times.append(stats.time / stats.vertices)
    finally:
        renderer.free(_REP)
        renderer.missing = 0
    return float(np.median(times)) if times else None
