"""``walkstream bench predict`` (prediction part): how far ahead the linear path prediction is right.

The selection for [t + 2τ, t + 3τ) is made from the camera samples the client
sent up to t (Zach 2002, 3.3 and 4.3), so what matters is the error of the
predicted pose against the horizon. Each scene's tour is sampled as the client
sends camera samples (``rate`` Hz, optionally with Gaussian jitter), fed to a
``Predictor``, and at every sample time after one second of warm-up the pose at
t + h is predicted and compared with the tour's true pose: eye distance (m)
and view-direction angle (degrees). The reference is the zero-order hold (the
last sample as it came), measured on the same samples, so ``ratio`` < 1 means
the prediction beats not predicting at all.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from proto.tour import Tour
from server.select.predict import MotionLimits, Predictor

__all__ = ["run", "tours_from_stores", "WARMUP", "HORIZONS"]

#: Seconds of samples before predictions are scored: the window has to fill first.
WARMUP = 1.0
HORIZONS = (0.25, 0.5, 1.0, 1.5, 2.0)
#: Tour seconds scored for a fixed camera (a one-key tour has no loop to take the length from).
STILL_SECONDS = 10.0

Tick = Callable[[str, int, int], None]


def tours_from_stores(paths: Sequence[str | Path]) -> list[tuple[str, list[dict]]]:
    """(scene name, tour keys) of each scene store, in the order given."""
    from server.scene.store import SceneStore

    out = []
    for path in paths:
        with SceneStore.open(path) as store:
            out.append((store.index.name, [dict(k) for k in store.index.tour]))
    return out


def _jittered(rng: np.random.Generator, eye, forward, up, jitter: float, turn_jitter: float):
    """The samples as a noisy tracker would send them: eye ± jitter m, forward and up turned by ~turn_jitter rad."""
    eye = eye + rng.normal(0.0, jitter, eye.shape) if jitter > 0 else eye
    if turn_jitter > 0:
        forward = forward + rng.normal(0.0, turn_jitter / math.sqrt(2), forward.shape)
        forward /= np.linalg.norm(forward, axis=1, keepdims=True)
        up = up + rng.normal(0.0, turn_jitter / math.sqrt(2), up.shape)
    return eye, forward, up


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n,) degrees between rows of unit vectors (n, 3)."""
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", a, b), -1.0, 1.0)))


def _figures(pos: np.ndarray, ang: np.ndarray, pos_hold: np.ndarray, ang_hold: np.ndarray) -> dict[str, Any]:
    def ratio(a: float, b: float) -> float | None:
        return a / b if b > 1e-12 else None

    r = {
        "n": int(len(pos)),
        "pos_mean": float(pos.mean()), "pos_p95": float(np.percentile(pos, 95)),
        "ang_mean": float(ang.mean()), "ang_p95": float(np.percentile(ang, 95)),
        "hold_pos_mean": float(pos_hold.mean()), "hold_pos_p95": float(np.percentile(pos_hold, 95)),
        "hold_ang_mean": float(ang_hold.mean()), "hold_ang_p95": float(np.percentile(ang_hold, 95)),
    }
    r["pos_ratio"] = ratio(r["pos_mean"], r["hold_pos_mean"])
    r["ang_ratio"] = ratio(r["ang_mean"], r["hold_ang_mean"])
    return r


def _times(tour: Tour, rate: float, duration: float | None) -> np.ndarray:
    """Sample times over ``duration`` seconds of tour (default one loop), ``rate`` per second."""
    span = duration if duration is not None else (tour.duration if tour.duration > 0 else STILL_SECONDS)
    return tour.t[0] + np.arange(int(math.floor(span * rate)) + 1) / rate


def _scene(
    tour: Tour, horizons: Sequence[float], rate: float, jitter: float, turn_jitter: float, seed: int,
    duration: float | None, options: Mapping[str, Any], tick: Callable[[int], None],
) -> dict[float, tuple[np.ndarray, ...]]:
    """Per horizon: (position error, angle error, hold position error, hold angle error), each (n,)."""
    t = _times(tour, rate, duration)
    eye, forward, up = tour.pose_at(t)
    eye, forward, up = _jittered(np.random.default_rng(seed), eye, forward, up, jitter, turn_jitter)
    scored = np.flatnonzero(t >= t[0] + WARMUP)
    h = np.asarray(horizons, np.float64)
    truth = [tour.pose_at(t[scored] + hk) for hk in h]  # per horizon: eye, forward, up (m, 3)
    pred_eye = np.empty((len(h), len(scored), 3))
    pred_fwd = np.empty_like(pred_eye)
    opts = dict(options)
    limits = opts.pop("limits", MotionLimits())
    predictor = Predictor(limits, **opts)
    j = 0
    for i in range(len(t)):
        predictor.add(t[i], eye[i], forward[i], up[i])
        if j < len(scored) and scored[j] == i:
            for k, hk in enumerate(h):
                q = predictor.pose(t[i] + hk)
                pred_eye[k, j], pred_fwd[k, j] = q.eye, q.forward
            j += 1
        tick(i + 1)
    out = {}
    for k, hk in enumerate(h):
        true_eye, true_fwd, _ = truth[k]
        out[float(hk)] = (
            np.linalg.norm(pred_eye[k] - true_eye, axis=1),
            _angle_deg(pred_fwd[k], true_fwd),
            np.linalg.norm(eye[scored] - true_eye, axis=1),
            _angle_deg(forward[scored], true_fwd),
        )
    return out


def _lines(rows: list[dict]) -> list[str]:
    def num(v: float | None, width: int, digits: int) -> str:
        return f"{'-':>{width}}" if v is None else f"{v:{width}.{digits}f}"

    name_w = max([5] + [len(r["scene"]) for r in rows])
    head = (f"{'scene':<{name_w}} {'h s':>5} │ {'pos mean':>8} {'p95':>7} {'hold':>7} {'hold95':>7} {'ratio':>6} │"
            f" {'ang mean':>8} {'p95':>7} {'hold':>7} {'hold95':>7} {'ratio':>6}")
    lines = ["prediction error against horizon (position m, view direction °; ratio = predicted / hold mean)",
             head, "─" * len(head)]
    for r in rows:
        lines.append(
            f"{r['scene']:<{name_w}} {r['horizon']:5.2f} │ {num(r['pos_mean'], 8, 3)} {num(r['pos_p95'], 7, 3)}"
            f" {num(r['hold_pos_mean'], 7, 3)} {num(r['hold_pos_p95'], 7, 3)} {num(r['pos_ratio'], 6, 2)} │"
            f" {num(r['ang_mean'], 8, 2)} {num(r['ang_p95'], 7, 2)} {num(r['hold_ang_mean'], 7, 2)}"
            f" {num(r['hold_ang_p95'], 7, 2)} {num(r['ang_ratio'], 6, 2)}"
        )
    return lines


def run(
    scenes: list[tuple[str, list[dict]]],
    horizons: Sequence[float] = HORIZONS,
    rate: float = 20.0,
    jitter: float = 0.0,
    seed: int = 0,
    progress: Tick | None = None,
    *,
    turn_jitter_deg: float | None = None,
    duration: float | None = None,
    predictor: Mapping[str, Any] | None = None,
) -> dict:
    """Prediction error against horizon on each scene's tour, beside the zero-order hold.

    scenes : (name, tour keys {"t", "eye", "forward", "up"}) pairs, e.g. from ``tours_from_stores``
    rate : camera samples per second; jitter : Gaussian noise on the eye, metres;
    turn_jitter_deg : noise on the view direction (default 0.5° when ``jitter`` > 0, else none)
    duration : tour seconds sampled (default one loop of each tour)
    predictor : keyword arguments of ``Predictor`` (``limits`` = a ``MotionLimits``)
    progress : tick(stage, done, total), called as samples are fed
    returns {"rows": [...], "lines": [...], "config": {...}}: a row per scene and horizon (and per
    horizon over all scenes when there are several) with mean and p95 errors, the hold's, and ratios.
    """
    if not scenes:
        raise ValueError("no scenes to run")
    if not (rate > 0 and math.isfinite(rate)):
        raise ValueError(f"rate must be positive, got {rate}")
    if not horizons or min(horizons) <= 0:
        raise ValueError(f"horizons must be positive, got {horizons}")
    if jitter < 0 or (turn_jitter_deg is not None and turn_jitter_deg < 0):
        raise ValueError("jitter must be non-negative")
    turn_jitter = math.radians(turn_jitter_deg if turn_jitter_deg is not None else (0.5 if jitter > 0 else 0.0))
    options = dict(predictor or {})
    rows: list[dict] = []
    pooled: dict[float, list[tuple[np.ndarray, ...]]] = {float(h): [] for h in horizons}
    for s, (name, keys) in enumerate(scenes):
        stage = f"predict {name}"
        tour = Tour(keys)
        total = len(_times(tour, rate, duration))
        every = max(1, total // 100)

        def tick(done: int, stage=stage, total=total, every=every) -> None:
            if progress is not None and (done % every == 0 or done == total):
                progress(stage, done, total)

        errors = _scene(tour, horizons, rate, jitter, turn_jitter, seed + s, duration, options, tick)
        for h, e in errors.items():
            if len(e[0]):
                rows.append({"scene": name, "horizon": h, **_figures(*e)})
                pooled[h].append(e)
    if len(scenes) > 1:
        for h, parts in pooled.items():
            if parts:
                rows.append({"scene": "all", "horizon": h, **_figures(*(np.concatenate(c) for c in zip(*parts)))})
    config = {
        "scenes": [name for name, _ in scenes], "horizons": [float(h) for h in horizons], "rate": float(rate),
        "jitter": float(jitter), "turn_jitter_deg": math.degrees(turn_jitter), "seed": int(seed),
        "warmup": WARMUP, "duration": duration,
        "predictor": {k: (repr(v) if k == "limits" else v) for k, v in options.items()},
    }
    return {"rows": rows, "lines": _lines(rows), "config": config}
