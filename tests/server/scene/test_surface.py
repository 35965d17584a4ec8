"""Exposed surface area: buried faces of overlapping shells do not count; nothing else changes."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from server.scene.blocks import pruned, shell_reach
from server.scene.surface import exposed_area, shells, surface_area


def _box(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    m = trimesh.creation.box(bounds=np.array([lo, hi], float))
    return np.asarray(m.vertices), np.asarray(m.faces, np.int64)


def _union(*meshes) -> tuple[np.ndarray, np.ndarray]:
    off = np.cumsum([0] + [p.shape[0] for p, _ in meshes[:-1]])
    return np.concatenate([p for p, _ in meshes]), np.concatenate([f + o for (_, f), o in zip(meshes, off)])


def test_a_box_sunk_into_another_counts_only_what_stands_out() -> None:
    """10 m cube; a 7 × 6 × 6 m box, 5 m of it inside: the cube loses the 36 m² it covers, the box
    shows its 36 m² end and 4 × 12 m² of sides; the plain area counts everything (840 m²)."""
    body = _box((0, 0, 0), (10, 10, 10))
    wing = _box((5, 2, 2), (12, 8, 8))
    p, f = _union(body, wing)
    assert surface_area(p, f) == pytest.approx(840.0)
    assert exposed_area(p, f) == pytest.approx(600.0 - 36.0 + 36.0 + 48.0, rel=0.03)


@settings(max_examples=25, deadline=None)
@given(st.lists(st.tuples(st.floats(1, 20), st.floats(1, 20), st.floats(1, 20)), min_size=1, max_size=5),
       st.floats(0.5, 10))
def test_shells_apart_hide_nothing(sizes, gap) -> None:
    """Boxes in a row with gaps between them: the exposed area is the plain area, exactly."""
    x, parts = 0.0, []
    for w, d, h in sizes:
        parts.append(_box((x, 0, 0), (x + w, d, h)))
        x += w + gap
    p, f = _union(*parts)
    assert shells(p.shape[0], f)[0] == len(sizes)
    assert exposed_area(p, f) == pytest.approx(surface_area(p, f), rel=1e-12)


def test_exposed_area_is_deterministic() -> None:
    p, f = _union(_box((0, 0, 0), (10, 10, 10)), _box((5, 2, 2), (12, 8, 8)))
    assert exposed_area(p, f) == exposed_area(p.copy(), f.copy())


def test_pruning_drops_the_shells_that_barely_stand_out() -> None:
    """A body with a frame 0.1 m proud and a tower 5 m above it: reach 0.5 drops the frame only."""
    body = _box((0, 0, 0), (10, 10, 10))
    frame = _box((3, -0.1, 3), (5, 0.2, 5))  # stands 0.1 m out of the body's box
    tower = _box((4, 4, 10), (6, 6, 15))  # stands 5 m out
    p, f = _union(body, frame, tower)
    label, reach = shell_reach(p, f)
    assert reach[label[0]] == np.inf and reach[label[12]] == pytest.approx(0.1) and reach[label[24]] == pytest.approx(5)
    kept = pruned(p, f, 0.5)
    assert kept is not None and kept[1].shape[0] == 24
    assert surface_area(*kept) == pytest.approx(surface_area(*_union(body, tower)))
    assert pruned(p, f, 0.05) is None  # nothing to prune
    assert pruned(*body, 1.0) is None  # one shell
