"""``walkstream bench build``: how fast scenes build, how big their stores are, how fast they open.

A shared machine is noisy, so next to each figure stands a reference
measured in the same run: the raw throughput of the quadric simplifier
(fast-simplification halving a fixed 81k-triangle mesh), the step every
build's chain stage is made of. ``ratio`` = build triangles/s ÷ simplifier
triangles/s says how much of the build is the simplifier's own work.

Goals: megacity builds in under 10 minutes on two cores and its index loads
in at most 2 s.
"""

from __future__ import annotations

import shutil
import statistics
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np

from server.scene.catalog import build_named
from server.scene.store import SceneStore

__all__ = ["run_build_bench", "simplifier_reference"]

GOALS = {"megacity": {"build_s": 600.0, "index_load_s": 2.0}}


def simplifier_reference(repeats: int = 3) -> float:
    """Triangles per second that fast-simplification removes-and-keeps on a fixed mesh (best of repeats)."""
    import fast_simplification
    import trimesh

    mesh = trimesh.creation.icosphere(6)  # 81,920 triangles
    v = mesh.vertices * (1 + 0.05 * np.sin(7 * mesh.vertices[:, :1]) * np.cos(5 * mesh.vertices[:, 1:2]))
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fast_simplification.simplify(v, mesh.faces, target_reduction=0.5)
        best = min(best, time.perf_counter() - t0)
    return mesh.faces.shape[0] / best


def index_load_time(path: Path, repeats: int = 3) -> float:
    """Median seconds to open a store and load its index."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        with SceneStore.open(path):
            pass
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def run_build_bench(scenes: list[str], *, size: int | None = None, workers: int | None = None,
                    keep: Path | None = None, progress: Callable | None = None) -> dict:
    """Build each scene once; returns figures per scene plus printable lines."""
    reference = simplifier_reference()
    folder = Path(keep) if keep else Path(tempfile.mkdtemp(prefix="walkstream-bench-"))
    folder.mkdir(parents=True, exist_ok=True)
    rows = []
    try:
        for name in scenes:
            path = folder / f"{name}.db"
            summary = build_named(name, path, size=size, workers=workers, progress=progress)
            seconds = float(summary["seconds"])
            tris = int(summary["triangles"])
            row = {
                "scene": name,
                "build_s": round(seconds, 2),
                "triangles": tris,
                "triangles_per_s": round(tris / seconds),
                "ratio_to_simplifier": round(tris / seconds / reference, 4),
                "store_bytes": path.stat().st_size,
                "index_load_s": round(index_load_time(path), 4),
                "objects": summary.get("objects"),
                "stages": summary.get("stages", {}),
            }
            goal = GOALS.get(name)
            if goal and size is None:
                row["goals_met"] = row["build_s"] < goal["build_s"] and row["index_load_s"] <= goal["index_load_s"]
            rows.append(row)
    finally:
        if keep is None:
            shutil.rmtree(folder, ignore_errors=True)
    lines = [f"reference: fast-simplification halves {reference / 1e6:.2f} M triangles/s on this machine"]
    for r in rows:
        goal = "" if "goals_met" not in r else ("  goals met" if r["goals_met"] else "  GOALS MISSED")
        lines.append(
            f"{r['scene']:<11} {r['build_s']:8.1f} s  {r['triangles'] / 1e6:7.2f} M tris  "
            f"{r['triangles_per_s'] / 1e3:8.1f} k tris/s  (×{r['ratio_to_simplifier']:.3f} of the simplifier)  "
            f"store {r['store_bytes'] / 1e6:7.1f} MB  index {r['index_load_s'] * 1e3:7.1f} ms{goal}")
    return {"reference_simplifier_tris_per_s": round(reference), "scenes": rows, "lines": lines}
