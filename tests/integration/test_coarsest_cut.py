"""A megacity street seen through the coarsest cut, drawn by the real client renderer, keeps its walls.

The coarsest cut is what a session draws when the budget allows nothing finer: the roots of the
kept HLOD forest (proxies, or buildings whose every ancestor's proxy was not kept) at their
coarsest level. The full-detail frame is drawn with each building split in two — its walls
(faces within about 17° of vertical) at false-colour level 1 (red), everything else at level 0
(blue) — so its red pixels are the walls a viewer sees, occlusion included.
"""

from __future__ import annotations

import numpy as np
import pytest

from proto.tour import Tour
from client.renderer import Renderer
from proto.camera import NEAR, far_plane
from proto.geometry import Geometry, decode_geometry
from server.scene.catalog import build_named
from server.scene.index import HLOD, MESH
from server.scene.store import SceneStore


def _frame(r: Renderer, reps, levels, pose, bounds) -> np.ndarray:
    eye, forward, up = pose
    r.draw(np.asarray(reps, np.int64), eye, forward, up, NEAR, far_plane(eye, bounds),
           levels=np.asarray(levels, np.float64))
    return r.read_image().astype(np.int16)


@pytest.fixture(scope="module")
def street(tmp_path_factory):
    """A 300-building megacity, the camera at its street viewpoint, the full and coarsest meshes."""
    path = tmp_path_factory.mktemp("scenes") / "megacity-300.db"
    build_named("megacity", path, seed=0, size=300)
    with SceneStore.open(path) as store:
        idx = store.index
        building = idx.class_names.index("building")
        meshes = np.flatnonzero((idx.object_kind == MESH) & (idx.object_class == building))
        roots = np.flatnonzero((idx.object_parent == -1) & ((idx.object_kind == HLOD) | (idx.object_class == building)))
        full = [decode_geometry(b) for b in store.geometries((idx.rep_first[meshes] + idx.rep_count[meshes] - 1).tolist())]
        coarse = [decode_geometry(b) for b in store.geometries(idx.rep_first[roots].tolist())]
        pose = Tour(idx.tour).pose_at(float(idx.meta["viewpoints"]["street"]))
        bounds = np.asarray(idx.bounds, np.float64)
        kinds = idx.object_kind[roots]
    return full, coarse, pose, bounds, kinds


def test_coarsest_cut_covers_the_walls_at_street_level(street) -> None:
    full, coarse, pose, bounds, kinds = street
    assert (kinds == HLOD).any()  # the cut holds proxies, not only buildings' own coarsest levels
    assert sum(g.faces for g in coarse) < 0.15 * sum(g.faces for g in full)
    with Renderer(640, 360, fov_y=60.0) as r:
        r.false_colour, r.false_colour_levels = True, 1.0
        background = _frame(r, [], [], pose, bounds)
        reps, levels = [], []
        for i, g in enumerate(full):
            tri = g.positions[g.indices.astype(np.int64)].astype(np.float64)
            n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            wall = np.abs(n[:, 2]) < 0.3 * np.linalg.norm(n, axis=1)
            for k, part in enumerate((g.indices[wall], g.indices[~wall])):
                if part.size:
                    r.upload(2 * i + k, Geometry(g.positions, np.ascontiguousarray(part)))
                    reps.append(2 * i + k)
                    levels.append(1.0 - k)
        detail = _frame(r, reps, levels, pose, bounds)
        base = 2 * len(full)
        for j, g in enumerate(coarse):
            r.upload(base + j, g)
        cut = _frame(r, np.arange(base, base + len(coarse)), np.zeros(len(coarse)), pose, bounds)
    drawn = np.abs(detail - background).max(axis=2) > 8
    walls = drawn & (detail[..., 0] > detail[..., 2] + 30)  # red: level 1
    covered = np.abs(cut - background).max(axis=2) > 8
    assert walls.sum() > 0.05 * walls.size  # the street view is mostly facades
    assert covered[walls].mean() >= 0.9
