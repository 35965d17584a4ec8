"""What the scenarios measure on a run's frames and trace: frame-time figures in a window, the
predictor's resets, level jumps, coverage of the view and the time it takes to recover.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

__all__ = ["frame_times", "window_stats", "rounded", "reset_times", "level_jumps", "coverage", "recovery_time"]


def frame_times(frames: Sequence, t0: float = -math.inf, t1: float = math.inf) -> np.ndarray:
    """Frame times (ms) of the drawn frames (a delta's selection on screen) with t in [t0, t1)."""
    return np.array([f.time * 1e3 for f in frames if t0 <= f.t < t1 and f.seq >= 0], np.float64)


def window_stats(frames: Sequence, t0: float = -math.inf, t1: float = math.inf) -> dict:
    """Frame-time figures (ms) over the drawn frames with t in [t0, t1): frames, mean, p95, max."""
    ms = frame_times(frames, t0, t1)
    if ms.size == 0:
        return {"frames": 0, "mean_ms": math.nan, "p95_ms": math.nan, "max_ms": math.nan}
    return {"frames": int(ms.size), "mean_ms": rounded(ms.mean()), "p95_ms": rounded(np.percentile(ms, 95)),
            "max_ms": rounded(ms.max())}


def rounded(x: float, nd: int = 2) -> float:
    return round(float(x), nd)


def reset_times(traces: Sequence) -> list[float]:
    """Client times at which a predicting session resets (its predictor sees a gap of over 0.5 s between camera
    samples, or a teleport): the server's own ``Predictor`` run over the traced camera, which is exactly what
    the client sent (one sample per frame). A reset delta replaces what is drawn at once, by design."""
    from server.select.predict import Predictor

    pred = Predictor()
    return [float(tr.t) for tr in traces if tr.eye is not None and pred.add(tr.t, tr.eye, tr.forward, tr.up)]


def level_jumps(traces: Sequence, *, span: np.ndarray | None = None, tau: float = 0.5, threshold: float = 0.5,
                resets: Sequence[float] = (), reset_window: float | None = None) -> dict:
    """Steps of each object's drawn continuous level between consecutive traced frames that no morph explains.

    Only objects drawn in both frames count (same key, ``drawn`` in both). A morph ramps d ≤ K − 1 levels
    within τ (``server/select/morph.py``), so over a frame interval dt it moves a level at most
    (K − 1)·dt/τ: 0.4 for K = 5 levels at 50 ms frames. A step is a jump when it exceeds both ``threshold``
    and that bound (K per key from ``span`` = K − 1 indexed by the key, a level-0 representation id; 4 if
    not given) — a pop moves a whole level in one frame. Pairs whose later frame lies within
    ``reset_window`` (default 2τ) after a reset (``reset_times``) are left out and counted apart.
    """
    window = 2 * tau if reset_window is None else reset_window
    resets = np.sort(np.asarray(resets, np.float64))
    pairs = jumps = excused = 0
    largest = 0.0
    prev = None
    for tr in traces:
        drawn = np.ones(tr.key.shape, bool) if tr.drawn is None else np.asarray(tr.drawn, bool)
        key, level = np.asarray(tr.key, np.int64)[drawn], np.asarray(tr.level, np.float64)[drawn]
        if prev is not None and key.size and prev[0].size:
            _, a, b = np.intersect1d(prev[0], key, assume_unique=True, return_indices=True)
            if a.size:
                i = int(np.searchsorted(resets, tr.t, side="right"))
                if i and tr.t - resets[i - 1] <= window:
                    excused += int(a.size)
                else:
                    step = np.abs(level[b] - prev[1][a])
                    k = np.full(b.size, 4.0) if span is None else np.asarray(span, np.float64)[key[b]]
                    bound = np.maximum(threshold, k * max(tr.t - prev[2], 0.0) / tau)
                    pairs += int(a.size)
                    jumps += int((step > bound + 1e-9).sum())
                    largest = max(largest, float(step.max()))
        prev = (key, level, float(tr.t))
    return {"pairs": pairs, "max_step": rounded(largest, 3), "jumps": jumps, "threshold": threshold,
            "resets": int(resets.size), "excused_pairs": excused}


def coverage(index, traces: Sequence, *, fov_y: float = 60.0, viewport: tuple[int, int] = (640, 360)) -> np.ndarray:
    """(k,) per traced frame, the share of the flat objects in its frustum (leaf meshes and terrain patches,
    boxes culled against the traced camera) that something drawn represents: the object itself or an
    ancestor (an HLOD proxy, a coarser terrain patch). 1.0 when nothing is in view."""
    from server.select.camera import View, cull_boxes

    flat = np.nonzero(index.flat)[0]
    lo, hi = index.object_lo[flat], index.object_hi[flat]
    parent = np.asarray(index.object_parent, np.int64)
    depth = np.asarray(index.object_depth, np.int64)
    by_depth = [np.nonzero(depth == d)[0] for d in range(1, int(depth.max(initial=0)) + 1)]
    rep_object = np.asarray(index.rep_object, np.int64)
    out = np.ones(len(traces))
    for i, tr in enumerate(traces):
        if tr.eye is None:
            out[i] = math.nan
            continue
        seen = cull_boxes(lo, hi, View.of_pose(tr.eye, tr.forward, tr.up, fov_y, viewport, index.bounds).planes())
        if not seen.any():
            continue
        covered = np.zeros(index.n_objects, bool)
        drawn = np.asarray(tr.key, np.int64)[np.asarray(tr.drawn, bool)] if tr.drawn is not None else np.asarray(tr.key)
        covered[rep_object[drawn]] = True
        for rows in by_depth:  # parents before children: a drawn proxy covers its whole subtree
            covered[rows] |= covered[parent[rows]]
        out[i] = float(covered[flat[seen]].mean())
    return out


def recovery_time(t: np.ndarray, cov: np.ndarray, after: float, baseline: float, tolerance: float = 0.05) -> float:
    """Seconds from ``after`` until coverage is back within ``tolerance`` of ``baseline`` and stays there
    (to the last frame given); 0 if it never dropped, inf if it never came back."""
    t, cov = np.asarray(t, np.float64), np.asarray(cov, np.float64)
    sel = t >= after
    t, cov = t[sel], cov[sel]
    if t.size == 0:
        return math.inf
    low = np.nonzero(cov < baseline - tolerance)[0]
    if low.size == 0:
        return 0.0
    if low[-1] == t.size - 1:
        return math.inf
    return float(t[low[-1] + 1] - after)
