"""The load test's goals over rounds of runs: each judged on its median round, the scaling ratio paired within
a round, and the spread of the rounds reported beside it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from bench.loadtest.goals import GOAL_COHERENT_MS, GOAL_SCALING, coherent_goal, judge, run_goals
from bench.loadtest.summary import LoadSummary

ROOT = Path(__file__).resolve().parents[2]


def _run(workers: int, per_core: float, *, held: bool = True) -> LoadSummary:
    """A run's summary with only the figures the goals read."""
    return LoadSummary(
        clients=40, sessions_opened=40, connected_at_end=40, window_s=10.0, deltas=800, selections_per_s=80.0,
        selections_due_share=0.999 if held else 0.7, selection_p50_ms=5.0, selection_p99_ms=20.0 if held else 400.0,
        selections_measured=800, selection_cpu_p50_ms=3.0, selection_cpu_p99_ms=6.0, delta_interarrival_p99_ms=600.0,
        bytes_per_s=1e5, server_bytes_out_per_s=1e5, server_cpu_s=4.0, server_cpu_per_session_s=1.0 / per_core,
        sessions_per_core=per_core, errors={}, server_errors={}, frame_p95_ms=40.0, frame_target_ms=50.0,
        frame_p95_over_target=0.8, clients_with_deltas=40, min_deltas_per_client=15, acks=800, pongs=80,
        workers=workers, lines_met=held, goal_met=held and per_core >= 100)


def _goals(by_round):
    goals, notes = judge(by_round, [1, 2])
    return {g["goal"] + str(g["workers"]): g for g in goals}, notes


def test_each_goal_is_judged_on_its_median_round_with_the_spread():
    rounds = [{1: _run(1, 90.0), 2: _run(2, 95.0)}, {1: _run(1, 130.0), 2: _run(2, 100.0)},
              {1: _run(1, 110.0), 2: _run(2, 104.0)}]
    goals, notes = _goals(rounds)
    one, two, scaling = goals["sessions_per_core1"], goals["sessions_per_core2"], goals["scaling2"]
    assert one["value"] == 110.0 and one["spread"] == [90.0, 130.0] and one["rounds_met"] == 2 and one["goal_met"]
    assert two["value"] == 100.0 and two["rounds_met"] == 2 and two["goal_met"]
    # Paired within each round: 2·95/90, 2·100/130, 2·104/110 — the median is round 3's, not a ratio of medians.
    assert scaling["values"] == pytest.approx([190 / 90, 200 / 130, 208 / 110])
    assert scaling["value"] == pytest.approx(208 / 110) and scaling["capacity_1"] == 110.0
    assert scaling["capacity_2"] == 208.0 and scaling["rounds_met"] == 2 and scaling["goal_met"]
    assert notes == []


def test_an_even_count_of_rounds_takes_the_lower_median():
    rounds = [{1: _run(1, 100.0), 2: _run(2, 99.0)}, {1: _run(1, 100.0), 2: _run(2, 80.0)}]
    goals, _ = _goals(rounds)
    assert goals["sessions_per_core2"]["value"] == 80.0 and not goals["sessions_per_core2"]["goal_met"]
    assert goals["scaling2"]["value"] == pytest.approx(1.6) and not goals["scaling2"]["goal_met"]
    assert goals["scaling2"]["rounds_met"] == 1


def test_a_median_round_that_missed_the_lines_fails_the_goal_and_says_why():
    rounds = [{1: _run(1, 100.0), 2: _run(2, 100.0, held=False)}]
    goals, notes = _goals(rounds)
    assert goals["scaling2"]["value"] == pytest.approx(2.0) and 2.0 >= GOAL_SCALING
    assert not goals["scaling2"]["goal_met"] and not goals["scaling2"]["lines_met"]
    assert any("did not hold the lines" in n for n in notes)


def test_the_coherent_step_is_judged_on_its_median_round():
    g = coherent_goal([4.0, 2.9, 2.8])
    assert g["value"] == 2.9 and g["spread"] == [2.8, 4.0] and g["rounds_met"] == 2 and g["goal_met"]
    assert not coherent_goal([GOAL_COHERENT_MS + 0.1, 2.0])["goal_met"]  # the lower median of two is the slower


def test_worker_counts_and_rounds_are_checked_before_any_run():
    with pytest.raises(ValueError, match="each count once"):
        run_goals([1, 1], repeats=1)
    with pytest.raises(ValueError, match="at least 1"):
        run_goals([1], repeats=0)
    with pytest.raises(ValueError, match="--url server's processes are its own"):
        run_goals([1], per_worker=True, url="ws://127.0.0.1:9/ws", clients=4)


def test_cli_clients_per_worker_drives_each_process_alike(demo_store):
    """``--clients-per-worker``: the run of two workers carries twice the clients of the one-worker run, so each
    process holds the load the other run's does."""
    out = subprocess.run(
        [sys.executable, "-m", "walkstream", "loadtest", "--store", str(demo_store), "--clients", "2",
         "--clients-per-worker", "--duration", "2.5", "--ramp", "0.5", "--reference", "0", "--workers", "1",
         "--workers", "2", "--no-coherent", "--json"],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    summary = json.loads(out.stdout.strip().splitlines()[-1])
    assert summary["clients_per_worker"] is True
    assert [(r["workers"], r["clients"], r["sessions_opened"]) for r in summary["runs"]] == [(1, 2, 2), (2, 4, 4)]


def test_cli_rounds_interleave_and_report_the_spread(demo_store):
    """``--repeats 2`` runs the worker counts in two rounds, the second in reverse order, and prints each goal as
    the median of the rounds with their spread."""
    out = subprocess.run(
        [sys.executable, "-m", "walkstream", "loadtest", "--store", str(demo_store), "--clients", "2",
         "--duration", "2.5", "--ramp", "0.5", "--reference", "0", "--workers", "1", "--workers", "2",
         "--repeats", "2", "--no-coherent", "--json"],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    summary = json.loads(out.stdout.strip().splitlines()[-1])
    assert summary["repeats"] == 2
    assert [(r["round"], r["workers"]) for r in summary["runs"]] == [(1, 1), (1, 2), (2, 2), (2, 1)]
    assert all(r["calibration_ms"] > 0 for r in summary["runs"])  # the machine's speed beside each run
    goals = {(g["goal"], g.get("workers")): g for g in summary["goals"]}
    for g in goals.values():
        assert g["rounds"] == 2 and len(g["values"]) == 2
        assert g["spread"][0] <= g["value"] <= g["spread"][1]
    assert "the median of 2 rounds" in out.stderr and "round 2 of 2: 2 worker processes" in out.stderr


def test_cli_refuses_zero_rounds_in_one_line(demo_store):
    out = subprocess.run([sys.executable, "-m", "walkstream", "loadtest", "--store", str(demo_store), "--clients", "2",
                          "--duration", "2", "--repeats", "0"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "--repeats" in out.stderr and "Traceback" not in out.stderr


def test_a_few_skipped_frames_do_not_say_the_generator_was_the_limit():
    fine, behind = _run(1, 120.0), _run(1, 120.0)
    fine.frames_skipped = 2  # of thousands: the generator kept up
    behind.frames_skipped, behind.generator_fell_behind = 400, True
    assert judge([{1: fine}], [1])[1] == []
    assert any("load generator" in n for n in judge([{1: behind}], [1])[1])
