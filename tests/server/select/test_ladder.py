"""The governor's ladder from a selection: chains of steps, priced by the vertices they change."""

from __future__ import annotations

import numpy as np
import pytest

from proto.messages import LADDER_DEPTH
from server.select.camera import View
from server.select.ladder import build_ladder, held_chain, prefetch

#: Three objects of 6 levels each (reps 0–5, 6–11, 12–17), coarsest first; vertices double per level.
N, K = 3, 6
REP_OBJECT = np.repeat(np.arange(N), K)
REP_VERTICES = np.tile(100 * 2 ** np.arange(K), N)
REP_FACES = 2 * REP_VERTICES
REP_BYTES = 12 * REP_VERTICES
REP_ERROR = np.tile(0.5 / 2.0 ** np.arange(K), N)
LO = np.array([[-1.0, 4.0, -1.0], [2.0, 6.0, -1.0], [-4.0, 8.0, -1.0]])
HI = LO + 2.0
CAM = View.of_pose([0, 0, 0], [0, 1, 0], [0, 0, 1], 60.0, (640, 360), np.array([[-10, -10, -10], [10, 20, 10]]))


def _arrays(resident):
    return dict(rep_object=REP_OBJECT, rep_faces=REP_FACES, rep_vertices=REP_VERTICES, object_lo=LO, object_hi=HI,
                resident=resident, eligible=np.ones(N * K, bool))


def test_chains_reach_down_through_held_levels_only_and_steps_are_counted_in_vertices():
    resident = np.zeros(N * K, bool)
    resident[[1, 2, 3, 4]] = True  # object 0 at level 4: levels 1–3 held below, none above
    resident[[8, 10, 11]] = True  # object 1 at level 4 (rep 10): level 3 (rep 9) missing, level 5 held
    resident[[12]] = True  # object 2 at its coarsest
    lad = build_ladder(np.array([4, 10, 12]), CAM, rep_error=REP_ERROR, **_arrays(resident))
    steps = sorted(zip(lad.rep.tolist(), lad.to.tolist()))
    assert steps == [(4, 1), (4, 2), (4, 3), (10, 11)]  # object 1's chain down stops at its gap
    # Each unit step costs the vertices it removes or adds; the client measures what a vertex costs.
    for r, t, c in zip(lad.rep, lad.to, lad.cost):
        finer, coarser = (t + 1, t) if t < r else (t, t - 1)
        assert c == REP_VERTICES[finer] - REP_VERTICES[coarser]
    assert lad.base == REP_VERTICES[[4, 10, 12]].sum()
    assert lad.shed == pytest.approx((REP_VERTICES[4] - REP_VERTICES[1]) / lad.base)
    assert np.all(np.diff(lad.value) >= 0) and np.all(lad.value >= 0)
    # Coarser steps of one chain lose more accuracy per vertex saved: the governor sheds them last.
    down = {t: v for r, t, v in zip(lad.rep, lad.to, lad.value) if r == 4}
    assert down[1] > down[2] > down[3]


def test_held_chain_stops_at_the_depth_and_at_another_object():
    resident = np.ones(N * K, bool)
    chain = held_chain(np.array([5, 6]), -1, rep_object=REP_OBJECT, resident=resident,
                       eligible=np.ones(N * K, bool))
    assert len(chain) == LADDER_DEPTH
    assert [rows.tolist() for rows, _ in chain] == [[0]] * LADDER_DEPTH  # rep 6 is object 1's coarsest
    assert [to.tolist() for _, to in chain] == [[4], [3], [2], [1]]


def test_prefetch_sends_coarser_levels_before_finer_ones():
    resident = np.zeros(N * K, bool)
    resident[[3, 9, 15]] = True  # every object at level 3, nothing around it
    reps = np.array([3, 9, 15])
    coarser = REP_BYTES[[2, 8, 14]].sum()
    got = prefetch(reps, CAM, rep_bytes=REP_BYTES, left=float(coarser), rep_error=REP_ERROR, **{
        k: v for k, v in _arrays(resident).items() if k != "rep_vertices"})
    assert got.tolist() == [2, 8, 14]
    more = prefetch(reps, CAM, rep_bytes=REP_BYTES, left=float(coarser + REP_BYTES[4]), rep_error=REP_ERROR, **{
        k: v for k, v in _arrays(resident).items() if k != "rep_vertices"})
    assert set(more.tolist()) >= {2, 8, 14} and len(more) == 4
