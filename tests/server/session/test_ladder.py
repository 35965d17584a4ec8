"""The governor's ladder as real selections build it: a simulated client on a simulated link (``test_pipeline``)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from proto.messages import LADDER_DEPTH, Delta, FrameReport

from server.session import SessionConfig

from .test_pipeline import Link, scenes  # noqa: F401  (the fixture)


def test_each_delta_carries_a_ladder_over_what_the_client_holds(scenes):  # noqa: F811
    link = Link(scenes, one_way=0.03, budget=0.004, governor=True)
    index = link.index
    link.run(6.0)
    deltas = [d for _, d in link.deltas]
    assert len(deltas) >= 6
    held = set()
    ups = downs = deep = 0
    for d in deltas:
        held |= {a.rep for a in d.add}
        held -= set(d.drop)
        rep, to = np.asarray(d.ladder_rep, np.int64), np.asarray(d.ladder_to, np.int64)
        assert set(rep.tolist()) <= set(d.selection)
        depth = np.abs(to - rep)
        assert np.all((depth >= 1) & (depth <= LADDER_DEPTH)) and np.all(index.rep_object[to] == index.rep_object[rep])
        # Chains are contiguous: a step of depth d comes with the one of depth d − 1 on the same side.
        steps = set(zip(rep.tolist(), (to - rep).tolist()))
        assert all((r, s - np.sign(s)) in steps for r, s in steps if abs(s) > 1)
        assert set(to.tolist()) <= held  # a step only goes where the client holds the level
        assert np.all(np.diff(d.ladder_value) >= 0) and np.all(np.asarray(d.ladder_cost) > 0)
        assert d.ladder_base > 0
        ups += int((to > rep).sum())
        downs += int((to < rep).sum())
        deep += int((to < rep - 1).sum())
    # Coarser levels held (chains deeper than one level among them), finer ones sent ahead with the bytes left.
    assert downs > 0 and ups > 0 and deep > 0


def _governed_frames(spare: bool):
    """Frame reports of a governed client that says, every frame, whether it had time to spare."""
    def report(frame, t, drawn):
        return FrameReport(frame=frame, t=t, time=0.003, triangles=20_000, vertices=12_000, draws=40,
                           selection=drawn, governor_cost=12_000.0, governor_spare=spare)
    return report


def test_more_levels_are_sent_ahead_while_the_governor_has_time_to_spare(scenes):  # noqa: F811
    """A governor that drew every step up and still had time left asks, by its reports, for finer levels: the
    server sends more ahead for its ladder, and no more than the usual while the governor is bound."""
    ahead, spare = {}, {}
    # An allowance small enough to bind on the demo scene, whose few levels are otherwise all sent ahead at once.
    config = SessionConfig(ahead_share=0.0, ahead_floor=8 * 1024)
    for says in (False, True):
        link = Link(scenes, one_way=0.03, budget=0.004, governor=True, report=_governed_frames(says), config=config)
        link.run(8.0)
        rep_bytes = link.session.pipeline.table.rep_bytes
        sent = 0
        for _, d in link.deltas[2:]:  # from the third delta on: the reports have had a second to tell
            beyond = [a.rep for a in d.add if a.rep not in set(d.selection)]
            sent += int(rep_bytes[beyond].sum())
        ahead[says], spare[says] = sent, link.session.pipeline.spare
    assert spare[False] == 0.0 and spare[True] > 0.9
    assert ahead[True] > 1.5 * ahead[False] > 0


@pytest.mark.parametrize("bad", [dict(ahead_gain=-1.0), dict(ahead_gain=math.inf), dict(ahead_gain=math.nan),
                                 dict(ahead_share=-0.1), dict(ahead_floor=-1)])
def test_the_allowance_for_levels_sent_ahead_refuses_bad_settings(bad):
    with pytest.raises(ValueError, match="must be finite and non-negative"):
        SessionConfig(**bad)
    SessionConfig(**{k: 0 for k in bad})  # zero is allowed: nothing sent ahead, or no growth


def test_without_the_governor_no_ladder_is_sent(scenes):  # noqa: F811
    link = Link(scenes, one_way=0.03, budget=0.004)
    link.run(3.0)
    assert link.deltas and all(not d.ladder_rep and d.ladder_base == 0 for _, d in link.deltas)


@pytest.mark.parametrize("bad", [
    dict(ladder_rep=[1], ladder_to=[2, 3], ladder_cost=[1e-4], ladder_value=[1.0]),  # columns differ
    dict(ladder_rep=[6], ladder_to=[6 + LADDER_DEPTH + 1], ladder_cost=[1e-4], ladder_value=[1.0]),  # too deep
    dict(ladder_rep=[1], ladder_to=[1], ladder_cost=[1e-4], ladder_value=[1.0]),  # no step
    dict(ladder_rep=[5], ladder_to=[4], ladder_cost=[1e-4], ladder_value=[1.0]),  # not selected
    dict(ladder_rep=[1, 2], ladder_to=[0, 3], ladder_cost=[1e-4, 1e-4], ladder_value=[2.0, 1.0]),  # unordered
    dict(ladder_rep=[1], ladder_to=[0], ladder_cost=[float("nan")], ladder_value=[1.0]),  # not finite
    dict(ladder_rep=[1], ladder_to=[0], ladder_cost=[0.0], ladder_value=[1.0]),  # a step costs something
    dict(ladder_rep=[1], ladder_to=[0], ladder_cost=[1e-4], ladder_value=[float("inf")]),
    dict(ladder_base=-1.0),
])
def test_the_protocol_refuses_a_malformed_ladder(bad):
    with pytest.raises(ValidationError):
        Delta(seq=1, t0=0.0, t1=0.5, selection=[1, 2, 6], **bad)
    Delta(seq=1, t0=0.0, t1=0.5, selection=[1, 2], ladder_rep=[1, 2], ladder_to=[0, 3], ladder_cost=[1e-4, 2e-4],
          ladder_value=[1.0, 2.0], ladder_base=0.01)


@pytest.mark.parametrize("governor", [False, True])
def test_a_governed_session_gets_collapse_maps_without_morphing(scenes, governor):  # noqa: F811
    """The governor ramps between adjacent levels by their collapse maps: a session that governs gets them with
    its adds even when it does not morph; one that does neither does not pay their bytes."""
    link = Link(scenes, one_way=0.03, budget=0.004, morph=False, predict=False, governor=governor)
    link.run(3.0)
    index = link.index
    adds = [a for _, d in link.deltas for a in d.add if a.kind == "mesh" and index.rep_morph[a.rep]]
    assert adds
    assert all((a.morph is not None) == governor for a in adds)
