"""``walkstream bench select``: how fast and how well the selection solvers choose, on generated scenes.

Instances look like real scenes (Funkhouser & Séquin 1993, sections 4–5): the
pixels each object covers are heavy-tailed (log-normal), each level has four
times the faces of the one below, benefit = Size · Accuracy = size · (1 − 0.5 /
faces), cost = c_vertex · vertices + a per-draw overhead, and the budget holds
only part of the full-detail cost, so the multiple-choice knapsack bites.

Figures per size: the greedy from scratch; a coherent step of the incremental
"optimization" solver (the camera moved 0.5 m and 1°: sizes change by ~1.5 %,
a few objects enter and leave, the previous frame's solution and stopping value
are the start, as a session hands them on; beside it the same step without the
stopping value, which it then estimates on a sample);
optimality against the exact MIP optimum (small sizes) and the LP upper bound;
and, since a shared machine is noisy, the speed against a plain-Python
reference of the same greedy measured in the same run. Times are the
process's CPU seconds (the kernels run on the calling thread).

Goals: 100k from scratch ≤ 20 ms, coherent step at 100k ≤ 3 ms,
1M from scratch ≤ 250 ms, greedy ≥ 0.99 of the optimum at 1k.
"""

from __future__ import annotations

import math
import os
import platform
import statistics
import time
from typing import Callable

import numpy as np

__all__ = ["GOALS", "instance", "moved", "reference_greedy", "run", "C_VERTEX", "C_DRAW"]

#: Seconds per vertex (the server's first guess before frames are measured) and per draw call.
C_VERTEX = 2.0e-7
C_DRAW = 2.0e-6
#: Share of the full-detail cost the budget holds.
BUDGET_FRACTION = 0.45
#: The camera move of a coherent step: relative size noise, and share of objects entering/leaving.
SIZE_NOISE = 0.015
TURNOVER = 0.005

#: (name, objects, figure, bound, "max" | "min"): "max" means the figure must stay at or under the bound.
GOALS = (
    ("greedy_100k_ms", 100_000, "greedy_ms", 20.0, "max"),
    ("coherent_100k_ms", 100_000, "coherent_ms", 3.0, "max"),
    ("greedy_1m_ms", 1_000_000, "greedy_ms", 250.0, "max"),
    ("optimality_1k", 1_000, "greedy_vs_exact", 0.99, "min"),
)


# ----------------------------------------------------------------------------- instances


def _objects(rng: np.random.Generator, n: int, levels: int) -> tuple[np.ndarray, np.ndarray]:
    """(n,) pixels covered (log-normal: a few large objects, many small) and (n, levels) faces (×4 per level)."""
    size = np.clip(rng.lognormal(math.log(100.0), 1.5, n), 1.0, 2.0e6)
    base = np.maximum(1.0, np.rint(rng.lognormal(math.log(6.0), 0.8, n)))
    faces = (base[:, None] * 4.0 ** np.arange(levels)).astype(np.int64)
    return size, faces


def _tuples(size: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n, K) benefit = Size · Accuracy and cost = c_vertex · vertices + per-draw overhead."""
    from server.select.benefit import benefit as size_accuracy

    benefit = size_accuracy(size[:, None], faces)
    vertices = faces / 2.0 + 2.0  # a closed triangle mesh: V ≈ F / 2 + 2
    return benefit, C_VERTEX * vertices + C_DRAW


def instance(n: int, levels: int = 4, seed: int = 0, *, fraction: float = BUDGET_FRACTION):
    """A generated scene of ``n`` objects × ``levels`` levels: (Candidates, budget in seconds).

    Deterministic for (n, levels, seed). The budget is ``fraction`` of the full-detail cost, but
    never less than the coarsest level of every object: that always fits, full detail (levels ≥ 2,
    fraction < 1) does not.
    """
    from server.select.solvers.candidates import Candidates

    rng = np.random.default_rng([seed, n, levels])
    size, faces = _objects(rng, n, levels)
    benefit, cost = _tuples(size, faces)
    cand = Candidates.of(benefit, cost, size=size, faces=faces, previous=np.full(n, -1, np.int64))
    # 0.1 % over the coarsest total: a budget that exactly fits a sum leaves the answer to float rounding
    return cand, float(max(fraction * cost[:, -1].sum(), 1.001 * cost[:, 0].sum()))


def moved(cand, previous: np.ndarray, seed: int = 0, *, noise: float = SIZE_NOISE, turnover: float = TURNOVER):
    """The next frame after the camera moved 0.5 m and turned 1°, with ``previous`` as the last selection.

    Each object's size changes by multiplicative noise (an object tens of metres away grows or
    shrinks by ~2·0.5/d ≈ 1–2 %); a ``turnover`` share of the objects leaves the view and is
    replaced by new ones (previous −1). Costs of the objects that stay do not change.
    """
    from server.select.solvers.candidates import Candidates

    n, levels = cand.n, cand.k
    rng = np.random.default_rng([seed, n, levels, 1])
    size = cand.size * np.exp(rng.normal(0.0, noise, n))
    faces = cand.faces.copy()
    prev = np.asarray(previous, np.int64).copy()
    new = rng.random(n) < turnover
    size[new], faces[new] = _objects(rng, int(new.sum()), levels)
    prev[new] = -1
    benefit, cost = _tuples(size, faces)
    return Candidates.of(benefit, cost, size=size, faces=faces, previous=prev)


# ----------------------------------------------------------------------------- the plain reference


def reference_greedy(benefit: np.ndarray, cost: np.ndarray, budget: float) -> tuple[np.ndarray, float, float]:
    """The same greedy by value in plain Python: the yardstick the vectorised solvers are timed against.

    benefit, cost : (n, K) float — options of each object; returns ((n,) option or −1, cost, benefit).
    Builds each object's upper hull of (cost, benefit) from (0, 0), lists every increment as a
    tuple, sorts them all by value with ``sorted`` and takes, in falling value, each increment
    that is its object's next one and still fits; then compares with the best single option.
    """
    rows_b, rows_c = np.asarray(benefit, float).tolist(), np.asarray(cost, float).tolist()
    hulls, increments = [], []
    for i, (bs, cs) in enumerate(zip(rows_b, rows_c)):
        points = sorted((c, b, k) for k, (b, c) in enumerate(zip(bs, cs)) if 0 < c <= budget and math.isfinite(b))
        hull = [(0.0, 0.0, -1)]
        for c, b, k in points:
            if b <= hull[-1][1]:
                continue  # costs no less, gives no more
            while len(hull) >= 2:
                c2, b2, _ = hull[-2]
                c1, b1, _ = hull[-1]
                if (b1 - b2) * (c - c2) <= (b - b2) * (c1 - c2):
                    hull.pop()  # on or under the chord: never worth stopping at
                else:
                    break
            hull.append((c, b, k))
        hulls.append(hull)
        for j in range(1, len(hull)):
            d_cost = hull[j][0] - hull[j - 1][0]
            increments.append(((hull[j][1] - hull[j - 1][1]) / d_cost, d_cost, i, j))
    at = [0] * len(hulls)
    spent = 0.0
    for _, d_cost, i, j in sorted(increments, reverse=True):
        if at[i] == j - 1 and spent + d_cost <= budget:
            at[i] = j
            spent += d_cost
    level = [hull[j][2] for hull, j in zip(hulls, at)]
    total_c = sum(hull[j][0] for hull, j in zip(hulls, at))
    total_b = sum(hull[j][1] for hull, j in zip(hulls, at))
    single = max(((p[1], p[0], i, p[2]) for i, hull in enumerate(hulls) for p in hull[1:]), default=None)
    if single is not None and single[0] > total_b:
        level = [-1] * len(hulls)
        level[single[2]] = single[3]
        total_b, total_c = single[0], single[1]
    return np.asarray(level, np.int64), float(total_c), float(total_b)


# ----------------------------------------------------------------------------- measuring


def _median_time(fn: Callable, repeats: int, warmup: bool = True):
    """(median CPU seconds of this process over ``repeats`` calls, last result); one untimed call first when
    ``warmup``. CPU, not wall time: on a shared machine the other work's share of the cores is not the solver's."""
    if warmup:
        fn()
    times, out = [], None
    for _ in range(max(1, repeats)):
        t0 = time.process_time()
        out = fn()
        times.append(time.process_time() - t0)
    return statistics.median(times), out


def _exact(cand, budget: float):
    """The MIP optimum (exact.solve scales costs to the budget itself)."""
    from server.select.solvers import exact

    return exact.solve(cand, budget)


def _ratio(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None or not b > 0 else a / b


def _measure(n: int, levels: int, repeats: int, seed: int, exact_max: int, reference_max: int,
             tick: Callable[[str], None]) -> dict:
    from server.select import solvers
    from server.select.solvers import exact

    greedy, optimization = solvers.get("greedy"), solvers.get("optimization")
    cand, budget = instance(n, levels, seed)
    row: dict = {"objects": n, "options": n * levels, "budget_s": budget,
                 "budget_fraction": budget / float(cand.cost[:, -1].sum()),
                 "coarsest_fraction": float(cand.cost[:, 0].sum()) / budget}

    tick("greedy")
    t, r = _median_time(lambda: greedy(cand, budget), repeats)
    row.update(greedy_ms=t * 1e3, greedy_benefit=r.benefit, greedy_cost=r.cost,
               greedy_feasible=bool(r.cost <= budget * (1 + 1e-9)))
    # The same greedy in numpy passes: what the compiled kernels are measured against.
    from server.select.solvers import greedy as greedy_module

    t_np, r_np = _median_time(lambda: greedy_module.solve_numpy(cand, budget), repeats)
    row.update(greedy_numpy_ms=t_np * 1e3, kernels_speedup=_ratio(t_np, t),
               numpy_agrees=bool(abs(r_np.benefit - r.benefit) <= 1e-9 * max(abs(r.benefit), 1.0)))

    tick("coherent")
    nxt = moved(cand, r.level, seed)
    # As a session runs it: the last frame's selection and its stopping value are the start.
    state = _last_frame(r)
    t, o = _median_time(lambda: optimization(nxt, budget, state=state), repeats)
    t_cold, _ = _median_time(lambda: optimization(nxt, budget), repeats)
    t_scratch, g1 = _median_time(lambda: greedy(nxt, budget), repeats)
    row.update(coherent_ms=t * 1e3, coherent_cold_ms=t_cold * 1e3, coherent_greedy_ms=t_scratch * 1e3,
               coherent_speedup=_ratio(t_scratch, t), optimization_benefit=o.benefit, optimization_cost=o.cost,
               optimization_feasible=bool(o.cost <= budget * (1 + 1e-9)),
               optimization_vs_greedy=_ratio(o.benefit, g1.benefit),
               coherent_rounds=o.stats.get("rounds"), coherent_moves=o.stats.get("moves"),
               coherent_fallback=o.stats.get("fallback"),
               entered=int((nxt.previous < 0).sum()))

    tick("bounds")
    lp0, lp1 = exact.upper_bound(cand, budget), exact.upper_bound(nxt, budget)
    row.update(lp_bound=lp0, greedy_vs_lp=_ratio(r.benefit, lp0), optimization_vs_lp=_ratio(o.benefit, lp1))
    row.update(exact_benefit=None, exact_ms=None, greedy_vs_exact=None, optimization_vs_exact=None)
    if n <= exact_max:
        tick("exact")
        t0 = time.perf_counter()
        e0 = _exact(cand, budget)
        row["exact_ms"] = (time.perf_counter() - t0) * 1e3
        e1 = _exact(nxt, budget)
        row.update(exact_benefit=e0.benefit, exact_status=e0.stats.get("status"),
                   greedy_vs_exact=_ratio(r.benefit, e0.benefit), optimization_vs_exact=_ratio(o.benefit, e1.benefit))

    row.update(reference_ms=None, reference_benefit=None, speedup_vs_reference=None)
    if n <= reference_max:
        tick("reference")
        reps = repeats if n <= 10_000 else 1  # plain Python at 100k takes seconds; it does not warm up
        t, (_, _, b) = _median_time(lambda: reference_greedy(cand.benefit, cand.cost, budget), reps,
                                    warmup=n <= 10_000)
        row.update(reference_ms=t * 1e3, reference_benefit=b, speedup_vs_reference=_ratio(t * 1e3, row["greedy_ms"]))
    return row


def coherent_step_ms(n: int = 100_000, levels: int = 4, repeats: int = 7, seed: int = 0) -> float:
    """The incremental solver's coherent step on the generated instance of ``n`` objects: median CPU ms."""
    from server.select import kernels, solvers

    kernels.warm_up(setting=os.environ.get("WALKSTREAM_NUMBA"))
    greedy, optimization = solvers.get("greedy"), solvers.get("optimization")
    cand, budget = instance(n, levels, seed)
    last = greedy(cand, budget)
    nxt, state = moved(cand, last.level, seed), _last_frame(last)
    t, _ = _median_time(lambda: optimization(nxt, budget, state=state), repeats)
    return t * 1e3


def _last_frame(result) -> dict:
    """The solver state a session hands the next selection (``selection.Memory``): the stopping value."""
    return {"threshold": result.stats.get("threshold")}


def _goals(rows: list[dict]) -> list[dict]:
    by_n = {r["objects"]: r for r in rows}
    out = []
    for name, n, figure, bound, kind in GOALS:
        value = by_n[n].get(figure) if n in by_n else None
        goal = {"goal": name, "objects": n, "figure": figure, "bound": bound, "kind": kind, "value": value,
                "met": None, "margin": None}
        if value is not None:
            goal["met"] = bool(value <= bound) if kind == "max" else bool(value >= bound)
            goal["margin"] = bound - value if kind == "max" else value - bound  # > 0: met with room to spare
        out.append(goal)
    return out


def _fmt(v, spec: str, none: str = "—") -> str:
    return none if v is None else format(v, spec)


def _lines(result: dict) -> list[str]:
    lines = [f"bench select: {result['levels']} levels, median of {result['repeats']} after a warm-up, "
             f"seed {result['seed']}, budget {BUDGET_FRACTION:.0%} of full detail, {result['machine']['cpus']} CPUs, "
             f"kernels {result['kernels']} (ready in {result['kernels_warm_s']:.1f} s)"]
    for r in result["sizes"]:
        lines.append(
            f"{r['objects']:>9,} objects  greedy {r['greedy_ms']:8.2f} ms (numpy {r['greedy_numpy_ms']:.2f})  coherent {r['coherent_ms']:7.2f} ms "
            f"(without last θ {r['coherent_cold_ms']:.2f}, scratch {r['coherent_greedy_ms']:.2f}, "
            f"{_fmt(r['coherent_rounds'], 'd')} rounds)  "
            f"greedy/exact {_fmt(r['greedy_vs_exact'], '.6f')}  greedy/LP {_fmt(r['greedy_vs_lp'], '.6f')}  "
            f"optimization/LP {_fmt(r['optimization_vs_lp'], '.6f')}  reference "
            + ("not run" if r["reference_ms"] is None
               else f"{r['reference_ms']:.1f} ms (greedy ×{r['speedup_vs_reference']:.0f} faster)"))
    for g in result["goals"]:
        unit = " ms" if g["figure"].endswith("_ms") else ""
        op = "≤" if g["kind"] == "max" else "≥"
        if g["met"] is None:
            lines.append(f"goal {g['goal']:<17} {op} {g['bound']:g}{unit}: not measured (size {g['objects']:,} not run)")
        else:
            spec = ".2f" if unit else ".5f"
            lines.append(f"goal {g['goal']:<17} {op} {g['bound']:g}{unit}: {format(g['value'], spec)}{unit} — "
                         f"{'met' if g['met'] else 'MISSED'}, margin {g['margin']:+{spec}}{unit}")
    return lines


def run(sizes=(1_000, 10_000, 100_000, 1_000_000), levels: int = 4, repeats: int = 7, seed: int = 0,
        progress: Callable[[str, int, int], None] | None = None, *, exact_max: int = 1_000,
        reference_max: int = 100_000) -> dict:
    """Measure every size; returns {"sizes": [figures per size], "goals": [...], "lines": [...], ...}.

    exact_max : largest size solved by the MIP (it is the slow yardstick)
    reference_max : largest size timed with the plain-Python reference
    progress : ``progress(stage, done, total)`` called as each part starts and ends
    """
    sizes = [int(s) for s in sizes]
    if not sizes or min(sizes) < 1 or levels < 1 or repeats < 1:
        raise ValueError("sizes, levels and repeats must be positive")
    parts = ("greedy", "coherent", "bounds", "exact", "reference")
    from server.select import kernels

    t0 = time.perf_counter()
    # Time the solvers as a warm server runs them, not while numba compiles.
    compiled = kernels.warm_up(setting=os.environ.get("WALKSTREAM_NUMBA"))
    warm_s = time.perf_counter() - t0
    rows = []
    for n in sizes:
        stage = f"{n:,} objects"

        def tick(part: str, stage=stage) -> None:
            if progress is not None:
                progress(stage, parts.index(part), len(parts))

        rows.append(_measure(n, levels, repeats, seed, exact_max, reference_max, tick))
        if progress is not None:
            progress(stage, len(parts), len(parts))
    import numpy

    result = {"levels": levels, "repeats": repeats, "seed": seed, "budget_fraction": BUDGET_FRACTION,
              "kernels": "numba" if compiled else "numpy", "kernels_warm_s": warm_s,
              "c_vertex": C_VERTEX, "c_draw": C_DRAW, "size_noise": SIZE_NOISE, "turnover": TURNOVER,
              "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "numpy": numpy.__version__},
              "sizes": rows, "goals": _goals(rows)}
    result["lines"] = _lines(result)
    return result
