"""The failure scenarios (``bench.scenarios``): their paths, their criteria on crafted frames, and one real run.

The real run (small demo store, short phases) checks the structure of the results and the criteria that
do not depend on timing — the budget held or the coarsest cut drawn, no level jumps — never a PASS that
a loaded machine could flip.
"""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from bench.methods import METHODS as _METHODS
from bench.scenarios import paths as sc_paths
from bench.scenarios import run as sc_run
from bench.scenarios.measures import coverage, level_jumps, recovery_time, reset_times, window_stats
from bench.scenarios.paths import Anchor, anchor_of, oscillation_path, spin_path, straight_path, tour_segment, turn_path
from bench.scenarios.run import SCENARIOS, Context, below_coarsest, print_results, run_scenarios
from bench.scenarios.verdicts import (
    below_coarsest_verdict, drift_verdict, network_verdict, oscillation_verdict, spin_verdict, turn_verdict,
)
from client.records import FrameRecord, FrameTrace
from proto.tour import Tour
from server.scene.store import SceneStore

#: (solver, predict, morph) of each method, as a session is asked for it.
METHODS = {n: (m.solver, m.predict, m.morph) for n, m in _METHODS.items()}

ANCHOR = Anchor(eye=np.array([1.0, 2.0, 3.0]), yaw=math.radians(-90.0), pitch=math.radians(-12.0), speed=1.2,
                source="test")


def _yaw(forward: np.ndarray) -> np.ndarray:
    return np.unwrap(np.arctan2(forward[:, 1], forward[:, 0]))


def _frame(t: float, ms: float, seq: int = 1, **kw) -> FrameRecord:
    fields = dict(frame=0, t=t, time=ms / 1e3, triangles=kw.pop("triangles", 100), vertices=100, draws=1, seq=seq,
                  cost_coeff=kw.pop("cost_coeff", 1e-6), budget=kw.pop("budget", 0.05),
                  predicted_cost=kw.pop("predicted_cost", 0.04))
    return FrameRecord(**fields, **kw)


def _trace(t: float, key, level, drawn=None, eye=None, forward=None) -> FrameTrace:
    key = np.asarray(key, np.int64)
    level = np.asarray(level, np.float64)
    return FrameTrace(t, key, level, key + np.ceil(level).astype(np.int64), np.ones(key.size),
                      eye=None if eye is None else np.asarray(eye, np.float64),
                      forward=None if forward is None else np.asarray(forward, np.float64),
                      up=None if eye is None else np.array([0.0, 0.0, 1.0]),
                      drawn=np.ones(key.size, bool) if drawn is None else np.asarray(drawn, bool))


# ------------------------------------------------------------------------------------------------ paths


def test_spin_path_turns_a_full_circle_within_one_second_at_the_anchor():
    keys = spin_path(ANCHOR, hold=3.0, spin=1.0, after=2.0)
    tour = Tour(keys)
    eye, fwd, _ = tour.pose_at(np.linspace(0.0, 6.0, 601))
    assert np.allclose(eye, ANCHOR.eye)  # on the spot, at C
    yaw = _yaw(fwd[300:401])  # t = 3.0 … 4.0
    assert abs(abs(yaw[-1] - yaw[0]) - 2 * math.pi) < 1e-6
    assert np.all(np.diff(yaw) > 0)  # one way round, never back
    assert np.all(fwd[:300, 2] > math.sin(math.radians(55)))  # looking up first: the sparse view
    assert np.allclose(fwd[-1], sc_paths.forward_of(ANCHOR.yaw, ANCHOR.pitch), atol=1e-9)  # ends on the dense view
    assert tour.pose_at(500.0)[1] @ fwd[-1] > 0.999999  # and holds it: the path does not loop back


def test_turn_path_turns_150_degrees_in_015_seconds_and_walks_on():
    keys = turn_path(ANCHOR, walk=4.0, turn_deg=150.0, turn_s=0.15, after=3.0)
    tour = Tour(keys)
    t = np.linspace(0.0, 7.15, 716)
    eye, fwd, _ = tour.pose_at(t)
    yaw = _yaw(fwd)
    before, after = t <= 4.0, t >= 4.15
    assert np.allclose(yaw[before], ANCHOR.yaw) and np.allclose(yaw[after], ANCHOR.yaw + math.radians(150.0))
    assert np.allclose(eye[t == 4.0] if (t == 4.0).any() else tour.pose_at(4.0)[0], ANCHOR.eye)
    v0 = eye[10] - eye[0]
    v1 = eye[-1] - eye[-11]
    heading = math.degrees(math.acos(v0 @ v1 / np.linalg.norm(v0) / np.linalg.norm(v1)))
    assert abs(heading - 150.0) < 1e-6  # the walk goes on along the new view
    assert abs(np.linalg.norm(eye[-1] - ANCHOR.eye) - 1.2 * 3.0) < 1e-6


def test_oscillation_path_reverses_every_half_period():
    keys = oscillation_path(ANCHOR, amplitude=2.0, period=1.0, duration=8.0)
    t = np.arange(0.0, 8.0, 0.05)
    eye, fwd, _ = Tour(keys).pose_at(t)
    along = (eye - ANCHOR.eye) @ ANCHOR.ahead
    assert along.min() >= -1e-9 and abs(along.max() - 2.0) < 1e-9
    assert np.allclose(np.cross(eye - ANCHOR.eye, ANCHOR.ahead), 0.0)  # straight forward and back
    assert np.allclose(fwd, sc_paths.forward_of(ANCHOR.yaw, ANCHOR.pitch))  # the view direction is held
    direction = np.sign(np.diff(along))
    direction = direction[direction != 0]
    flips = np.nonzero(np.diff(direction))[0]
    assert len(flips) == 15  # 8 s at a 0.5 s half period: reversals at every half period
    assert np.allclose(np.diff(t[flips + 1]), 0.5, atol=0.051)


def test_paths_refuse_nonsense():
    with pytest.raises(ValueError):
        spin_path(ANCHOR, hold=0.0)
    with pytest.raises(ValueError):
        turn_path(ANCHOR, turn_s=0.0)
    with pytest.raises(ValueError):
        oscillation_path(ANCHOR, period=-1.0)
    with pytest.raises(ValueError):
        straight_path(ANCHOR, duration=0.0, speed=1.0)


def test_anchor_is_viewpoint_c_when_the_scene_has_one(demo_store):
    index = SceneStore.open(demo_store).index
    plain = anchor_of(index)
    assert plain.source.startswith("tour pose with most objects in view") and plain.speed > 0
    tour = Tour(index.tour)
    t_c = float(tour.t[len(tour.t) // 3])
    with_c = anchor_of(SimpleNamespace(**{**index.__dict__, "meta": {**index.meta, "viewpoints": {"C": t_c}}}))
    assert with_c.source == "viewpoint C" and np.allclose(with_c.eye, tour.pose_at(t_c)[0])
    seg = tour_segment(index, 5.0, 3.0)
    assert seg[0]["t"] == 0.0 and np.allclose(seg[0]["eye"], tour.pose_at(5.0)[0])


# ------------------------------------------------------------------------------------------------ figures


def test_window_stats_count_only_drawn_frames_in_the_window():
    frames = [_frame(0.5, 200.0, seq=-1)] + [_frame(1.0 + 0.05 * i, 40.0 + i) for i in range(20)]
    st = window_stats(frames, 1.0, 1.5)
    assert st["frames"] == 10 and st["max_ms"] == 49.0 and st["mean_ms"] == 44.5
    assert window_stats(frames, 10.0)["frames"] == 0 and math.isnan(window_stats(frames, 10.0)["p95_ms"])


def test_level_jumps_tell_a_pop_from_a_morph():
    ramp = [_trace(0.05 * i, [0, 5], [min(1.0, 0.1 * i), 2.0]) for i in range(12)]  # 1 level in 0.5 s
    assert level_jumps(ramp)["jumps"] == 0 and level_jumps(ramp)["pairs"] == 22
    pop = ramp + [_trace(0.65, [0, 5], [1.0, 3.0])]  # object 5 jumps a whole level in one 50 ms frame
    j = level_jumps(pop)
    assert j["jumps"] == 1 and j["max_step"] == 1.0
    slow = ramp + [_trace(1.2, [0, 5], [1.0, 3.0])]  # the same step after a 0.6 s frame: a morph could do it
    assert level_jumps(slow, span=np.full(10, 1.0))["jumps"] == 0
    assert level_jumps(pop, resets=[0.6])["jumps"] == 0 and level_jumps(pop, resets=[0.6])["excused_pairs"] == 2
    hidden = ramp + [_trace(0.65, [0, 5], [1.0, 3.0], drawn=[True, False])]  # not drawn: not judged
    assert level_jumps(hidden)["jumps"] == 0


def test_reset_times_replay_the_servers_predictor():
    fwd = [0.0, 1.0, 0.0]
    traces = [_trace(0.05 * i, [0], [0.0], eye=[0.0, 0.05 * i, 0.0], forward=fwd) for i in range(20)]
    assert reset_times(traces) == []
    gap = traces + [_trace(0.95 + 0.6, [0], [0.0], eye=[0.0, 1.0, 0.0], forward=fwd)]
    assert reset_times(gap) == [pytest.approx(1.55)]


def test_recovery_time():
    t = np.arange(0.0, 2.0, 0.1)
    assert recovery_time(t, np.ones_like(t), 0.2, 1.0) == 0.0
    cov = np.where((t > 0.25) & (t < 0.75), 0.3, 1.0)
    assert recovery_time(t, cov, 0.2, 1.0) == pytest.approx(0.6)  # first good frame after the last bad one
    assert recovery_time(t, np.where(t > 1.5, 0.3, 1.0), 0.2, 1.0) == math.inf


def test_coverage_counts_visible_objects_that_something_drawn_represents(demo_store):
    index = SceneStore.open(demo_store).index
    eye, fwd, _ = Tour(index.tour).pose_at(0.0)
    flat = np.nonzero(index.flat)[0]
    keys = index.rep_first[flat]
    every = _trace(0.0, keys, np.zeros(keys.size), eye=eye, forward=fwd)
    half = _trace(0.0, keys, np.zeros(keys.size), drawn=np.arange(keys.size) % 2 == 0, eye=eye, forward=fwd)
    sky = _trace(0.0, keys[:0], [], eye=index.bounds[1] + [0.0, 0.0, 100.0], forward=[0.1, 0.0, 1.0])
    none = _trace(0.0, keys, np.zeros(keys.size), drawn=np.zeros(keys.size, bool), eye=eye, forward=fwd)
    cov = coverage(index, [every, half, sky, none])
    assert cov[0] == 1.0 and 0.2 < cov[1] < 0.8 and cov[3] == 0.0
    assert cov[2] == 1.0  # looking at the sky: nothing in view, nothing missing


def test_coverage_counts_a_drawn_proxy_for_its_whole_subtree():
    # An HLOD node (object 0, reps 0..1) over two buildings (objects 1 and 2, reps 2..3 and 4..5), in front of the eye.
    index = SimpleNamespace(
        flat=np.array([False, True, True]), n_objects=3, bounds=np.array([[-10.0, 5.0, -1.0], [10.0, 15.0, 5.0]]),
        object_lo=np.array([[-10.0, 5.0, -1.0], [-10.0, 5.0, -1.0], [1.0, 5.0, -1.0]]),
        object_hi=np.array([[10.0, 15.0, 5.0], [-1.0, 15.0, 5.0], [10.0, 15.0, 5.0]]),
        object_parent=np.array([-1, 0, 0]), object_depth=np.array([0, 1, 1]),
        rep_object=np.array([0, 0, 1, 1, 2, 2]))
    look = dict(eye=[0.0, 0.0, 2.0], forward=[0.0, 1.0, 0.0])
    cov = coverage(index, [_trace(0.0, [0], [1.0], **look), _trace(0.0, [2], [0.0], **look),
                           _trace(0.0, [0], [1.0], drawn=[False], **look)])
    assert cov.tolist() == [1.0, 0.5, 0.0]


# ------------------------------------------------------------------------------------------------ verdicts


def _below(**kw) -> dict:
    fig = dict(frames=100, errors=0, disconnected=False, mean_ms=2.0, median_ms=2.0, coarsest_ms=10.0,
               over_budget_deltas=0, deltas_drawn=8, cut_solver=False, target_ms=1.0, below=True)
    fig.update(kw)
    return fig


def test_below_coarsest_verdict():
    assert below_coarsest_verdict(_below())[0]
    assert not below_coarsest_verdict(_below(over_budget_deltas=1))[0]  # a flat solver must drop objects
    assert not below_coarsest_verdict(_below(median_ms=11.0))[0]
    assert below_coarsest_verdict(_below(mean_ms=11.0))[0]  # a few stalled frames move the mean, not the verdict
    assert not below_coarsest_verdict(_below(errors=1))[0]
    assert not below_coarsest_verdict(_below(frames=0, mean_ms=math.nan, median_ms=math.nan))[0]
    assert not below_coarsest_verdict(_below(disconnected=True))[0]
    cut = dict(cut_solver=True, over_budget_deltas=6, median_ms=13.0, max_triangles=5000, p95_triangles=900,
               coarsest_triangles=1000)
    ok, line = below_coarsest_verdict(_below(**cut))
    assert ok and "coarsest cut" in line  # the same picture as the coarsest frame: its time is not judged
    assert not below_coarsest_verdict(_below(**{**cut, "p95_triangles": 1001}))[0]
    # Increments its cost model prices free (a fill-bound raise) add triangles, not time: within 1.25 × the
    # coarsest frame they pass, beyond it they do not.
    ok, line = below_coarsest_verdict(_below(**{**cut, "p95_triangles": 2000, "median_ms": 12.5}))
    assert ok and "cost 1.25 × the coarsest frame (limit 1.25)" in line
    assert not below_coarsest_verdict(_below(**{**cut, "p95_triangles": 2000, "median_ms": 12.6}))[0]
    assert not below_coarsest_verdict(_below(**cut, errors=2))[0]


def test_frame_time_verdicts_hold_their_limits():
    st = lambda p95: {"frames": 40, "mean_ms": 40.0, "p95_ms": p95, "max_ms": p95 + 5}  # noqa: E731
    assert spin_verdict({"spin": st(62.0), "reference": {"p95_ms": 120.0}}, 50.0) == (
        True, "p95 62.0 ms (1.24× target 50 ms) during the spin and 1 s after, max 67.0 ms; static 2.4×")
    assert not spin_verdict({"spin": st(63.0)}, 50.0)[0]
    assert not spin_verdict({"spin": st(math.nan)}, 50.0)[0]
    turn = {"recovery_s": 1.2, "after": st(60.0), "hole_frames": 0}
    assert turn_verdict(turn, 50.0, 0.5)[0]
    assert not turn_verdict({**turn, "recovery_s": 1.35}, 50.0, 0.5)[0]
    assert not turn_verdict({**turn, "recovery_s": math.inf}, 50.0, 0.5)[0]
    assert not turn_verdict({**turn, "after": st(70.0)}, 50.0, 0.5)[0]
    drift = {"before": st(50.0), "first_second": st(90.0), "settled": {**st(60.0), "mean_ms": 57.0},
             "cost_coeff_before": 1e-6, "cost_coeff_settled": 2e-6, "triangles_before": 1e5, "triangles_settled": 5e4}
    ok, line = drift_verdict(drift, 50.0)
    assert ok and "c_vertex ×2.00" in line
    assert not drift_verdict({**drift, "settled": {**st(60.0), "mean_ms": 58.0}}, 50.0)[0]
    assert "over its budget" not in line
    # A solver at its floor is said so, and judged by the same line.
    floor = {**drift, "settled": {**st(60.0), "mean_ms": 58.0}, "over_budget_settled": 0.9}
    ok, line = drift_verdict(floor, 50.0)
    assert not ok and "90 % of those frames drew a delta priced over its budget" in line
    assert drift_verdict({**floor, "settled": drift["settled"]}, 50.0)[0]
    # A cut solver at its floor under a load that makes its coarsest cut dearer than the target is held to that
    # cut's time under the load in the target's place (1.15 × 60 ms); not at its floor, or a flat solver, to the
    # target's line.
    cut = {**floor, "cut_solver": True, "coarsest_loaded_ms": 60.0, "settled": {**st(80.0), "mean_ms": 68.5}}
    ok, line = drift_verdict(cut, 50.0)
    assert ok and "its coarsest cut drew in 60.0 ms under the load, so the line is 1.15 × that, 69.0 ms" in line
    assert not drift_verdict({**cut, "settled": {**st(80.0), "mean_ms": 69.5}}, 50.0)[0]
    assert not drift_verdict({**cut, "over_budget_settled": 0.4}, 50.0)[0]
    assert not drift_verdict({**cut, "cut_solver": False}, 50.0)[0]
    assert not drift_verdict({**cut, "coarsest_loaded_ms": math.nan}, 50.0)[0]
    cheap = {**cut, "coarsest_loaded_ms": 30.0}  # a floor under the target leaves the target's line
    ok, line = drift_verdict({**cheap, "settled": drift["settled"]}, 50.0)
    assert ok and "under the load" not in line and not drift_verdict(cheap, 50.0)[0]
    net = {"p95_ms": 55.0, "errors": 0, "late": 1, "reconnects": 0, "bytes": 1e6, "lost_chunks": 3}
    assert network_verdict(net, 50.0)[0]
    assert not network_verdict({**net, "p95_ms": 55.1}, 50.0)[0]
    assert not network_verdict({**net, "errors": 1}, 50.0)[0]
    osc = {"levels": {"jumps": 0, "pairs": 100, "max_step": 0.3, "threshold": 0.5}, "late": 0, "unmorphed": 0,
           "morph_frames": 10}
    assert oscillation_verdict(osc)[0]
    assert not oscillation_verdict({**osc, "late": 1})[0]
    assert not oscillation_verdict({**osc, "levels": {**osc["levels"], "jumps": 1}})[0]


def test_cpu_load_is_always_cleaned_up():
    load = sc_run._CpuLoad(2)
    with pytest.raises(RuntimeError):
        with load:
            load.start()
            procs = list(load.procs)
            assert all(p.poll() is None for p in procs)
            raise RuntimeError("the run failed")
    assert not load.procs and all(p.poll() is not None for p in procs)


def test_runner_checks_names_and_turns_a_crash_into_a_fail_line(demo_store, monkeypatch, capsys):
    name = SceneStore.open(demo_store).index.name
    with pytest.raises(ValueError, match="unknown scenario"):
        run_scenarios(demo_store, name, names=["nope"])
    with pytest.raises(ValueError, match="unknown method"):
        run_scenarios(demo_store, name, names=["spin"], method="nope")

    def broken(ctx):
        raise RuntimeError("boom")

    monkeypatch.setitem(SCENARIOS, "spin", ("sudden complexity", broken))
    ticks = []
    [res] = run_scenarios(demo_store, name, names=["spin"], progress=lambda *a: ticks.append(a))
    assert not res["passed"] and res["line"].startswith("FAIL spin") and "boom" in res["line"]
    assert res["figures"]["error"] == "boom" and res["figures"]["method"] == "predictive"
    assert ticks == [("scenarios", 0, 1), ("scenarios", 1, 1)]
    print_results([res])
    assert capsys.readouterr().out.startswith("FAIL spin")


def test_methods_name_real_solvers():
    from server.select import solvers

    for solver, predict, morph in METHODS.values():
        solvers.get(solver)
    assert METHODS["predictive"] == ("hierarchical", True, True)
    assert METHODS["optimization"] == ("optimization", False, False)
    assert list(SCENARIOS) == ["spin", "turn", "oscillation", "drift", "below_coarsest", "network"]


# ------------------------------------------------------------------------------------------------ a real run


@pytest.fixture(scope="module")
def demo_results(demo_store):
    name = SceneStore.open(demo_store).index.name
    return run_scenarios(demo_store, name, names=["oscillation", "below_coarsest"], method="predictive",
                         viewport=(320, 180), duration_scale=0.4)


def test_real_run_results_have_the_schema_and_hold_the_timing_free_criteria(demo_results):
    osc, below = demo_results
    for res, name in zip(demo_results, ("oscillation", "below_coarsest")):
        assert set(res) == {"name", "title", "passed", "line", "figures"} and res["name"] == name
        assert res["title"] == SCENARIOS[name][0]
        assert res["line"].startswith(("PASS " + name, "FAIL " + name))
        assert isinstance(res["passed"], bool) and res["line"].startswith("PASS") == res["passed"]
        json.dumps(res, allow_nan=False)  # strict JSON
        f = res["figures"]
        assert f["frames"] > 0 and f["errors"] == 0 and not f["disconnected"] and f["deltas"] > 0
        assert f["method"] == "predictive"
    # Oscillation: geomorphing kept every level continuous, and the figures are the run's.
    lv = osc["figures"]["levels"]
    assert lv["jumps"] == 0 and lv["pairs"] > 0 and 0 <= lv["max_step"], osc["line"]
    assert osc["figures"]["frame"]["frames"] <= osc["figures"]["frames"]
    # Below the coarsest level: the hierarchical solver keeps every visible object (no flat scene splits).
    fb = below["figures"]
    assert fb["target_ms"] == 1.0 and fb["cut_solver"] and fb["split_frames"] == 0 and 0 <= fb["raised_share"] <= 1
    if fb["over_budget_deltas"]:  # it can do no better than the coarsest cut, and did no worse
        assert 0 < fb["p95_triangles"] <= fb["coarsest_triangles"] and fb["over_budget_frames"] > 0
    assert fb["coarsest_ms"] > 0 and fb["deltas_drawn"] >= 1 and 0 <= fb["over_budget_deltas"] <= fb["deltas_drawn"]


def test_a_flat_solver_never_exceeds_a_budget_below_the_coarsest_level(demo_store):
    ctx = Context(demo_store, SceneStore.open(demo_store).index.name, method="optimization", viewport=(320, 180),
                  scale=0.4)
    try:
        res = below_coarsest(ctx)
    finally:
        ctx.close()
    f = res["figures"]
    assert f["frames"] > 0 and f["errors"] == 0 and not f["cut_solver"]
    assert f["over_budget_deltas"] == 0 and f["deltas_drawn"] >= 1  # it drops objects instead
    assert f["predicted_ms"] <= f["budget_ms"]
