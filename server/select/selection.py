"""One selection, start to end: cull, size, benefit and cost per level, solve.

The steps the session runs every τ, as one pure function over the scene's
arrays, so that a benchmark or a test can run exactly what a session runs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import solvers
from .benefit import benefit as level_benefit
from .camera import View, cull_boxes, frustum_planes, screen_size, widened
from .cost import CostModel

__all__ = ["Levels", "Choice", "select"]


@dataclass(frozen=True)
class Levels:
    """The part of a scene index the selection reads (structure of arrays).

    object_lo, object_hi : (n, 3) float bounding boxes
    rep_first, rep_count : (n,) int — the object's representations are ids
        rep_first .. rep_first + rep_count − 1, coarsest first
    rep_faces, rep_vertices : (m,) int
    """

    object_lo: np.ndarray
    object_hi: np.ndarray
    rep_first: np.ndarray
    rep_count: np.ndarray
    rep_faces: np.ndarray
    rep_vertices: np.ndarray

    @classmethod
    def of(cls, index) -> "Levels":
        """The flat view of a scene index: its triangle-mesh leaves (``SceneIndex.flat``).

        HLOD proxies, coarse terrain patches and tree groups need the
        hierarchical and mixed solvers; a flat selection draws the leaves only.
        """
        flat = np.nonzero(index.flat)[0]
        return cls(
            index.object_lo[flat], index.object_hi[flat], index.rep_first[flat], index.rep_count[flat],
            index.rep_faces, index.rep_vertices,
        )


@dataclass(frozen=True)
class Choice:
    """The selection: representation ids to draw (one per drawn object), predicted cost and benefit."""

    reps: np.ndarray  # (s,) int64
    cost: float
    benefit: float
    visible: int
    stats: dict


def select(
    levels: Levels,
    view: View,
    cost_model: CostModel,
    budget: float,
    solver: str = "greedy",
    margin_deg: float = 20.0,
) -> Choice:
    """Choose representations for ``view`` within ``budget`` seconds.

    ``margin_deg`` widens the field of view so that objects about to come into
    view during the interval are already selected.
    """
    wide = widened(view, margin_deg)
    clip = wide.matrix()
    visible = np.nonzero(cull_boxes(levels.object_lo, levels.object_hi, frustum_planes(clip)))[0]
    if visible.size == 0:
        return Choice(np.zeros(0, np.int64), 0.0, 0.0, 0, {})
    size = screen_size(levels.object_lo[visible], levels.object_hi[visible], clip, wide.width, wide.height)

    count = levels.rep_count[visible].astype(np.int64)
    k = int(count.max())
    slot = np.arange(k)[None, :]
    valid = slot < count[:, None]
    rep = np.where(valid, levels.rep_first[visible, None].astype(np.int64) + slot, 0)  # (v, K)
    benefit = np.where(valid, level_benefit(size[:, None], levels.rep_faces[rep]), 0.0)
    cost = np.where(valid, cost_model.predict(levels.rep_vertices[rep]), np.inf)

    faces = np.where(valid, levels.rep_faces[rep], 0)
    cand = solvers.Candidates.of(benefit, cost, valid, size=size, faces=faces)
    result = solvers.get(solver)(cand, budget)
    drawn = result.level >= 0
    reps = rep[drawn, result.level[drawn]]
    return Choice(reps=reps, cost=result.cost, benefit=result.benefit, visible=int(visible.size), stats=result.stats)
