"""A kiosk's tour, and how much the prediction gains from knowing it (``walkstream bench predict --kiosk``).

A kiosk plays tours of stops: the camera stands at a stop (``dwell`` seconds),
turns towards the way on, walks there at a bounded speed along walkable ground
(``proto.walkpath``), turns to the next stop's view and stands again.
Such a path is the worst case of linear extrapolation — every stop is a sudden
halt, every turn a sudden change — and the best case of a server told the tour
(``proto.messages.TourPlan``).

Two comparisons on the same tour:

- **prediction error**: the tour sampled as a client sends its camera, fed to a
  ``Predictor`` that extrapolates linearly, one confined to the walkable grid
  (walk mode, as a visitor driving would be predicted) and one told the tour as
  a plan; eye error (m) and view error (°) at each horizon, and their ratios to
  linear;
- **image error**: the real server and headless client run the tour twice —
  the client sending its plan in the hello, and not — and the traces are
  replayed against full detail (``bench.quality``): FLIP and PSNR with the plan
  against without.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
from scipy import ndimage

from proto.messages import Navigation, TourKey, TourPlan
from proto.tour import Tour
from proto.walkable import WalkableGrid
from proto.walkpath import largest_region, walk_path
from server.select.navigation import Navigable
from server.select.predict import Predictor

__all__ = ["kiosk_tour", "predict_kiosk", "image_kiosk", "KIOSK_HORIZONS"]

KIOSK_HORIZONS = (0.25, 0.5, 1.0, 1.5)
MODES = ("linear", "walk", "plan")

Tick = Callable[[str, int, int], None]


def _stops(grid: WalkableGrid, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` stops (n, 2) spread over the largest walkable region: farthest-point picks among its cells."""
    region = largest_region(grid)
    rows, cols = np.nonzero(region)
    if rows.size == 0:
        raise ValueError("the scene has no walkable ground for a kiosk tour")
    # Stay a few cells from the region's edge: a stop against a wall looks at the wall.
    inner = ndimage.binary_erosion(region, iterations=max(1, int(round(0.6 / grid.cell))))
    if inner.any():
        rows, cols = np.nonzero(inner)
    centres = np.asarray(grid.origin) + (np.column_stack([cols, rows]) + 0.5) * grid.cell
    picks = [int(rng.integers(len(centres)))]
    dist = np.linalg.norm(centres - centres[picks[0]], axis=1)
    for _ in range(n - 1):
        picks.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.linalg.norm(centres - centres[picks[-1]], axis=1))
    return centres[picks]


def _forward(yaw: float, pitch: float) -> list[float]:
    return [math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), math.sin(pitch)]


def kiosk_tour(grid: WalkableGrid, *, stops: int = 4, dwell: float = 4.0, first_dwell: float = 1.0,
               speed: float = 1.2, turn_deg: float = 60.0, eye_height: float = 1.7, pitch_deg: float = -5.0,
               seed: int = 0) -> list[dict]:
    """A closed kiosk tour on ``grid``: keys {"t", "eye", "forward", "up"} (``TourKey`` fields).

    At each stop the camera stands ``dwell`` s (``first_dwell`` at the first, so a short run sees motion
    soon), turns at ``turn_deg`` °/s to the way on, walks at ``speed`` m/s along the shortest walk to the
    next stop, turns to a view of its own and stands again; the last leg returns to the first stop.
    """
    if stops < 2:
        raise ValueError(f"a kiosk tour needs at least 2 stops, got {stops}")
    if not (speed > 0 and turn_deg > 0 and dwell >= 0 and first_dwell >= 0):
        raise ValueError("speed and turn_deg must be positive, dwell and first_dwell non-negative")
    rng = np.random.default_rng(seed)
    where = _stops(grid, stops, rng)
    views = rng.uniform(-math.pi, math.pi, stops)  # each stop looks its own way
    pitch, turn = math.radians(pitch_deg), math.radians(turn_deg)
    keys: list[dict] = []
    t, yaw = 0.0, float(views[0])

    def key(xy, heading: float) -> None:
        z = float(grid.height(np.asarray(xy)[None, :])[0]) + eye_height
        keys.append({"t": round(t, 6), "eye": [float(xy[0]), float(xy[1]), z], "forward": _forward(heading, pitch),
                     "up": [0.0, 0.0, 1.0]})

    def turn_to(xy, heading: float) -> float:
        nonlocal t, yaw
        delta = (heading - yaw + math.pi) % (2 * math.pi) - math.pi
        steps = max(1, int(math.ceil(abs(delta) / math.radians(45.0))))  # keys every ≤ 45°: nlerp stays close
        for k in range(1, steps + 1):
            t += abs(delta) / turn / steps
            key(xy, yaw + delta * k / steps)
        yaw = yaw + delta
        return yaw

    for i in range(stops):
        here, there = where[i], where[(i + 1) % stops]
        key(here, yaw)
        t += first_dwell if i == 0 else dwell
        key(here, yaw)
        path = walk_path(grid, here, there)
        for a, b in zip(path[:-1], path[1:]):
            heading = math.atan2(b[1] - a[1], b[0] - a[0])
            turn_to(a, heading)
            length = float(np.linalg.norm(b - a))
            n = max(1, int(math.ceil(length / 0.5)))  # a key every ≤ 0.5 m: the eye follows the ground's steps
            for k in range(1, n + 1):
                t += length / n / speed
                key(a + (b - a) * k / n, heading)
        turn_to(there, float(views[(i + 1) % stops]))
    keys[-1] = {**keys[0], "t": keys[-1]["t"]}  # closed: the loop starts again where it began
    return keys


def _samples(tour: Tour, rate: float, duration: float) -> tuple[np.ndarray, ...]:
    t = tour.t[0] + np.arange(int(math.floor(duration * rate)) + 1) / rate
    eye, fwd, up = tour.pose_at(t)
    return t, eye, fwd, up


def predict_kiosk(keys: Sequence[dict], grid: WalkableGrid, *, horizons: Sequence[float] = KIOSK_HORIZONS,
                  rate: float = 20.0, warmup: float = 1.0, eye_height: float = 1.7,
                  progress: Tick | None = None) -> dict:
    """Prediction error on one loop of the kiosk tour ``keys``, per horizon: linear, walk-confined and
    tour-aware (the whole loop sent as a plan) predictors fed the same samples.

    Returns {"rows": [{"horizon", "<mode>_pos_mean", "<mode>_pos_p95", "<mode>_ang_mean", "<mode>_ang_p95",
    "<mode>_pos_ratio", "<mode>_ang_ratio" (to linear) …}], "lines": [...], "config": {...}}.
    """
    tour = Tour(keys)
    t, eye, fwd, up = _samples(tour, rate, tour.duration)
    h = np.asarray(horizons, np.float64)
    scored = np.flatnonzero((t >= t[0] + warmup) & (t + h.max() <= tour.t[-1]))
    plan = TourPlan(t=0.0, keys=[TourKey(**k) for k in keys], tour="kiosk")
    predictors = {m: Predictor() for m in MODES}
    predictors["walk"].navigable = Navigable.of(Navigation(mode="walk", eye_height=eye_height), grid)
    predictors["plan"].set_plan(plan, np.array([[-1e6] * 3, [1e6] * 3]))
    pos = {m: np.zeros((h.size, scored.size)) for m in MODES}
    ang = {m: np.zeros((h.size, scored.size)) for m in MODES}
    truth = [tour.pose_at(t[scored] + hk) for hk in h]
    j = 0
    for i in range(t.size):
        for p in predictors.values():
            p.add(t[i], eye[i], fwd[i], up[i])
        if j < scored.size and scored[j] == i:
            for m, p in predictors.items():
                for k, q in enumerate(p.poses(t[i] + h)):
                    pos[m][k, j] = np.linalg.norm(q.eye - truth[k][0][j])
                    ang[m][k, j] = math.degrees(math.acos(min(1.0, max(-1.0, float(q.forward @ truth[k][1][j])))))
            j += 1
        if progress is not None and (i % 50 == 0 or i == t.size - 1):
            progress("predict kiosk", i + 1, t.size)
    rows = []
    for k, hk in enumerate(h):
        row: dict[str, Any] = {"horizon": float(hk), "n": int(scored.size)}
        for m in MODES:
            row.update({f"{m}_pos_mean": float(pos[m][k].mean()), f"{m}_pos_p95": float(np.percentile(pos[m][k], 95)),
                        f"{m}_ang_mean": float(ang[m][k].mean()), f"{m}_ang_p95": float(np.percentile(ang[m][k], 95))})
        for m in ("walk", "plan"):
            for what in ("pos", "ang"):
                base = row[f"linear_{what}_mean"]
                row[f"{m}_{what}_ratio"] = row[f"{m}_{what}_mean"] / base if base > 1e-12 else None
        rows.append(row)
    config = {"keys": len(keys), "tour_seconds": tour.duration, "rate": rate, "warmup": warmup,
              "horizons": [float(x) for x in h], "eye_height": eye_height}
    return {"rows": rows, "lines": _lines(rows), "config": config}


def _num(v, width: int, digits: int) -> str:
    return f"{'-':>{width}}" if v is None else f"{v:{width}.{digits}f}"


def _lines(rows: list[dict]) -> list[str]:
    head = (f"{'h s':>5} │ {'linear m':>8} {'walk m':>7} {'plan m':>7} {'walk/lin':>8} {'plan/lin':>8} │"
            f" {'linear °':>8} {'walk °':>7} {'plan °':>7} {'walk/lin':>8} {'plan/lin':>8}")
    out = ["kiosk tour: prediction error (mean eye m, mean view °) — linear, walk-confined, tour-aware", head,
           "─" * len(head)]
    for r in rows:
        out.append(
            f"{r['horizon']:5.2f} │ {_num(r['linear_pos_mean'], 8, 3)} {_num(r['walk_pos_mean'], 7, 3)}"
            f" {_num(r['plan_pos_mean'], 7, 3)} {_num(r['walk_pos_ratio'], 8, 3)} {_num(r['plan_pos_ratio'], 8, 3)} │"
            f" {_num(r['linear_ang_mean'], 8, 2)} {_num(r['walk_ang_mean'], 7, 2)} {_num(r['plan_ang_mean'], 7, 2)}"
            f" {_num(r['walk_ang_ratio'], 8, 3)} {_num(r['plan_ang_ratio'], 8, 3)}")
    return out


def image_kiosk(store: str | Path, keys: Sequence[dict], *, duration: float = 6.0, viewport=(320, 180),
                target_ms: float = 50.0, method: str = "predictive", warmup: float = 2.0, samples: int = 12,
                tau: float = 0.5, progress: Tick | None = None) -> dict:
    """The eval's image error on the kiosk tour with and without the plan: one real server, the headless
    client run twice over ``duration`` s of the tour (``bench.evaluate.run_one``, ``plan`` off then on), each
    run's traces replayed against full detail (``samples`` frames after ``warmup``).

    Returns {"runs": {"linear": summary, "plan": summary}, "ratios": {"flip", "psnr"} (plan / linear),
    "lines": [...], "config": {...}}; a summary holds flip_mean, psnr_mean, ssim_mean, popping_mean,
    frames, late and errors.
    """
    from bench import quality as q
    from bench.demo import ServerProcess
    from bench.evaluate import RunSpec, run_one
    from bench.methods import METHODS
    from bench.replay import Replayer
    from server.scene.store import SceneStore

    if not duration > warmup:
        raise ValueError(f"the duration ({duration} s) must exceed the warm-up ({warmup} s)")
    with SceneStore.open(store) as s:
        scene = s.index.name
    spec = RunSpec(METHODS[method], float(target_ms))
    runs: dict[str, dict] = {}
    traced: dict[str, list] = {}
    with ServerProcess([Path(store)], extra=["--tau", str(tau)]) as server:
        for i, mode in enumerate(("linear", "plan")):
            if progress is not None:
                progress("kiosk runs", i, 2)
            run, traces = run_one(server.url, scene, spec, duration=duration, viewport=tuple(viewport),
                                  tour=list(keys), warmup=warmup, calibrate=False, plan=mode == "plan")
            runs[mode], traced[mode] = run, traces
    out: dict[str, dict] = {}
    with Replayer(store, viewport=tuple(viewport)) as replayer:
        for i, mode in enumerate(("linear", "plan")):
            if progress is not None:
                progress("kiosk quality", i, 2)
            measured = q.measure(replayer, traced[mode], warmup=warmup, samples=samples, every=1)
            summary = runs[mode]["summary"]
            out[mode] = {**q.summary(measured), "frames": summary["frames"], "late": summary["late"],
                         "errors": summary["errors"], "samples": len(measured.get("flip", []))}
    ratios = {k: (out["plan"][f"{k}_mean"] / out["linear"][f"{k}_mean"]
                  if out["linear"][f"{k}_mean"] and math.isfinite(out["linear"][f"{k}_mean"]) else None)
              for k in ("flip", "psnr")}
    lines = [f"kiosk tour on {scene}: image error against full detail ({duration:g} s, {viewport[0]}×{viewport[1]}, "
             f"{method} at {target_ms:g} ms)",
             f"  linear prediction: FLIP {out['linear']['flip_mean']:.4f}  PSNR {out['linear']['psnr_mean']:.2f} dB"
             f"  ({out['linear']['samples']} frames, {out['linear']['late']} late deltas)",
             f"  tour-aware:        FLIP {out['plan']['flip_mean']:.4f}  PSNR {out['plan']['psnr_mean']:.2f} dB"
             f"  ({out['plan']['samples']} frames, {out['plan']['late']} late deltas)",
             f"  ratio tour-aware / linear: FLIP {_num(ratios['flip'], 0, 3)}, PSNR {_num(ratios['psnr'], 0, 3)}"]
    config = {"scene": scene, "duration": duration, "viewport": list(viewport), "target_ms": target_ms,
              "method": method, "warmup": warmup, "samples": samples, "tau": tau}
    return {"runs": out, "ratios": ratios, "lines": lines, "config": config}
