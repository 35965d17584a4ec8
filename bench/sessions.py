"""``walkstream bench sessions``: the server's CPU per session-second by part, in one process, without a network.

The load test's clients (``bench.loadtest.scripted``) drive sans-I/O sessions on a
virtual clock: poses with their frame reports ten times a second, pongs and acks
a round trip later, selections polled in batches as the server's ticker polls
them (``session.batch.poll_many``), and each session's state snapshotted at most
every ``save_interval`` while it has changed, as the app saves it. Each part's
thread CPU per session-second is what a server core spends on it apart from the
websocket stack and the event loop (``walkstream loadtest`` measures those too,
with the noise of a network and a load generator beside it).

This machine is shared: beside every repeat the calibration workload
(``bench.machine``) is timed, and each figure is also given as a multiple of it,
so that runs at different times compare. Repeats are reported as the median and
the spread.
"""

from __future__ import annotations

import statistics
from pathlib import Path
from typing import Callable

from bench.machine import calibration_workload

__all__ = ["run", "PARTS"]

#: Parts of a session's CPU as the report groups them: (name, the scripted run's keys).
PARTS = (
    ("selection and delta", ("poll",)),
    ("poses and frame reports", ("receive:camera", "receive:frame_report")),
    ("acks and pongs", ("receive:ack", "receive:pong")),
    ("encoding", ("encode",)),
    ("snapshots", ("snapshot",)),
)


def _calibration_ms(rounds: int = 5) -> float:
    return 1e3 * statistics.median(calibration_workload() for _ in range(rounds))


def run(store: Path, *, clients: int = 40, seconds: float = 20.0, repeats: int = 3, save_interval: float = 1.0,
        separate: bool = False, progress: Callable[[str, int, int], None] | None = None) -> dict:
    """Figures of ``repeats`` scripted runs of ``clients`` sessions over ``seconds`` of virtual time on ``store``."""
    from bench.loadtest.scripted import run_scripted
    from server.scene.store import SceneStore
    from server.select import kernels
    from server.session import Session, SessionConfig
    from server.session.batch import poll_many
    from server.session.table import SceneTable

    kernels.warm_up()
    rows = []
    with SceneStore.open(store) as opened:
        scenes = {opened.index.name: opened}
        SceneTable.of(opened.index).prepare(SessionConfig().importance)  # as the app does when it opens a store
        config = SessionConfig()
        for r in range(repeats):
            if progress is not None:
                progress("scripted runs", r, repeats)
            before = _calibration_ms()
            result = run_scripted(scenes, clients, seconds, make_session=lambda i: Session(scenes, f"s{i:03d}", config),
                                  poll=poll_many, algorithms=("flat", "lit"), separate=separate,
                                  save_interval=save_interval, seed=r)
            after = _calibration_ms()
            per = result.per_session_second()
            row = {name: 1e3 * sum(per.get(k, 0.0) for k in keys) for name, keys in PARTS}
            row["total"] = 1e3 * per["total"]
            row["calibration_ms"] = (before + after) / 2
            row["deltas"], row["saves"] = result.deltas, result.snapshots
            rows.append(row)
            if progress is not None:
                progress("scripted runs", r + 1, repeats)
    names = [name for name, _ in PARTS] + ["total"]
    figures = {}
    for name in names:
        values = [row[name] for row in rows]
        ratios = [row[name] / row["calibration_ms"] for row in rows]
        figures[name] = {"ms": statistics.median(values), "min": min(values), "max": max(values),
                         "per_calibration": statistics.median(ratios)}
    total = figures["total"]["ms"]
    out = {"store": str(store), "clients": clients, "seconds": seconds, "repeats": repeats,
           "save_interval": save_interval, "separate": separate, "parts": figures, "runs": rows,
           "calibration_ms": statistics.median(row["calibration_ms"] for row in rows),
           "sessions_per_core": 1e3 / total if total > 0 else None}
    out["lines"] = _lines(out)
    return out


def _lines(out: dict) -> list[str]:
    lines = [f"{out['clients']} scripted sessions × {out['seconds']:g} s, {out['repeats']} repeats "
             f"(save every {out['save_interval']:g} s; calibration workload {out['calibration_ms']:.2f} ms)",
             f"{'CPU per session-second':<26}{'median':>9}{'spread':>17}{'× calibration':>15}"]
    for name, f in out["parts"].items():
        lines.append(f"{name:<26}{f['ms']:>7.2f} ms{f['min']:>8.2f}–{f['max']:.2f} ms{f['per_calibration']:>13.3f}")
    spc = out["sessions_per_core"]
    lines.append(f"sessions per core, these parts alone: {spc:.0f} (the websocket stack and event loop not included)"
                 if spc else "sessions per core: no CPU measured")
    return lines
