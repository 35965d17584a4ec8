"""The frame plan without GL: culling, grouping by algorithm and the counts, on a few hand-made slots."""

from __future__ import annotations

import numpy as np
import pytest

from client.frame_plan import DRAW, FLAG_MORPH, plan_frame
from client.slots import SlotTable
from proto.camera import projection_matrix, view_matrix

EYE = np.zeros(3)
FORWARD = np.array([0.0, 0.0, -1.0])
UP = np.array([0.0, 1.0, 0.0])
#: Camera-relative view-projection, as the renderer builds it: 90° fov, square, near 0.1, far 100.
VP = projection_matrix(90.0, 1.0, 0.1, 100.0) @ view_matrix(np.zeros(3), FORWARD, UP)


def _table(meshes: dict[int, tuple[tuple[float, float, float], int, int, bool]]) -> SlotTable:
    """A slot table holding rep → (centre, faces, vertices, has a morph target), unit boxes round each centre."""
    table = SlotTable(capacity=2)  # small, so adding the reps grows it
    for i, (rep, (centre, faces, vertices, target)) in enumerate(meshes.items()):
        slot = table.new()
        table.command[slot] = (3 * faces, 1, 100 * rep % 1000, 10 * rep % 1000, 0)
        table.faces[slot], table.vertices[slot] = faces, vertices
        table.tint[slot] = i  # tells the draws apart
        table.target[slot] = target
        c = np.asarray(centre, np.float64)
        table.bound(slot, c - 0.5, c + 0.5)
        table.bind(rep, slot)
    return table


def _reps(table: SlotTable, plan) -> list[int]:
    """The reps a plan draws, in its order."""
    rep_of = {slot: rep for rep, slot in table.meshes.items()}
    return [rep_of[int(s)] for s in plan.slots]


# Four reps in front of the camera, one behind it, one far to its left; rep -3 and 1 << 30 use the overflow.
MESHES = {
    1: ((0.0, 0.0, -5.0), 10, 8, False),
    2: ((1.0, 0.0, -6.0), 20, 15, True),
    3: ((0.0, 0.0, 5.0), 40, 30, True),  # behind
    4: ((-50.0, 0.0, -5.0), 80, 60, False),  # far outside the 90° frustum
    -3: ((0.0, 1.0, -8.0), 5, 4, True),
    1 << 30: ((0.0, -1.0, -9.0), 7, 6, False),
}


def test_reps_outside_the_frustum_are_culled_and_counted_in_nothing_else() -> None:
    table = _table(MESHES)
    plan = plan_frame(np.array([1, 2, 3, 4, -3, 1 << 30]), table, VP, EYE)
    assert plan.culled == 2 and plan.missing == 0 and len(plan) == 4
    assert _reps(table, plan) == [1, 2, -3, 1 << 30]
    assert plan.triangles.tolist() == [10 + 20 + 5 + 7, 0, 0] and plan.vertices.tolist() == [8 + 15 + 4 + 6, 0, 0]
    assert plan.draws.tolist() == [4, 0, 0]

    kept = plan_frame(np.array([1, 2, 3, 4, -3, 1 << 30]), table, VP, EYE, cull=False)
    assert kept.culled == 0 and len(kept) == 6 and kept.triangles.sum() == 10 + 20 + 40 + 80 + 5 + 7


def test_a_box_that_straddles_a_plane_is_drawn() -> None:
    table = _table({7: ((-5.4, 0.0, -5.0), 1, 3, False)})  # x = −5 is the left plane at z = −5
    assert plan_frame(np.array([7]), table, VP, EYE).culled == 0


def test_missing_reps_are_skipped_and_counted() -> None:
    table = _table(MESHES)
    plan = plan_frame(np.array([9, 1, 5, 2]), table, VP, EYE, weights=np.array([0.5, 1.0, 0.5, 1.0]))
    assert plan.missing == 2 and len(plan) == 2 and plan.morphs == 0 and plan.unmorphed == 0


def test_draws_are_grouped_by_algorithm_in_the_callers_order() -> None:
    table = _table(MESHES)
    reps = np.array([1, 2, -3, 1 << 30, 3])
    plan = plan_frame(reps, table, VP, EYE, algorithms=np.array([2, 0, 2, 1, 0]),
                      levels=np.array([1.0, 2.0, 3.0, 4.0, 5.0]))
    order = _reps(table, plan)
    assert order == [2, 1 << 30, 1, -3]  # algorithm 0, then 1, then 2; rep 3 culled
    assert plan.draws.tolist() == [1, 1, 2]
    assert plan.triangles.tolist() == [20, 7, 10 + 5] and plan.vertices.tolist() == [15, 6, 8 + 4]
    assert plan.rows["level"].tolist() == [2.0, 4.0, 1.0, 3.0]
    # Each draw's command is its slot's template with baseInstance = its row.
    assert plan.commands[:, 4].tolist() == [0, 1, 2, 3]
    assert (plan.commands[:, :4] == table.command[plan.slots, :4]).all()
    assert plan.rows.dtype == DRAW and (plan.rows["tint"] == table.tint[plan.slots]).all()


def test_morph_weights_flags_and_counts() -> None:
    table = _table(MESHES)
    reps = np.array([1, 2, -3, 1 << 30])  # targets: no, yes, yes, no
    plan = plan_frame(reps, table, VP, EYE, weights=np.array([0.4, 0.25, -0.5, 1.0]))
    assert plan.morphs == 2 and plan.unmorphed == 1  # rep 1 asks to morph but has no target
    assert plan.rows["weight"].tolist() == [1.0, 0.25, 0.0, 1.0]  # below 0 counts as 0; static draws weigh 1
    assert plan.rows["flags"].tolist() == [0, FLAG_MORPH, FLAG_MORPH, 0]
    # A morphing draw costs the finer level's triangles.
    assert plan.triangles.tolist() == [10 + 20 + 5 + 7, 0, 0]


def test_an_empty_frame() -> None:
    plan = plan_frame(np.zeros(0, np.int64), _table(MESHES), VP, EYE, algorithms=np.zeros(0, np.int64))
    assert len(plan) == 0 and plan.draws.tolist() == [0, 0, 0] and plan.triangles.tolist() == [0, 0, 0]
    assert plan.commands.shape == (0, 5)


@pytest.mark.parametrize("kw, match", [
    ({"weights": np.ones(3)}, "aligned"),
    ({"weights": np.array([1.0, np.nan])}, "finite"),
    ({"algorithms": np.array([0, 3])}, "0..2"),
    ({"algorithms": np.array([0.5, 1.0])}, "integers"),
    ({"levels": np.array([0.0, np.inf])}, "finite"),
])
def test_bad_arguments_are_refused(kw, match) -> None:
    with pytest.raises(ValueError, match=match):
        plan_frame(np.array([1, 2]), _table(MESHES), VP, EYE, **kw)


def test_removed_reps_are_missing_and_their_slots_reused() -> None:
    table = _table(MESHES)
    table.vblock[table.meshes[2]] = 123
    assert table.remove(2) == (123, -1, -1, -1) and table.remove(2) is None
    assert table.remove(1 << 30) is not None
    plan = plan_frame(np.array([2, 1 << 30, 1]), table, VP, EYE)
    assert plan.missing == 2 and len(plan) == 1


def test_culling_is_relative_to_the_eye() -> None:
    table = _table({5: ((100.0, 0.0, -5.0), 1, 3, False)})
    assert plan_frame(np.array([5]), table, VP, np.array([100.0, 0.0, 0.0])).culled == 0
    assert plan_frame(np.array([5]), table, VP, EYE).culled == 1


def test_seen_marks_the_reps_asked_for_that_were_drawn() -> None:
    table = _table(MESHES)
    reps = np.array([9, 1, 3, 2, -3, 4])  # 9 is not resident; 3 and 4 are out of view
    plan = plan_frame(reps, table, VP, EYE)
    assert plan.seen.tolist() == [False, True, False, True, True, False]
    assert int(plan.seen.sum()) == len(plan) == reps.size - plan.missing - plan.culled
