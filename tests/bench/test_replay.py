"""bench.replay: a traced frame drawn again matches the client's own, the finest cut, the upload cache."""

from __future__ import annotations

import numpy as np
import pytest

from bench import quality
from bench.replay import Replayer, finest_cut, tree_groups
from client.records import FrameTrace
from proto.tour import Tour
from server.scene.index import TREES
from server.scene.store import SceneStore
from server.select.morph import rep_parents

VIEW = (160, 90)


def _uniform(index, level: int, t: float) -> FrameTrace:
    """A trace drawing every flat object at ``level`` (clamped to its chain), static, from the tour's pose at t."""
    obj = np.flatnonzero(index.flat)
    first = index.rep_first[obj].astype(np.int64)
    reps = first + np.minimum(level, index.rep_count[obj] - 1)
    eye, forward, up = Tour(index.tour).pose_at(t)
    return FrameTrace(t, first, (reps - first).astype(np.float64), reps, np.ones(reps.size), eye=eye,
                      forward=forward, up=up, drawn=np.ones(reps.size, bool))


def test_finest_cut_is_a_cover_of_the_leaves_without_ancestors(denhaag_store) -> None:
    with SceneStore.open(denhaag_store) as store:
        ix = store.index
        assert ix.height > 1 and (ix.object_parent >= 0).any()  # there is a hierarchy to cut
        cut = finest_cut(ix)
        parent = rep_parents(ix.rep_level, ix.rep_object, ix.object_parent, ix.rep_first, ix.rep_count)
        in_cut = np.zeros(ix.n_representations, bool)
        in_cut[cut] = True
        anc = parent[cut]
        while (anc >= 0).any():  # climb every cut rep's ancestry at once: none of them is in the cut
            assert not in_cut[anc[anc >= 0]].any()
            anc = np.where(anc >= 0, parent[np.maximum(anc, 0)], -1)
        objects = ix.rep_object[cut]
        assert np.array_equal(np.sort(objects), np.flatnonzero(ix.flat))  # every mesh leaf once, nothing else
        assert np.array_equal(ix.rep_level[cut], ix.rep_count[objects] - 1)  # at its finest level
        groups = tree_groups(ix)
        assert groups.size and (ix.object_kind[ix.rep_object[groups]] == TREES).all()


def test_replay_reproduces_the_clients_last_frame(denhaag_store, tmp_path) -> None:
    from PIL import Image

    from bench.demo import ServerProcess
    from client.app import run_client

    shot = tmp_path / "last.png"
    with ServerProcess([denhaag_store]) as server:
        run = run_client(server.url, "denhaag", duration=3.0, viewport=VIEW, target_frame_time=0.05,
                         solver="mixed", trace=True, screenshot=shot)
    assert not run.errors and len(run.trace) == len(run.frames) > 5
    last = run.trace[-1]
    assert last.drawn.sum() > 0
    client = np.asarray(Image.open(shot).convert("RGB"))
    with Replayer(denhaag_store, viewport=VIEW) as replayer:
        again = replayer.drawn(last)
        assert replayer.loaded <= int(last.drawn.sum())  # lazily: the reps drawn (and in view), no more
        assert quality.psnr(client, again) >= 50.0
        assert (np.abs(client.astype(int) - again).max(axis=2) > 0).mean() < 1e-3
        loaded = replayer.loaded
        np.testing.assert_array_equal(replayer.drawn(last), again)
        assert replayer.loaded == loaded  # uploaded once


def test_a_tight_budget_evicts_but_draws_the_same(demo_store) -> None:
    with SceneStore.open(demo_store) as store:
        coarse, fine = _uniform(store.index, 0, 2.0), _uniform(store.index, 99, 2.0)
        with Replayer(store, viewport=VIEW) as roomy, Replayer(store, viewport=VIEW, budget_bytes=1) as tight:
            want = [roomy.drawn(coarse), roomy.drawn(fine)]
            got = [tight.drawn(coarse), tight.drawn(fine)]
            assert tight.resident_bytes > 0  # the frame's own reps stay, over budget or not
            held = np.flatnonzero(tight._resident)
            assert set(held.tolist()) <= set(fine.rep.tolist())  # the coarse frame's were freed
            got.append(tight.drawn(coarse))
            for a, b in zip(got, want + want[:1]):
                np.testing.assert_array_equal(a, b)
            assert tight.loaded > roomy.loaded


def test_full_detail_inherits_algorithms_and_refuses_foreign_traces(demo_store) -> None:
    with SceneStore.open(demo_store) as store, Replayer(store, viewport=VIEW) as replayer:
        fine = _uniform(store.index, 99, 2.0)
        lit = FrameTrace(**{**fine.__dict__, "algorithm": np.ones(fine.rep.size, np.int64)})
        flat = replayer.full(fine.eye, fine.forward, fine.up)
        np.testing.assert_array_equal(replayer.drawn(fine), flat)  # no hierarchy, no trees: finest = full
        shaded = replayer.full(lit.eye, lit.forward, lit.up, algorithms_from=lit)
        np.testing.assert_array_equal(replayer.drawn(lit), shaded)
        assert not np.array_equal(shaded, flat)
        bad = FrameTrace(**{**fine.__dict__, "rep": fine.rep + store.index.n_representations})
        with pytest.raises(ValueError):
            replayer.drawn(bad)
        with pytest.raises(ValueError):
            replayer.drawn(FrameTrace(**{**fine.__dict__, "eye": None}))
