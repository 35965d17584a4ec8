"""What a pose means: the view and projection conventions both sides must share.

The server culls and measures screen size with exactly the matrices the client
draws with, so they live in the contract. OpenGL conventions: right-handed
world, the camera looks down its −Z axis, clip space z in [−1, 1], matrices
are row-major numpy arrays applied as ``M @ column_vector`` (upload ``M.T``
to GLSL, which reads column-major).
"""

from __future__ import annotations

import numpy as np

__all__ = ["NEAR", "view_matrix", "projection_matrix", "far_plane", "normalize", "cross3"]

#: Near clip distance in metres: walkthroughs come close to walls, never closer than this.
NEAR = 0.1


def normalize(v: np.ndarray) -> np.ndarray:
    """Unit vectors along the last axis; (..., 3) float64."""
    v = np.asarray(v, np.float64)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, 1e-300)


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3,) float64 cross product of two 3-vectors: np.cross's general machinery costs far more than the
    arithmetic, and a frame that builds its camera from a pose pays it several times over."""
    a0, a1, a2 = (float(x) for x in np.asarray(a, np.float64).reshape(3))
    b0, b1, b2 = (float(x) for x in np.asarray(b, np.float64).reshape(3))
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def view_matrix(eye: np.ndarray, forward: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(4, 4) float64 world → eye transform. ``up`` is re-orthogonalised against ``forward``."""
    f = normalize(forward)
    s = normalize(cross3(f, up))
    u = cross3(s, f)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = s, u, -f
    m[:3, 3] = -m[:3, :3] @ np.asarray(eye, np.float64)
    return m


def projection_matrix(fov_y_deg: float, aspect: float, near: float, far: float) -> np.ndarray:
    """(4, 4) float64 perspective projection (gluPerspective)."""
    t = 1.0 / np.tan(np.radians(fov_y_deg) / 2.0)
    m = np.zeros((4, 4))
    m[0, 0] = t / aspect
    m[1, 1] = t
    m[2, 2] = (far + near) / (near - far)
    m[2, 3] = 2.0 * far * near / (near - far)
    m[3, 2] = -1.0
    return m


def far_plane(eye: np.ndarray, bounds: np.ndarray) -> float:
    """Far clip distance that keeps the whole scene box (2, 3) in view depth from ``eye``."""
    bounds = np.asarray(bounds, np.float64)
    corners = np.stack(np.meshgrid(*bounds.T, indexing="ij"), axis=-1).reshape(-1, 3)
    return float(np.linalg.norm(corners - np.asarray(eye, np.float64), axis=1).max() * 1.05 + 1.0)
