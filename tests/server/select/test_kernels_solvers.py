"""The compiled kernels (numba) against the numpy reference: same hulls, same starts, same fill rounds,
same chosen options and totals for the greedy and the incremental solver, on random instances and on
the edge cases (invalid options, infinite and NaN costs and benefits, zero budget, every option over
the cap, no objects, one option per object)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from server.select import kernels
from server.select.solvers import greedy, incremental
from server.select.solvers.candidates import NO_LIMIT, Candidates


@pytest.fixture(autouse=True)
def compiled():
    kernels.use_kernels(True)
    yield
    kernels.use_kernels(None)


def numpy_only(fn, *args, **kw):
    kernels.use_kernels(False)
    try:
        return fn(*args, **kw)
    finally:
        kernels.use_kernels(True)


# Costs and benefits from small sets (ties, duplicates, collinear points) plus the awkward values.
ODD = st.sampled_from([0.0, -1.0, np.inf, -np.inf, np.nan])


@st.composite
def wild(draw, n=st.integers(0, 12), k=st.integers(1, 5)):
    """Any (n, K) candidates: costs in any order, invalid options, 0, negative, ±inf, NaN."""
    n, k = draw(n), draw(k)
    num = st.one_of(st.integers(1, 6).map(float), st.floats(1e-3, 10.0), ODD)
    benefit = draw(arrays(np.float64, (n, k), elements=num))
    cost = draw(arrays(np.float64, (n, k), elements=num))
    valid = draw(arrays(np.bool_, (n, k)))
    cap = draw(st.one_of(st.none(), st.floats(0.0, 40.0)))
    return Candidates.of(benefit, cost, valid), cap


@settings(max_examples=400, deadline=None)
@given(wild())
def test_hull_kernel_equals_the_numpy_hull(inst):
    cand, cap = inst
    got = greedy.upper_hull(cand, cap)
    ref = greedy.upper_hull_numpy(cand, cap)
    assert got.shape == ref.shape
    np.testing.assert_array_equal(got.count, ref.count)
    ref_opt = np.broadcast_to(np.arange(cand.k)[:, None], ref.shape) if ref.opt is None else ref.opt
    for i in range(cand.n):
        c = int(ref.count[i])
        np.testing.assert_array_equal(got.opt[:c, i], ref_opt[:c, i])
        np.testing.assert_array_equal(got.value[:c, i], ref.value[:c, i])
        np.testing.assert_array_equal(got.d_cost[:c, i], ref.d_cost[:c, i])
        assert (got.value[c:, i] == -np.inf).all() and (got.d_cost[c:, i] == 0).all()
    # The best single option: the usable option of highest benefit, first in flat order.
    ok = greedy._usable(cand, cap)
    if ok.any() and np.isfinite(cand.benefit[ok]).any():
        top = cand.benefit[ok].max()
        assert got.best == int(np.flatnonzero(ok.ravel() & (cand.benefit.ravel() == top))[0])
    else:
        assert got.best == -1


@settings(max_examples=300, deadline=None)
@given(wild(), st.integers(0, 2**32 - 1))
def test_start_kernel_equals_the_numpy_start(inst, seed):
    cand, cap = inst
    rng = np.random.default_rng(seed)
    cand = Candidates.of(cand.benefit, cand.cost, cand.valid, previous=rng.integers(-2, cand.k + 2, cand.n))
    hull = greedy.upper_hull(cand, cap)
    np.testing.assert_array_equal(incremental.start(cand, hull), incremental.start_numpy(cand, hull))
    # The hull kernel finds the same start while it builds the hulls.
    if cand.n:
        fused = greedy._hull_compiled(kernels.compiled(), cand, cap, scratch=True,
                                      previous=cand.previous.astype(np.int64))
        np.testing.assert_array_equal(fused.begin, incremental.start_numpy(cand, hull))


def check_same(cand, budget, got, ref, *, exact_levels: bool):
    assert got.level.shape == ref.level.shape == (cand.n,)
    rows = np.flatnonzero(got.level >= 0)
    assert cand.valid[rows, got.level[rows]].all()
    spent = float(cand.cost[rows, got.level[rows]].sum())
    assert spent <= budget * (1 + 1e-9) + 1e-12
    assert got.cost == pytest.approx(spent, rel=1e-9, abs=1e-12)
    assert got.benefit == pytest.approx(float(cand.benefit[rows, got.level[rows]].sum()), rel=1e-9, abs=1e-12)
    assert got.benefit == pytest.approx(ref.benefit, rel=1e-9, abs=1e-12)
    if exact_levels:
        np.testing.assert_array_equal(got.level, ref.level)
    assert got.stats["stopped"] == ref.stats["stopped"] == "done"


def tie_free(rng, n, k, *, concave: bool, invalid: float = 0.0, algorithms: int = 1):
    """Random candidates whose values have no ties (continuous draws)."""
    cost = np.cumsum(rng.uniform(0.01, 1.0, (n, k)), axis=1)
    if concave:
        benefit = np.cumsum(np.sort(rng.uniform(0.0, 1.0, (n, k)), axis=1)[:, ::-1], axis=1)
    else:
        benefit = rng.uniform(0.0, 3.0, (n, k))
    if algorithms > 1:
        order = rng.permuted(np.tile(np.arange(k), (n, 1)), axis=1)
        cost = np.take_along_axis(cost, order, axis=1)
        benefit = np.take_along_axis(benefit, order, axis=1)
    valid = rng.random((n, k)) >= invalid
    return Candidates.of(benefit, cost, valid, algorithms=algorithms)


@pytest.mark.parametrize("seed", range(12))
def test_greedy_kernels_choose_what_the_numpy_greedy_chooses(seed):
    rng = np.random.default_rng(seed)
    n, k = int(rng.integers(1, 3000)), int(rng.integers(1, 6))
    cand = tie_free(rng, n, k, concave=bool(seed % 2), invalid=0.2 * (seed % 3 == 0), algorithms=1 + (seed % 4 == 1))
    for share in (0.0, 0.05, 0.3, 0.7, 1.2):
        budget = float(np.where(cand.valid, cand.cost, 0).max(axis=1).sum() * share)
        got = greedy.solve(cand, budget)
        ref = greedy.solve_numpy(cand, budget)
        check_same(cand, budget, got, ref, exact_levels=True)
        assert got.stats["threshold"] == ref.stats["threshold"]
        assert got.stats["increments"] == ref.stats["increments"]


def test_greedy_kernels_on_a_large_instance_need_the_radix_cut():
    from bench.select import instance

    cand, budget = instance(200_000, 4, 3)
    got, ref = greedy.solve(cand, budget), greedy.solve_numpy(cand, budget)
    check_same(cand, budget, got, ref, exact_levels=True)


@settings(max_examples=300, deadline=None)
@given(wild(n=st.integers(0, 25)), st.floats(0.0, 60.0), st.integers(0, 2**32 - 1))
def test_greedy_and_incremental_kernels_on_wild_candidates(inst, budget, seed):
    cand, _ = inst
    rng = np.random.default_rng(seed)
    cand = Candidates.of(cand.benefit, cand.cost, cand.valid, previous=rng.integers(-1, cand.k, cand.n))
    ref = greedy.solve_numpy(cand, budget)
    for got in (greedy.solve(cand, budget), incremental.solve(cand, budget),
                incremental.solve(cand, budget, state={"threshold": float(rng.uniform(0.01, 10))})):
        rows = np.flatnonzero(got.level >= 0)
        assert cand.valid[rows, got.level[rows]].all()
        assert float(cand.cost[rows, got.level[rows]].sum()) <= budget * (1 + 1e-9) + 1e-12
        # Ties (hypothesis loves them) may be broken either way: the same greedy up to one increment.
        if ref.benefit > 0:
            assert got.benefit >= 0.5 * ref.benefit - 1e-9


@pytest.mark.parametrize("budget", [0.0, -1.0, float("nan")])
def test_zero_budget_and_no_objects(budget):
    cand = tie_free(np.random.default_rng(0), 50, 3, concave=True)
    for solve in (greedy.solve, incremental.solve):
        r = solve(Candidates.of(cand.benefit, cand.cost, previous=np.zeros(50, np.int64)), budget)
        assert (r.level == -1).all() and r.cost == 0.0 and r.benefit == 0.0
    empty = Candidates.of(np.zeros((0, 4)), np.zeros((0, 4)), previous=np.zeros(0, np.int64))
    assert greedy.solve(empty, 1.0).level.shape == incremental.solve(empty, 1.0).level.shape == (0,)
    assert greedy.upper_hull(empty).shape == (4, 0)


def test_every_option_over_the_cap_and_infinite_costs():
    b = np.array([[1.0, 2.0], [3.0, 4.0]])
    c = np.array([[5.0, np.inf], [np.inf, 6.0]])
    for budget in (4.0, 5.5):
        got, ref = greedy.solve(Candidates.of(b, c), budget), greedy.solve_numpy(Candidates.of(b, c), budget)
        assert got.level.tolist() == ref.level.tolist()
        assert got.benefit == ref.benefit and got.cost == ref.cost
    assert greedy.solve(Candidates.of(b, c), 4.0).level.tolist() == [-1, -1]
    assert greedy.solve(Candidates.of(b, c), 5.5).level.tolist() == [0, -1]


def test_one_option_per_object():
    rng = np.random.default_rng(5)
    cand = tie_free(rng, 1000, 1, concave=True, invalid=0.1)
    budget = float(cand.cost.sum() * 0.4)
    check_same(cand, budget, greedy.solve(cand, budget), greedy.solve_numpy(cand, budget), exact_levels=True)


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("n", [300, 40_000])
def test_incremental_kernels_match_the_numpy_incremental(seed, n):
    """Tie-free coherent frames: the one-pass band (last frame's threshold, or one estimated on a sample
    for many objects), and the radix path, choose what the numpy band and the greedy choose."""
    rng = np.random.default_rng(seed)
    k = int(rng.integers(1, 6))
    base = tie_free(rng, n, k, concave=bool(seed % 2), invalid=0.1 * (seed % 3 == 0), algorithms=1 + (seed % 4 == 1))
    budget = float(np.where(base.valid, base.cost, 0).max(axis=1).sum() * rng.uniform(0.1, 0.8))
    last = greedy.solve(base, budget)
    drift = rng.uniform(0.97, 1.03, (n, 1))
    previous = np.where(rng.random(n) < 0.01, -1, last.level)
    cand = Candidates.of(base.benefit * drift, base.cost, base.valid, algorithms=base.algorithms, previous=previous)
    fresh = greedy.solve_numpy(cand, budget)
    for state in (None, {"threshold": last.stats["threshold"]}, {"threshold": 1e-6}, {"threshold": 1e9}):
        got = incremental.solve(cand, budget, state=state)
        ref = incremental.solve_numpy(cand, budget, state=state)
        check_same(cand, budget, got, ref, exact_levels=True)
        check_same(cand, budget, got, fresh, exact_levels=True)
        assert "fallback" not in got.stats
        assert got.stats["moves"] == int(np.abs(_steps(cand, budget, got.level) - _steps(cand, budget, previous)).sum())


def _steps(cand, budget, level):
    """Hull increments of each object's option (clamped to the hull point below, like ``start``)."""
    hull = greedy.upper_hull_numpy(cand, budget)
    return incremental.start_numpy(Candidates.of(cand.benefit, cand.cost, cand.valid, previous=level), hull)


def test_fill_kernel_equals_the_numpy_fill():
    rng = np.random.default_rng(11)
    cand = tie_free(rng, 2000, 4, concave=False, invalid=0.1)
    hull = greedy.upper_hull(cand)
    ref_hull = greedy.upper_hull_numpy(cand)
    start = rng.integers(0, 2, cand.n).astype(np.int64) * (hull.count > 0)
    spent = float(sum(hull.d_cost[:s, i].sum() for i, s in enumerate(start)))
    a, b = start.copy(), start.copy()
    ra = greedy.fill(hull, a, spent * 0.2, NO_LIMIT, 64)
    rb = greedy.fill_numpy(ref_hull, b, spent * 0.2, NO_LIMIT, 64)
    assert ra == rb
    np.testing.assert_array_equal(a, b)


def test_an_expired_limit_stops_the_compiled_paths_too():
    from server.select.solvers.candidates import TimeLimit

    rng = np.random.default_rng(3)
    cand = tie_free(rng, 400, 4, concave=True)
    cand = Candidates.of(cand.benefit, cand.cost, previous=np.full(400, 3))
    budget = float(cand.cost[:, 1].sum())
    expired = TimeLimit(clock=lambda: 1.0, deadline=0.0)
    r = incremental.solve(cand, budget, limit=expired)
    assert r.stats["stopped"] == "limit" and r.cost <= budget * (1 + 1e-12)
    assert r.benefit <= incremental.solve(cand, budget).benefit + 1e-9
    g = greedy.solve(cand, budget, limit=expired)
    assert g.stats["stopped"] == "limit" and g.cost <= budget * (1 + 1e-12)


def test_numpy_mode_and_kernel_mode_agree_through_the_public_solvers():
    rng = np.random.default_rng(2)
    cand = tie_free(rng, 5000, 3, concave=True)
    budget = float(cand.cost[:, 1].sum())
    got = greedy.solve(cand, budget)
    ref = numpy_only(greedy.solve, cand, budget)
    check_same(cand, budget, got, ref, exact_levels=True)


def test_kernels_compile_without_a_usable_cache(tmp_path):
    """Kernels imported from a zip (no directory beside them to cache in) with NUMBA_CACHE_DIR unset and a
    user cache directory that cannot exist: numba finds no usable cache and they compile in memory.
    (Slow: a full compile, 10–25 s.)"""
    import zipfile

    root = os.path.abspath(os.path.join(os.path.dirname(kernels.__file__), "..", "..", ".."))
    with zipfile.ZipFile(tmp_path / "kernels.zip", "w") as z:
        for folder in ("server", "server/select", "server/select/kernels"):
            for name in sorted(os.listdir(os.path.join(root, folder))):
                if name.endswith(".py"):
                    z.write(os.path.join(root, folder, name), f"{folder}/{name}")
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env.update(HOME="/dev/null", XDG_CACHE_HOME="/dev/null/cache", PYTHONDONTWRITEBYTECODE="1")
    code = textwrap.dedent(f"""
        import sys
        import time
        sys.path.insert(0, {str(tmp_path / "kernels.zip")!r})
        began = time.perf_counter()
        from server.select import kernels
        assert kernels.__file__.startswith({str(tmp_path / "kernels.zip")!r}), kernels.__file__
        kernels.use_kernels(True)  # raises if a kernel failed to compile
        print(round(time.perf_counter() - began, 1))
    """)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    assert float(out.stdout.split()[-1]) >= 0
