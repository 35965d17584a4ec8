"""The issue's goals from load tests of 1, 2, … worker processes in one invocation.

Each worker count gets a run of its own (its own server, the same clients and
seed; with ``per_worker``, as many clients per worker process as the one-worker
run has, so each process carries the same load). Per run: the server's CPU per
session-second over all its processes and the sessions per core it implies, at
the lines — ≥ 95 % of the selections due delivered, p99 selection latency
≤ 100 ms. The scaling ratio is the capacity
the runs imply, sessions per core × workers, of the most workers against one
worker's (the goal counts when both runs held the lines): on a machine whose
cores the load generator shares with the server the runs cannot hold the full
load of each, so the server's own CPU is what is compared — and the notes say
when a run missed the lines or the generator was the limit.

With ``repeats`` the worker counts run in rounds, interleaved (1 2, 2 1, 1 2, …):
a shared machine's speed wanders from one minute to the next, so a verdict from
one pair of runs says more about the minute than about the server. Each goal is
then judged on its median round and printed with the rounds' spread; the scaling
ratio of a round pairs the two runs of that round.

Why ``per_worker``: a worker's CPU per session-second falls as it holds more
sessions (a tick's culling and pricing are batched over the sessions due in it),
so two workers at half the load each imply fewer sessions per core than they
would hold at the load one worker is measured at; driving each worker alike
compares capacity with capacity.

The coherent step of the incremental solver at 100k objects is timed too, in CPU
seconds (``bench.select``), once in each round and judged on the median.
"""

from __future__ import annotations

import statistics
from dataclasses import asdict
from typing import Callable, Mapping, Sequence

from bench.loadtest.run import run_loadtest
from bench.machine import calibration_workload
from bench.loadtest.summary import GOAL_SESSIONS_PER_CORE, LoadSummary, fmt, format_summary

__all__ = ["GOAL_SCALING", "GOAL_COHERENT_MS", "judge", "coherent_goal", "run_goals", "format_goals"]

#: Sessions held with two workers against one (both at the lines), and the coherent step at 100k objects (ms).
GOAL_SCALING = 1.8
GOAL_COHERENT_MS = 3.0
#: A generator using more than this share of a core is taken to limit the load it produces.
GENERATOR_LIMIT = 0.8


def capacity(run: LoadSummary) -> float | None:
    """Sessions the server would hold on one core per worker, by its CPU per session-second."""
    if run.sessions_per_core is None:
        return None
    return run.sessions_per_core * (run.workers or 1)


def _median_index(values: Sequence[float | None]) -> int | None:
    """Index of the median of the values that are there (the lower one of an even count: the cautious side)."""
    known = sorted((v, i) for i, v in enumerate(values) if v is not None)
    return known[(len(known) - 1) // 2][1] if known else None


def _spread(values: Sequence[float | None]) -> list[float] | None:
    known = [v for v in values if v is not None]
    return [min(known), max(known)] if known else None


def judge(by_round: Sequence[Mapping[int, LoadSummary]], counts: Sequence[int]) -> tuple[list[dict], list[str]]:
    """The goals of rounds of runs (``by_round[k][w]``: round k's run of w workers), each on its median round,
    and the notes on what limited them."""
    goals = []
    for w in counts:
        mine = [r[w] for r in by_round]
        values = [r.sessions_per_core for r in mine]
        m = mine[_median_index(values) or 0]
        goals.append({"goal": "sessions_per_core", "workers": m.workers, "value": m.sessions_per_core,
                      "bound": GOAL_SESSIONS_PER_CORE, "kind": "min", "lines_met": m.lines_met,
                      "delivered": m.selections_due_share, "p99_ms": m.selection_p99_ms,
                      "server_cpu_per_session_s": m.server_cpu_per_session_s, "sessions": m.connected_at_end,
                      "generator_cores": m.generator_cores, "calibration_ms": m.calibration_ms,
                      "goal_met": m.goal_met, "rounds": len(mine),
                      "values": values, "spread": _spread(values), "rounds_met": sum(r.goal_met for r in mine)})
    notes = []
    base_w = next((w for w in counts if w == 1), None)
    top_w = max(counts)
    if base_w is not None and top_w != base_w:
        ratios, held, c1s, cns = [], [], [], []
        for mine in by_round:  # paired within a round: the two runs saw the same stretch of the machine
            base, top = mine[base_w], mine[top_w]
            c1, cn = capacity(base), capacity(top)
            ratios.append(cn / c1 if c1 and cn else None)
            held.append(bool(base.lines_met and top.lines_met))
            c1s.append(c1)
            cns.append(cn)
        i = _median_index(ratios)
        ratio = None if i is None else ratios[i]
        both = bool(i is not None and held[i])
        goals.append({"goal": "scaling", "workers": top_w, "value": ratio, "bound": GOAL_SCALING, "kind": "min",
                      "capacity_1": None if i is None else c1s[i],
                      f"capacity_{top_w}": None if i is None else cns[i], "lines_met": both,
                      "goal_met": bool(both and ratio is not None and ratio >= GOAL_SCALING), "rounds": len(ratios),
                      "values": ratios, "spread": _spread(ratios),
                      "rounds_met": sum(bool(h and r is not None and r >= GOAL_SCALING) for r, h in zip(ratios, held))})
        if not all(held):
            notes.append("the scaling ratio compares the capacity each run's CPU per session-second implies; a run "
                         "that did not hold the lines spent less than its load would cost (selections skipped), so "
                         "its capacity is overstated — run at a load one worker holds for the goal to count")
    for r in (r for mine in by_round for r in mine.values()):
        if (r.generator_cores or 0) > GENERATOR_LIMIT or r.generator_fell_behind:
            notes.append(f"with {r.workers} worker(s) the load generator used {fmt(r.generator_cores, '.2f')} of a "
                         "core beside the server: the load it produced is what was delivered, and the sessions per "
                         "core are implied by the server's CPU per session-second at that load")
    return goals, list(dict.fromkeys(notes))


def coherent_goal(steps: Sequence[float]) -> dict:
    """The coherent step's goal from its timing in each round (ms): judged on the median (the higher one of an
    even count: for a ceiling that is the cautious side), with the spread."""
    value = sorted(steps)[len(steps) // 2]
    return {"goal": "coherent_step_ms", "objects": 100_000, "value": value, "bound": GOAL_COHERENT_MS, "kind": "max",
            "goal_met": bool(value <= GOAL_COHERENT_MS), "rounds": len(steps), "values": list(steps),
            "spread": _spread(steps), "rounds_met": sum(v <= GOAL_COHERENT_MS for v in steps)}


def run_goals(workers: Sequence[int], *, repeats: int = 1, coherent: bool = True, per_worker: bool = False,
              log: Callable[[str], None] | None = None, **kw) -> tuple[dict, list[LoadSummary]]:
    """``run_loadtest(workers=w, **kw)`` for each ``w``, ``repeats`` rounds interleaved (the order of the worker
    counts reversed every other round, so a machine that drifts slower or faster weighs on each alike), then
    the goals, each on the median round with the spread of the rounds: a JSON-ready dict whose top level is the
    first run's summary (as a single run prints it) with ``runs``, ``goals`` and ``goal_met`` added, and the
    runs in the order they ran. ``per_worker``: ``kw["clients"]`` clients per worker process (w × clients in
    the run of w workers)."""
    if repeats < 1:
        raise ValueError("--repeats must be at least 1")
    if per_worker and kw.get("url"):
        raise ValueError("--clients-per-worker scales the load with --workers; a --url server's processes are "
                         "its own: give the clients it should carry")
    counts = [int(w) for w in workers]
    if len(set(counts)) != len(counts):
        raise ValueError(f"--workers: each count once (got {', '.join(map(str, counts))})")
    say = log or (lambda s: None)
    runs: list[LoadSummary] = []
    rounds: list[int] = []
    by_round: list[dict[int, LoadSummary]] = []
    steps: list[float] = []
    for k in range(repeats):
        mine: dict[int, LoadSummary] = {}
        for w in counts if k % 2 == 0 else counts[::-1]:
            head = f"round {k + 1} of {repeats}: " if repeats > 1 else ""
            say(f"— {head}{w} worker process{'es' if w > 1 else ''} —")
            speed = statistics.median(calibration_workload() for _ in range(5))
            load = {**kw, "clients": kw["clients"] * w} if per_worker and "clients" in kw else kw
            mine[w] = run_loadtest(workers=w, log=log, **load)
            mine[w].calibration_ms = 1e3 * speed
            runs.append(mine[w])
            rounds.append(k)
        by_round.append(mine)
        if coherent:  # in every round, beside its runs: one timing says more about the minute than the solver
            from bench.select import coherent_step_ms

            steps.append(coherent_step_ms(100_000))
    goals, notes = judge(by_round, counts)
    if coherent:
        goals.append(coherent_goal(steps))
    out = {**runs[0].as_dict(), "repeats": repeats, "clients_per_worker": bool(per_worker),
           "runs": [{**asdict(r), "round": k + 1} for r, k in zip(runs, rounds)],
           "goals": goals, "notes_goals": notes}
    out["goal_met"] = all(g["goal_met"] for g in goals)
    return out, runs


def format_goals(result: dict, runs: list[LoadSummary]) -> list[str]:
    """Each run's summary, then one line per goal."""
    lines: list[str] = []
    for r in runs:
        lines += format_summary(r)
    for g in result["goals"]:
        op = "≥" if g["kind"] == "min" else "≤"
        what = g["goal"] + (f" ({g['workers']} workers)" if g.get("workers") else "")
        value = fmt(g["value"], ".2f")
        extra = "" if g["goal"] != "sessions_per_core" else (
            f" — delivered {fmt(None if g['delivered'] is None else 100 * g['delivered'], '.0f')} %, "
            f"p99 {fmt(g['p99_ms'])} ms, lines {'held' if g['lines_met'] else 'NOT held'}")
        if (g.get("rounds") or 1) > 1:
            low, high = g["spread"] or (None, None)
            extra += (f" (the median of {g['rounds']} rounds, {fmt(low, '.2f')}–{fmt(high, '.2f')}; "
                      f"met in {g['rounds_met']} of {g['rounds']})")
        lines.append(f"goal {what}: {value} {op} {g['bound']:g}: {'met' if g['goal_met'] else 'NOT met'}{extra}")
    lines += [f"note: {n}" for n in result["notes_goals"]]
    return lines
