"""Why a governed run's mean and std over the bound frames are what they are, from its own frames.

The frame governor steers each frame's predicted time to its aim, ``bound ÷ (the line's quantile of measured ÷
predicted) ÷ (1 + slack)`` × target (``client.governor``): the aim comes down as far as the frames scatter about
their predictions, and from the top of its band so the band's frames hold the line too. So on a bound frame

    measured ÷ target ≈ aim × (predicted ÷ aimed) × (measured ÷ predicted),

except where everything the ladder offered was drawn under the aim (the governor had nothing finer to add).
``explain`` measures each factor over the frames where full detail exceeds the target, and the std those
frames would have with the aim held still, and without the frames that had nothing finer: a check that misses
then says which part it misses by. The machine's own share is the scatter of identical work (consecutive
frames drawing the same triangles), which no method can take out.

Pure numpy over a run's ``frames`` as ``results.json`` records them.
"""

from __future__ import annotations

import numpy as np

from bench.machine import frame_noise
from client.governor import NEAR

__all__ = ["explain", "mean_words", "std_words"]


def _array(frames: dict, name: str, n: int) -> np.ndarray | None:
    v = frames.get(name)
    if v is None or len(v) != n:
        return None
    return np.asarray(v, np.float64)


def explain(frames: dict, bound: np.ndarray, target_ms: float, warmup: float = 0.0) -> dict | None:
    """The governed run's factors over its ``bound`` (n,) frames, in shares of the target and in ms.

    Returns None where the run carries no governor figures (an older results.json, or no governor), else
    {frames, mean, aim, aim_p10, aim_p90, landing (predicted ÷ aimed on the frames the aim bound),
    measured_vs_predicted (their mean ratio on the bound frames), ratio_p99 (of measured ÷ predicted over every
    frame predicted at ``NEAR`` × target or more after the warm-up: what the aim is steered by), free (share of
    bound frames with nothing finer to add) and free_mean, std_ms, std_steady_ms (with each frame's aim moved to
    the run's mean aim), std_held_ms (that, without the free frames), miss_ms (std of measured − predicted on the
    bound frames), machine_ms (the per-frame scatter of identical work at the bound frames' mean)}; with free frames
    also free_draws / held_draws (median objects drawn on the free frames and on the others) and free_bytes_s /
    held_bytes_s (median bytes received in the second before them).
    """
    t = _array(frames, "t", len(frames.get("time_ms") or []))
    ms = _array(frames, "time_ms", len(frames.get("t") or []))
    if t is None or ms is None:
        return None
    n = t.size
    aim, pred = _array(frames, "governor_aim", n), _array(frames, "governor_predicted_ms", n)
    held, tri = _array(frames, "governor_bound", n), _array(frames, "triangles", n)
    bound = np.asarray(bound, bool)
    if aim is None or pred is None or held is None or bound.shape != (n,):
        return None
    b = bound & (aim > 0)
    if not b.any():
        return None
    target = float(target_ms)
    held = held > 0
    bh = b & held
    free = b & ~held
    aim_ms = aim * target
    mean_aim = float(aim[b].mean())
    steady = ms - aim_ms + mean_aim * target
    after = t >= warmup
    scored = after & (pred >= NEAR * target) & (ms > 0)
    ratio = np.where(pred > 0, ms / np.where(pred > 0, pred, 1.0), np.nan)
    predicted = b & (pred > 0)
    out = {
        "frames": int(b.sum()),
        "mean": float(ms[b].mean() / target),
        "aim": mean_aim,
        "aim_p10": float(np.percentile(aim[b], 10)),
        "aim_p90": float(np.percentile(aim[b], 90)),
        "landing": float(np.mean(pred[bh] / aim_ms[bh])) if bh.any() else None,
        "measured_vs_predicted": float(np.mean(ratio[predicted])) if predicted.any() else None,
        "ratio_p99": float(np.percentile(ratio[scored], 99)) if scored.sum() >= 10 else None,
        "free": float(free.sum() / b.sum()),
        "free_mean": float(ms[free].mean() / target) if free.any() else None,
        "std_ms": float(ms[b].std()),
        "std_steady_ms": float(steady[b].std()),
        "std_held_ms": float(steady[bh].std()) if bh.any() else None,
        "miss_ms": float((ms - pred)[predicted].std()) if predicted.any() else None,
        "machine_ms": None,
    }
    draws, got = _array(frames, "reps", n), _array(frames, "bytes", n)
    if free.any() and bh.any() and draws is not None and got is not None:
        # What set the free frames apart: fewer objects drawn, while more bytes came in (the second before each).
        run = np.concatenate([[0.0], np.cumsum(got)])
        second = run[1:] - run[np.searchsorted(t, t - 1.0)]
        out["free_draws"], out["held_draws"] = float(np.median(draws[free])), float(np.median(draws[bh]))
        out["free_bytes_s"], out["held_bytes_s"] = float(np.median(second[free])), float(np.median(second[bh]))
    if tri is not None:
        noise = frame_noise(t, ms / 1e3, tri, warmup, least=target / 2e3)
        if noise["pairs"] >= 10:
            out["machine_ms"] = float(noise["frame_sd"] * ms[b].mean())
    return out


def mean_words(why: dict, bound_line: float) -> str:
    """The mean check's reason, in a clause: the aim and what set it, and the frames with nothing finer."""
    words = (f"the governor aimed these frames at {why['aim']:.3f} × target on average ({why['aim_p10']:.2f}–"
             f"{why['aim_p90']:.2f}, p10–p90)")
    if why.get("ratio_p99"):
        words += (f": {bound_line:g} ÷ the p99 of its measured ÷ predicted frames ({why['ratio_p99']:.3f}), from "
                  f"the top of its band")
    if why.get("landing") and why.get("measured_vs_predicted"):
        words += (f"; frames were predicted at {why['landing']:.3f} × the aim and measured at "
                  f"{why['measured_vs_predicted']:.3f} × their prediction")
    if why["free"] > 0 and why.get("free_mean") is not None:
        words += (f"; in {100 * why['free']:.0f} % of them everything offered fitted under the aim "
                  f"({why['free_mean']:.3f} × target)")
        if why.get("free_draws") is not None:
            words += (f", drawing {why['free_draws']:.0f} objects against {why['held_draws']:.0f} while "
                      f"{why['free_bytes_s'] / 1e3:.0f} kB/s came in against {why['held_bytes_s'] / 1e3:.0f}")
    return words


def std_words(why: dict) -> str:
    """The std check's reason, in a clause: the std without the aim's movement, without the frames with nothing
    finer, the prediction's miss and the machine's own scatter."""
    words = (f"with the aim held at its mean the std is {why['std_steady_ms']:.2f} ms"
             + (f", and {why['std_held_ms']:.2f} ms over the frames the aim bound" if why.get("std_held_ms")
                else ""))
    if why.get("miss_ms") is not None:
        words += f"; measured − predicted scatters by {why['miss_ms']:.2f} ms"
    if why.get("machine_ms") is not None:
        words += f", identical work by {why['machine_ms']:.2f} ms a frame"
    return words
