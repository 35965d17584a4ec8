"""The compiled fold of frame reports is the online cost model's own fold: the same frames folded one by one
by the Python reference and in batches by the kernel leave the same model."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from server.select import cost_online, rls
from server.select.cost_online import MODELS, OnlineCostModel
from server.select.kernels import choose as choose_kernel
from server.select.kernels import fold as fold_kernel


def _frames(seed: int, n: int, regime: str):
    """Frames of a simulated renderer: per-algorithm loads, fill-bound stretches, a machine that changes speed,
    empty frames and absurd ones, as (time, triangles, vertices, pixels, draws, splats)."""
    rng = np.random.default_rng(seed)
    out = []
    speed = 1.0
    for i in range(n):
        if regime == "step" and i == n // 2:
            speed = rng.choice([0.4, 2.5])
        if regime == "drift":
            speed *= 1.01
        algs = rng.random(3) < [0.9, 0.5, 0.2]
        v = np.where(algs, rng.integers(100, 60_000, 3), 0).astype(float)
        f = v * rng.uniform(1.2, 2.0)
        p = np.where(algs, rng.integers(1_000, 900_000, 3), 0).astype(float)
        d = np.where(algs, rng.integers(1, 300, 3), 0).astype(float)
        s = float(rng.integers(0, 50_000)) if rng.random() < 0.3 else 0.0
        geo = 1.5e-7 * f + 2e-7 * v
        fill = 4e-9 * p
        t = speed * (0.002 + np.maximum(geo, fill).sum() + 1e-5 * d.sum() + 2e-8 * s) * rng.lognormal(0, 0.05)
        if rng.random() < 0.03:
            t *= 6.0  # a spike
        if rng.random() < 0.03:
            v[:], f[:], s = 0.0, 0.0, 0.0  # drew nothing
        if rng.random() < 0.01:
            t = -1.0  # refused
        out.append((t, f, v, p, d, s))
    return out


def _compare(a: OnlineCostModel, b: OnlineCostModel, rtol: float = 1e-9) -> None:
    a.flush(), b.flush()
    assert (a.chosen, a._pending, a._count, a.frames) == (b.chosen, b._pending, b._count, b.frames)
    assert a.least == b.least and list(a._ratios) == pytest.approx(list(b._ratios), rel=rtol)
    for name in MODELS:
        ra, rb = a.rungs[name], b.rungs[name]
        scale = np.abs(ra.full()).max()
        assert np.allclose(ra.full(), rb.full(), rtol=rtol, atol=rtol * scale)
        assert np.allclose(ra.rls.P, rb.rls.P, rtol=rtol, atol=rtol * np.abs(ra.rls.P).max())
        assert list(ra.fill) == list(rb.fill) and ra.sides == rb.sides and (ra.seen == rb.seen).all()
        assert list(ra.errors) == pytest.approx(list(rb.errors), rel=rtol, abs=1e-15)
        assert list(ra.rls.residuals) == pytest.approx(list(rb.rls.residuals), rel=rtol, abs=1e-12)
        assert (ra.rls.updates, ra.rls.changes, len(ra.rls._up), len(ra.rls._down)) == (
            rb.rls.updates, rb.rls.changes, len(rb.rls._up), len(rb.rls._down))
        assert (ra.rls._hi, ra.rls._lo) == pytest.approx((rb.rls._hi, rb.rls._lo), rel=rtol, abs=1e-12)
        assert ra.c_vertex() == pytest.approx(rb.c_vertex(), rel=rtol)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(1, 200), regime=st.sampled_from(["steady", "step", "drift"]),
       tail=st.sampled_from([0.0, 0.004]))
@example(seed=234, n=1, regime="steady", tail=0.0)  # a first frame both sides explain exactly: a tie
@example(seed=33554432, n=89, regime="drift", tail=0.0)  # a never-excited term at its bound ± rounding (BOX_TIE)
def test_the_kernel_folds_each_frame_as_the_reference_does(seed, n, regime, tail):
    """From the same state, one frame folded by the kernel and by the Python reference gives the same model,
    to rounding. (Along a whole sequence rounding may grow: the fit is ill-conditioned while the terms are
    collinear, and a change detector or a bound can trip one frame apart — so each step is compared.)"""
    reference = OnlineCostModel()
    reference.tail_min_time = tail
    for frame in _frames(seed, n, regime):
        kernel = copy.deepcopy(reference)
        kernel.batch = True
        assert kernel.observe(*frame) == reference.observe(*frame)
        _compare(reference, kernel)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(1, 200), regime=st.sampled_from(["steady", "step", "drift"]),
       batch=st.integers(2, 12))
def test_frames_folded_in_batches_equal_frames_folded_one_at_a_time(seed, n, regime, batch):
    """A selection folds the reports of its τ at once: the model is the one that folding each as it came gives."""
    single, batched = OnlineCostModel(batch=True), OnlineCostModel(batch=True)
    for i, frame in enumerate(_frames(seed, n, regime)):
        single.observe(*frame)
        single.flush()
        batched.observe(*frame)
        if (i + 1) % batch == 0:
            batched.flush()
    _compare(single, batched, rtol=0.0)
    assert single.to_state() == batched.to_state()


def test_a_step_change_is_detected_and_the_batch_waits_for_a_read():
    frames = _frames(7, 240, "step")
    batched = OnlineCostModel(batch=True)
    used = [batched.observe(*frame) for frame in frames[:8]]
    assert batched.frames == 0 and 0 < len(batched._queue) <= 8  # nothing folded until the model is read ...
    assert batched.updates == sum(used) > 0 and not batched._queue  # ... and then all of it
    for frame in frames[8:]:
        batched.observe(*frame)
    batched.flush()
    assert sum(r.rls.changes for r in batched.rungs.values()) > 0  # the step tripped the detector
    assert len(batched._queue) == 0


def test_the_kernel_keeps_the_models_constants():
    assert fold_kernel.RESCALE_SHARE == rls.RESCALE_SHARE
    assert fold_kernel.SECONDARY == cost_online.SECONDARY and fold_kernel.YOUNG == cost_online.YOUNG
    assert fold_kernel.TIE == cost_online.TIE
    assert choose_kernel.REGIME == (cost_online.REGIME_FRAMES, cost_online.REGIME_ERROR, cost_online.REGIME_RATIO)


def test_fsum_is_correctly_rounded():
    rng = np.random.default_rng(1)
    for _ in range(200):
        a = rng.standard_normal(rng.integers(1, 70)) * 10.0 ** rng.integers(-8, 8, 1)
        a[rng.random(a.size) < 0.2] *= 1e12
        assert choose_kernel._fsum(a, 0, a.size) == math.fsum(a)
    assert choose_kernel._fsum(np.array([1e100, 1.0, -1e100, 1e-100]), 0, 4) == math.fsum([1e100, 1.0, -1e100, 1e-100])


@settings(max_examples=200, deadline=None)
@given(st.integers(1, 12), st.integers(0, 12), st.one_of(st.just(0.0), st.floats(1e-9, 1e-3)), st.integers(0, 2**32 - 1))
def test_the_projections_solve_is_lstsqs_minimum_norm_answer(na, rank, ridge, seed):
    """``_project``'s solve of a principal block of the covariance (symmetric, often near-singular: collinear
    terms) gives lstsq's answer, the dropped directions included."""
    rng = np.random.default_rng(seed)
    b = rng.standard_normal((na, min(rank, na))) * np.exp(3.0 * rng.standard_normal(min(rank, na)))
    m = b @ b.T + ridge * np.diag(rng.random(na))
    m = (m + m.T) / 2
    rhs = rng.standard_normal(na)
    cut = fold_kernel._EPS * na
    s = np.linalg.svd(m, compute_uv=False)
    # A singular value within a factor 10 of lstsq's cut is dropped or kept by rounding: either answer is right.
    assume(not ((s > cut * s[0] / 10) & (s < cut * s[0] * 10)).any())
    want = np.linalg.lstsq(m, rhs, rcond=cut)[0]
    got = fold_kernel._solve_small(m, rhs, na)
    kept = s[s > cut * s[0]]
    cond = kept[0] / kept[-1] if kept.size else 1.0  # of the part both solve: their rounding differs by ~eps·cond
    scale = max(np.abs(want).max(), 1e-300)
    assert np.abs(got - want).max() <= max(1e-9, 1e-13 * na * cond) * scale


def test_a_snapshot_keeps_the_frames_not_yet_folded():
    """A session saves more often than it selects: its snapshot holds the frames still queued, unfolded, and the
    restored model folds them as the original does."""
    frames = _frames(3, 40, "steady")
    a = OnlineCostModel(batch=True)
    for frame in frames[:30]:
        a.observe(*frame)
    a.flush()
    for frame in frames[30:]:
        a.observe(*frame)
    state = a.to_state()
    assert a._queue and len(state["queue"]) == len(a._queue)  # nothing folded by the snapshot
    b = OnlineCostModel(batch=True)
    b.from_state(state)
    a.flush(), b.flush()
    assert b.frames == a.frames > 30 and b.to_state() == a.to_state()
    with pytest.raises(ValueError, match="queue"):
        OnlineCostModel(batch=True).from_state({**state, "queue": [[0.01, [1.0, 2.0], False]]})
    c = OnlineCostModel(batch=True)
    c.from_state({k: v for k, v in state.items() if k != "queue"})  # a snapshot from before the queue
    assert c._queue == []
