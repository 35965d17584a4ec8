"""What a load test found: the figures of a phase (``PhaseResult``), the whole test's summary
(``LoadSummary``) against the benchmark's goals, and the summary as lines for people.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

__all__ = ["GOAL_SESSIONS_PER_CORE", "GOAL_P99_MS", "GOAL_DELIVERED", "SKIPPED_LIMIT", "PhaseResult", "LoadSummary",
           "fmt", "format_summary", "at_the_lines"]


#: The benchmark's goal: sessions per server core, held at these lines — the share of the selections due that
#: are delivered, and the p99 selection latency (ms).
GOAL_SESSIONS_PER_CORE = 100.0
GOAL_P99_MS = 100.0
GOAL_DELIVERED = 0.95
#: A generator that skipped more than this share of the frames it was to send limited the load it produced.
SKIPPED_LIMIT = 0.01


@dataclass
class PhaseResult:
    """One measured run of ``clients`` simulated sessions; figures over the window after the ramp.

    Latencies are the server's ``walkstream_selection_seconds`` histogram over
    the window (None when it saw no selection); ``errors`` are the clients'
    (error frames by code, and connect_failed / connection_lost / no_welcome);
    ``mirror_*`` come from the server's ``/sessions`` just before the clients
    left (None when it would not say).
    """

    clients: int
    sessions_opened: int
    connected_at_end: int
    window_s: float
    deltas: int
    selections_per_s: float
    selections_due_share: float | None
    selection_p50_ms: float | None
    selection_p99_ms: float | None
    selections_measured: int
    selection_cpu_p50_ms: float | None
    selection_cpu_p99_ms: float | None
    delta_interarrival_p99_ms: float | None
    bytes_per_s: float
    server_bytes_out_per_s: float | None
    server_cpu_s: float | None
    server_cpu_per_session_s: float | None
    sessions_per_core: float | None
    errors: dict[str, int]
    server_errors: dict[str, int]
    frame_p95_ms: float | None
    frame_target_ms: float
    frame_p95_over_target: float | None
    clients_with_deltas: int
    min_deltas_per_client: int
    acks: int
    pongs: int
    generator_cpu_per_session_s: float | None = None
    generator_cores: float | None = None  # the load generator's CPU seconds per second (this process)
    server_cores: float | None = None  # the server's CPU seconds per second, all its processes
    polls_per_tick: float | None = None  # due polls the server ran together, on average (``server.ticker``)
    frames_skipped: int = 0
    generator_fell_behind: bool = False  # it skipped more than ``SKIPPED_LIMIT`` of the frames it was to send
    mirror_checks: int | None = None
    mirror_mismatch: int | None = None
    resyncs: int | None = None
    notes: list[str] = field(default_factory=list)


@dataclass
class LoadSummary(PhaseResult):
    """The load test's result: the N-client phase's figures, its setting, and the one-client reference."""

    scene: str = ""
    url: str = ""
    tau: float | None = None
    rate: float = 0.0
    duration_s: float = 0.0
    ramp_s: float = 0.0
    server_pid: int | None = None
    reference: PhaseResult | None = None
    cpu_per_session_ratio: float | None = None
    p99_ratio: float | None = None
    workers: int | None = None  # processes of the server the test started (None: not ours)
    # The calibration workload (``bench.machine``) just before the run, median of five: the machine's speed then,
    # so runs at different times can be compared.
    calibration_ms: float | None = None
    goal_sessions_per_core: float = GOAL_SESSIONS_PER_CORE
    goal_p99_ms: float = GOAL_P99_MS
    goal_delivered: float = GOAL_DELIVERED
    lines_met: bool = False  # ≥ 95 % of the selections due delivered, p99 ≤ 100 ms, no errors
    goal_met: bool = False

    def as_dict(self) -> dict:
        return asdict(self)


def at_the_lines(r: PhaseResult) -> bool:
    """Whether a run held the lines: ≥ ``GOAL_DELIVERED`` of the selections due delivered, p99 selection latency
    ≤ ``GOAL_P99_MS``, and no client saw an error."""
    return bool(r.selections_due_share is not None and r.selections_due_share >= GOAL_DELIVERED
                and r.selection_p99_ms is not None and r.selection_p99_ms <= GOAL_P99_MS and not r.errors)


def fmt(x: float | None, spec: str = ".1f") -> str:
    return "—" if x is None or not math.isfinite(x) else format(x, spec)


def _pct(x: float | None) -> float | None:
    return None if x is None else 100.0 * x


def format_summary(s: LoadSummary) -> list[str]:
    """The summary as lines for people."""
    lines = [
        f"walkstream loadtest: scene {s.scene!r}, {s.clients} clients, {s.duration_s:g} s (ramp {s.ramp_s:g} s, "
        f"measured {s.window_s:.1f} s), camera and frame reports at {s.rate:g} Hz",
        f"  sessions opened {s.sessions_opened} / {s.clients}, connected at the end {s.connected_at_end}",
        f"  selections {s.selections_per_s:.1f}/s ({fmt(_pct(s.selections_due_share), '.0f')} % of those due); "
        f"latency p50 {fmt(s.selection_p50_ms)} ms, p99 "
        f"{fmt(s.selection_p99_ms)} ms (server, {s.selections_measured} selections; worker CPU p50 "
        f"{fmt(s.selection_cpu_p50_ms)}, p99 {fmt(s.selection_cpu_p99_ms)} ms; {fmt(s.polls_per_tick)} polls per "
        f"tick); delta inter-arrival p99 {fmt(s.delta_interarrival_p99_ms)} ms (client)",
        f"  received {s.bytes_per_s / 1e6:.3f} MB/s; server CPU {fmt(s.server_cpu_per_session_s, '.4f')} s per "
        f"session-second ({fmt(s.server_cores, '.2f')} cores, "
        f"{'all ' + str(s.workers) + ' worker processes' if s.workers else 'as the server reports it'}) → "
        f"{fmt(s.sessions_per_core)} sessions per server core"
        + (f" (calibration workload {s.calibration_ms:.1f} ms just before)" if s.calibration_ms is not None else ""),
        f"  load generator CPU {fmt(s.generator_cpu_per_session_s, '.4f')} s per session-second "
        f"({fmt(s.generator_cores, '.2f')} cores), {s.frames_skipped} frames skipped for falling behind",
        f"  modelled frame time p95 {fmt(s.frame_p95_ms)} ms against {s.frame_target_ms:g} ms "
        f"({fmt(s.frame_p95_over_target, '.2f')} × target)",
        f"  errors: {', '.join(f'{k} {v}' for k, v in s.errors.items()) or 'none'}"
        f" (server counted: {', '.join(f'{k} {v}' for k, v in s.server_errors.items()) or 'none'})",
    ]
    if s.mirror_checks is not None:
        lines.append(f"  client-cache mirror: {s.mirror_checks} checks, {s.mirror_mismatch} mismatches")
    if s.reference is not None:
        r = s.reference
        lines.append(
            f"  reference (1 client, same run): CPU {fmt(r.server_cpu_per_session_s, '.4f')} s per session-second, "
            f"p99 {fmt(r.selection_p99_ms)} ms → ratios at {s.clients}: CPU per session "
            f"{fmt(s.cpu_per_session_ratio, '.2f')}, p99 {fmt(s.p99_ratio, '.2f')}")
    lines.append(f"  goal (≥ {s.goal_sessions_per_core:g} sessions per core at ≥ {100 * s.goal_delivered:g} % of the "
                 f"selections due delivered, p99 ≤ {s.goal_p99_ms:g} ms, no errors): "
                 + ("met" if s.goal_met else "NOT met") + (" (the lines held)" if s.lines_met and not s.goal_met
                                                          else ""))
    lines += [f"  note: {n}" for n in s.notes]
    return lines
