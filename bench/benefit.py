"""Calibrating accuracy: which model of a level's accuracy predicts the image error the eye sees.

Objects of a scene are drawn alone, at every level, by the real renderer (``client.renderer``
through ``bench.replay.Replayer``, headless over EGL), from a spread of distances and angles;
each coarser level's image is compared with the finest level's by FLIP. The measured error of a
sample is FLIP summed over the image ÷ the pixels the object covers (in either image; FLIP spreads an
edge's error a pixel or two beyond, so it can pass 1): the error per pixel of the object, which is
what Accuracy stands for (Benefit = Size · Accuracy · …).

Each accuracy model of ``server.select.benefit`` predicts a loss 1 − Accuracy for the same
sample, from what the selection knows: the level's faces and vertices, the pixels its box covers
(``camera.screen_size``), the object's full-detail faces, and the level's stored geometric error.

- ``fs``: F&S's 1 − 0.5 / min(faces, pixels) (flat shading: Samples are polygons, m = 1);
- ``zach``: Zach's face density, max(1, S / #original) / max(1, S / #faces);
- ``sse``: screen-space error, 1 / (1 + error in pixels) (``benefit.projected_error``).

Per model: Spearman's rank correlation of loss against measured error (how well it ranks levels
and views), and the relative RMS error of a power curve a · loss^p fitted to the measured error
(how well it predicts). The default is the simplest model (``SIMPLEST_FIRST``) whose rank
correlation is within 10 % of the best.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Callable

import numpy as np

from proto.camera import NEAR, far_plane, projection_matrix, view_matrix
from server.select.benefit import projected_error, screen_error_accuracy, zach_accuracy
from server.select.camera import screen_size

__all__ = ["MODELS", "SIMPLEST_FIRST", "predicted_loss", "pick_objects", "views", "measure", "score", "choose",
           "run"]

MODELS = ("fs", "zach", "sse")
#: Fewest inputs first: the stored error and the projected size; faces, original faces and size;
#: samples, their exponent per algorithm and the pixel cap.
SIMPLEST_FIRST = ("sse", "zach", "fs")
#: Distances as multiples of the object's bounding radius, and azimuths (degrees) around it.
DISTANCES = (1.6, 3.0, 6.0, 12.0, 24.0)
AZIMUTHS = (20.0, 140.0, 260.0)
ELEVATION = 20.0


def predicted_loss(model: str, *, size, faces, original, error, extent) -> np.ndarray:
    """(s,) float64 1 − Accuracy of each sample under ``model`` (inputs (s,) arrays)."""
    size = np.asarray(size, np.float64)
    faces = np.maximum(np.asarray(faces, np.float64), 1.0)
    if model == "fs":
        return 0.5 / np.minimum(faces, np.maximum(size, 1.0))
    if model == "zach":
        return 1.0 - zach_accuracy(size, faces, np.asarray(original, np.float64))
    if model == "sse":
        return 1.0 - screen_error_accuracy(projected_error(error, size, extent))
    raise ValueError(f"unknown accuracy model {model!r}; known: {MODELS}")


def pick_objects(index, count: int, seed: int = 0) -> np.ndarray:
    """(≤ count,) object ids: flat mesh objects with at least two levels, spread over sizes (largest first half)."""
    ids = np.flatnonzero(np.asarray(index.flat) & (np.asarray(index.rep_count) >= 2))
    if ids.size <= count:
        return ids
    extent = np.linalg.norm(index.object_hi[ids] - index.object_lo[ids], axis=1)
    order = ids[np.argsort(-extent, kind="stable")]
    rng = np.random.default_rng(seed)
    half = count // 2
    rest = rng.choice(order[half:], size=count - half, replace=False)
    return np.concatenate([order[:half], np.sort(rest)])


def views(lo: np.ndarray, hi: np.ndarray, up_axis: int = 2):
    """(eye, forward, up) cameras looking at a box's centre from ``DISTANCES`` × ``AZIMUTHS`` (yields distance too)."""
    centre = (lo + hi) / 2.0
    radius = max(float(np.linalg.norm(hi - lo)) / 2.0, 1e-6)
    up = np.zeros(3)
    up[up_axis] = 1.0
    a, b = [i for i in range(3) if i != up_axis]
    el = np.radians(ELEVATION)
    for k in DISTANCES:
        for az in np.radians(AZIMUTHS):
            d = np.zeros(3)
            d[a], d[b], d[up_axis] = np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)
            eye = centre + k * radius * d
            yield k, eye, -d, up


def _trace(reps, levels, eye, forward, up):
    return SimpleNamespace(rep=np.asarray(reps, np.int64), drawn=None, weight=np.ones(len(reps)),
                           level=np.asarray(levels, np.float64), algorithm=None, vegetation=None, resolution=None,
                           eye=eye, forward=forward, up=up)


def measure(replayer, objects: np.ndarray, progress: Callable[[str, int, int], None] | None = None) -> dict:
    """Samples {object, level, distance, size, faces, original, error, extent, measured} as plain lists.

    One sample per object × view × level coarser than the finest (whose error is 0 by definition).
    """
    from bench.quality import flip_map

    ix = replayer.index
    width, height = replayer.viewport
    out: dict[str, list] = {k: [] for k in ("object", "level", "distance", "size", "faces", "original", "error",
                                            "extent", "measured")}
    total = int(objects.size) * len(DISTANCES) * len(AZIMUTHS)
    done = 0
    for obj in objects.tolist():
        first, count = int(ix.rep_first[obj]), int(ix.rep_count[obj])
        reps = np.arange(first, first + count)
        lo, hi = ix.object_lo[obj].astype(np.float64), ix.object_hi[obj].astype(np.float64)
        extent = float(np.linalg.norm(hi - lo))
        for k, eye, forward, up in views(lo, hi):
            clip = (projection_matrix(replayer.fov_y, width / height, NEAR, far_plane(eye, replayer.bounds))
                    @ view_matrix(eye, forward, up))
            size = float(screen_size(lo[None], hi[None], clip, width, height)[0])
            empty = replayer.drawn(_trace([], [], eye, forward, up))
            finest = replayer.drawn(_trace([reps[-1]], [count - 1], eye, forward, up))
            cover_f = (finest != empty).any(axis=2)
            for lvl in range(count - 1):
                img = replayer.drawn(_trace([reps[lvl]], [lvl], eye, forward, up))
                covered = int((cover_f | (img != empty).any(axis=2)).sum())
                if covered == 0:
                    continue
                err = float(flip_map(finest, img).sum()) / covered
                out["object"].append(obj)
                out["level"].append(lvl)
                out["distance"].append(float(k))
                out["size"].append(size)
                out["faces"].append(int(ix.rep_faces[reps[lvl]]))
                out["original"].append(int(ix.rep_faces[reps[-1]]))
                out["error"].append(float(ix.rep_error[reps[lvl]]))
                out["extent"].append(extent)
                out["measured"].append(err)
            done += 1
            if progress is not None:
                progress(f"benefit {ix.name}", done, total)
    return out


def _fit_error(loss: np.ndarray, measured: np.ndarray) -> float:
    """Relative RMS error (÷ mean measured) of the power curve a · loss^p least-squares fitted to the samples."""
    from scipy.optimize import curve_fit

    x = np.maximum(loss, 1e-12)
    scale = float(np.median(x))
    xs = x / scale
    mean = float(measured.mean())
    if mean <= 0:
        return float("nan")
    try:
        (a, p), _ = curve_fit(lambda v, a, p: a * v ** p, xs, measured, p0=(mean, 0.5),
                              bounds=([0.0, 0.0], [np.inf, 5.0]), maxfev=20000)
        fitted = a * xs ** p
    except (RuntimeError, ValueError):
        fitted = np.full_like(measured, mean)
    return float(np.sqrt(np.mean((fitted - measured) ** 2)) / mean)


def score(samples: dict) -> dict:
    """{model: {"spearman", "fit_error"}} over the samples (NaN where there are fewer than 3)."""
    from scipy.stats import spearmanr

    measured = np.asarray(samples["measured"], np.float64)
    arrays = {k: np.asarray(samples[k], np.float64) for k in ("size", "faces", "original", "error", "extent")}
    out = {}
    for model in MODELS:
        loss = predicted_loss(model, **arrays)
        if measured.size < 3 or np.ptp(loss) == 0 or np.ptp(measured) == 0:
            out[model] = {"spearman": float("nan"), "fit_error": float("nan")}
            continue
        rho = spearmanr(loss, measured).statistic
        out[model] = {"spearman": float(rho), "fit_error": _fit_error(loss, measured)}
    return out


def choose(scores: dict, within: float = 0.10) -> str:
    """The simplest model (``SIMPLEST_FIRST``) whose Spearman ρ is at least (1 − within) × the best ρ."""
    rho = {m: s["spearman"] for m, s in scores.items() if np.isfinite(s["spearman"])}
    if not rho:
        return SIMPLEST_FIRST[-1]
    best = max(rho.values())
    for model in SIMPLEST_FIRST:
        if model in rho and rho[model] >= (1.0 - within) * best:
            return model
    return max(rho, key=rho.get)


def run(stores: list, *, objects: int = 8, viewport=(320, 180), seed: int = 0,
        progress: Callable[[str, int, int], None] | None = None) -> dict:
    """Measure every store, score the models over all samples together and per scene; lines for the terminal."""
    from bench.replay import Replayer

    per_scene, every = {}, None
    for store in stores:
        with Replayer(store, viewport=viewport) as rp:
            picked = pick_objects(rp.index, objects, seed)
            samples = measure(rp, picked, progress)
            per_scene[str(rp.index.name)] = {"objects": int(picked.size), "samples": len(samples["measured"]),
                                             "measured_max": max(samples["measured"], default=0.0),
                                             "scores": score(samples)}
        every = samples if every is None else {k: every[k] + samples[k] for k in every}
    overall = score(every) if every is not None else {}
    default = choose(overall)
    lines = [f"Accuracy models against measured FLIP per covered pixel ({len(every['measured'])} samples, "
             f"{viewport[0]}×{viewport[1]}, levels vs the finest):",
             f"{'scene':<12} {'model':<6} {'Spearman ρ':>10} {'fit error':>10}"]
    for name, res in [*per_scene.items(), ("all", {"scores": overall})]:
        for model in MODELS:
            s = res["scores"][model]
            mark = "  ← default" if name == "all" and model == default else ""
            lines.append(f"{name:<12} {model:<6} {s['spearman']:>10.3f} {s['fit_error']:>10.3f}{mark}")
    lines.append(f"default: {default} (simplest of {', '.join(SIMPLEST_FIRST)} with ρ within 10 % of the best)")
    return {"lines": lines, "scenes": per_scene, "scores": overall, "default": default,
            "samples": len(every["measured"]), "viewport": list(viewport)}
