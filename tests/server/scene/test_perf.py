"""How fast scene pieces run, as ratios to a plain numpy or library operation of the same size.

The machines that run the suite are shared and their speed varies, so no test
here asserts a time. Each measures the operation and a reference right beside
it, in turn, best of several, and bounds the ratio of the two. The bounds are
loose on purpose: they catch a lost vectorisation (a Python loop per point or
per tree, a quadratic step), not a few percent.
"""

from __future__ import annotations

import json
import time
from typing import Callable

import numpy as np
import pytest

from server.scene.data import data_file
from server.scene.importers.cityjson import load_cityjson
from server.scene.points import prefix_order
from server.scene.source import HeightGrid
from server.scene.vegetation import broadleaf, conifer, forest, group_trees

pytestmark = pytest.mark.perf


def _ratio(operation: Callable[[], object], reference: Callable[[], object], repeats: int = 3) -> float:
    """Best time of ``operation`` ÷ best time of ``reference``, the two measured alternately."""
    best_op = best_ref = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        reference()
        best_ref = min(best_ref, time.perf_counter() - t)
        t = time.perf_counter()
        operation()
        best_op = min(best_op, time.perf_counter() - t)
    return best_op / best_ref


def test_prefix_order_costs_a_few_sorts_per_level():
    """The vectorised K-d order against the naive build that re-sorts all points at every level."""
    p = np.random.default_rng(0).normal(size=(100_000, 3))
    levels = int(np.ceil(np.log2(p.shape[0])))

    def resort_every_level() -> None:
        for level in range(levels):
            np.argsort(p[:, level % 3], kind="stable")

    ratio = _ratio(lambda: prefix_order(p), resort_every_level)
    assert ratio < 15, f"prefix_order took {ratio:.1f}× {levels} stable argsorts of the same points"


def _hill(rows: int, spacing: float) -> HeightGrid:
    """The height field of ``test_vegetation``: a hill, ripples and a void in one corner."""
    yy, xx = np.mgrid[0:rows, 0:rows] / rows
    h = 900 * np.exp(-((xx - 0.5) ** 2 + (yy - 0.5) ** 2) / 0.04) + 30 * np.sin(xx * 9) + 100
    h[:40, :60] = np.nan
    return HeightGrid("g", h, (1000.0, -500.0), (spacing, spacing))


def _bilinear_lookup(grid: HeightGrid, n: int, seed: int) -> np.ndarray:
    """Heights at n uniform random points of the grid, bilinear: the core of placing a forest."""
    rows, cols = grid.heights.shape
    rng = np.random.default_rng(seed)
    u = rng.uniform(0, cols - 1, n)
    v = rng.uniform(0, rows - 1, n)
    c = np.minimum(u.astype(np.int64), cols - 2)
    r = np.minimum(v.astype(np.int64), rows - 2)
    fu, fv = u - c, v - r
    h = grid.heights
    return (h[r, c] * (1 - fu) * (1 - fv) + h[r, c + 1] * fu * (1 - fv)
            + h[r + 1, c] * (1 - fu) * fv + h[r + 1, c + 1] * fu * fv)


@pytest.fixture(scope="module")
def boxes():
    models = [conifer(i) for i in range(3)] + [broadleaf(i) for i in range(2)]
    return [(m.mesh.positions.min(axis=0), m.mesh.positions.max(axis=0)) for m in models]


def test_big_forest_places_and_groups_at_array_speed(boxes):
    """St. Helens' scale: 1.4 M trees placed on a 2049² grid and grouped ≤ 64 per leaf."""
    grid = _hill(rows=2049, spacing=58.6)
    n = 1_400_000
    placed = {}

    def place() -> None:
        placed["trees"] = None  # one forest held at a time
        placed["trees"] = forest(grid, n, seed=0, models=len(boxes))

    ratio = _ratio(place, lambda: _bilinear_lookup(grid, n, seed=0))
    assert ratio < 50, f"forest took {ratio:.1f}× a bilinear lookup of as many points"
    trees = placed["trees"]
    keys = np.random.default_rng(1).random(len(trees))
    ratio = _ratio(lambda: group_trees(trees, [4096] * len(boxes), model_boxes=boxes),
                   lambda: np.argsort(keys, kind="stable"))
    assert ratio < 50, f"group_trees took {ratio:.1f}× a stable argsort of as many keys"


def test_cityjson_import_is_a_small_multiple_of_parsing_it():
    """Den Haag's 3 MB CityJSON against json.loads of the same bytes."""
    path = data_file("city/DenHaag_01.city.json")
    ratio = _ratio(lambda: load_cityjson(path), lambda: json.loads(path.read_bytes()))
    assert ratio < 150, f"load_cityjson took {ratio:.1f}× parsing the file's JSON"
