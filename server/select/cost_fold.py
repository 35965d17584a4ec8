"""Frames folded into an ``OnlineCostModel`` in one compiled pass: its state packed into arrays and back.

A session folds the frame reports that arrived since its last selection when the
selection reads the model (``OnlineCostModel(batch=True)``): one call of
``kernels.fold.fold`` for all of them, instead of a few dozen numpy calls per
frame and model. The kernel runs the same steps in the same order as the
model's Python methods (the reference), on the arrays packed here; unpacking
puts every coefficient, covariance, counter and history back where the model
keeps it, so snapshots, reports and the reference path see one model.

Pure: no clock, no I/O.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["fold_frames", "queue_of"]


def _deque(rows, dtype=np.float64) -> tuple[np.ndarray, np.ndarray]:
    """Deques (oldest first) as a (len(rows), maxlen) array and their counts."""
    width = max(d.maxlen for d in rows)
    out = np.zeros((len(rows), width), dtype)
    n = np.zeros(len(rows), np.int64)
    for j, d in enumerate(rows):
        n[j] = len(d)
        if d:
            out[j, : len(d)] = np.fromiter(d, dtype, len(d))
    return out, n


def _back(d, row: np.ndarray, n: int, cast=float) -> None:
    d.clear()
    d.extend(row[:n].astype(cast).tolist())  # Python floats (bools): what the model's own methods append


def fold_frames(model, times: np.ndarray, z: np.ndarray, only_least: np.ndarray, kernel, models: tuple,
                least_slack: float, least_rise: float) -> None:
    """Fold frames into ``model`` (an ``OnlineCostModel``) with ``kernel`` (``kernels.fold.fold``).

    times : (F,) float64 measured seconds; z : (F, 3R + 3) float64 the frames in the model's z layout
    only_least : (F,) uint8 — frames that drew nothing (they only lower the lightest-frame bound)
    models, least_slack, least_rise : the model's ladder (simplest first) and its lightest-frame bound's constants
    """
    MODELS, LEAST_SLACK, LEAST_RISE = models, least_slack, least_rise  # noqa: N806 (the model's own names)
    r = model.algorithms
    big = 3 * r + 3
    rungs = [model.rungs[name] for name in MODELS]
    phi, scale, lower = np.zeros((3, big)), np.ones((3, big)), np.zeros((3, big))
    upper = np.full((3, big), np.inf)
    cov = np.zeros((3, big, big))
    seen = np.zeros((3, big), np.uint8)
    rs, rp = np.zeros((3, 8)), np.zeros((3, 8))
    for j, rung in enumerate(rungs):
        rls, k = rung.rls, rung.rls.k
        phi[j, :k], scale[j, :k], lower[j, :k], upper[j, :k] = rls.phi, rls.scale, rls.lower, rls.upper
        cov[j, :k, :k] = rls.P
        seen[j, :k] = rung.seen
        rs[j] = (rls._hi, rls._lo, rls.updates, rls.changes, rung._num, rung._den, rung.sides[0], rung.sides[1])
        rp[j] = (rls.forgetting, rls.huber, rls.floor, rls.reopen, rls.slack, rls.threshold, rls.clip, rls.cap)
    res, res_n = _deque([g.rls.residuals for g in rungs])
    up, up_n = _deque([g.rls._up for g in rungs])
    down, down_n = _deque([g.rls._down for g in rungs])
    err, err_n = _deque([g.errors for g in rungs])
    fill, fill_n = _deque([g.fill for g in rungs], np.uint8)
    (ratios,), ratios_n = _deque([model._ratios])
    mi = np.array([MODELS.index(model.chosen), MODELS.index(model._pending), model._count, model.frames], np.int64)
    mf = np.array([model.least, model._faces, model._verts])
    mp = np.array([model._lam, model.within, model.min_frames, model.recent, model.hold, model.tail_min_time,
                   LEAST_SLACK, LEAST_RISE])
    kernel(r, np.ascontiguousarray(times, np.float64), np.ascontiguousarray(z, np.float64),
           np.ascontiguousarray(only_least, np.uint8), phi, cov, scale, lower, upper, seen, rs, rp, res, res_n, up,
           up_n, down, down_n, err, err_n, fill, fill_n, mi, mf, ratios, ratios_n, mp,
           np.ascontiguousarray(rungs[0].alg, np.float64))
    for j, rung in enumerate(rungs):
        rls, k = rung.rls, rung.rls.k
        rls.phi, rls.scale, rls.lower, rls.upper = phi[j, :k].copy(), scale[j, :k].copy(), lower[j, :k].copy(), \
            upper[j, :k].copy()
        rls.P = cov[j, :k, :k].copy()
        rung.seen = seen[j, :k].astype(bool)
        rls._hi, rls._lo = float(rs[j, 0]), float(rs[j, 1])
        rls.updates, rls.changes = int(rs[j, 2]), int(rs[j, 3])
        rung._num, rung._den = float(rs[j, 4]), float(rs[j, 5])
        rung.sides = [int(rs[j, 6]), int(rs[j, 7])]
        _back(rls.residuals, res[j], res_n[j])
        _back(rls._up, up[j], up_n[j])
        _back(rls._down, down[j], down_n[j])
        _back(rung.errors, err[j], err_n[j])
        _back(rung.fill, fill[j], fill_n[j], bool)
        rung._full = None
    _back(model._ratios, ratios, ratios_n[0])
    model.chosen, model._pending = MODELS[mi[0]], MODELS[mi[1]]
    model._count, model.frames = int(mi[2]), int(mi[3])
    model.least, model._faces, model._verts = float(mf[0]), float(mf[1]), float(mf[2])


def queue_of(rows, width: int, most: int) -> list[tuple[float, np.ndarray, bool]]:
    """Frames not yet folded, as a snapshot holds them ([time, z row, drew nothing]); ValueError if malformed."""
    if not isinstance(rows, list) or len(rows) > most:
        raise ValueError(f"cost.queue: expected at most {most} frames")
    out = []
    for row in rows:
        try:
            t, z, empty = row
            z = np.array(z, np.float64)
        except (TypeError, ValueError):
            raise ValueError("cost.queue: a frame is [time, z, empty]") from None
        ok = isinstance(t, float) and math.isfinite(t) and t >= 1e-9 and isinstance(empty, bool)
        if not ok or z.shape != (width,) or not np.isfinite(z).all() or (z < 0).any():
            raise ValueError("cost.queue: a frame's time or terms are out of range")
        out.append((t, z, empty))
    return out
