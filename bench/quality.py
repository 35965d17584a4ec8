"""Image quality of traced frames against full detail: FLIP, PSNR, SSIM and popping.

Every figure compares two images drawn by the same renderer (``bench.replay.Replayer``),
untimed, from the same camera: the frame a method drew (reference: the full-detail
frame). Conventions, so the report can read the numbers:

- ``flip``: mean LDR-FLIP (Andersson et al. 2020, the ``flip-evaluator`` package), 0 for
  identical images, up to 1; at the package's default 67 pixels per degree.
- ``psnr``: dB over the RGB channels (peak 255), capped at ``PSNR_CAP`` = 100 dB: identical
  images would be +∞, which JSON cannot hold and a mean cannot use.
- ``ssim``: mean SSIM over the RGB channels (scikit-image, data range 255), 1 for identical images.
- ``popping``: how much more the drawn picture changes from one frame to the next than the
  full-detail picture does over the same camera motion — the change a method's switches add.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Sequence

import numpy as np

__all__ = ["PSNR_CAP", "psnr", "ssim", "flip", "flip_map", "change", "popping", "measure", "summary",
           "false_colour_images"]

#: PSNR reported for identical images (and the most any pair reports), in dB.
PSNR_CAP = 100.0


def _pair(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape or a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"need two (h, w, 3) images of one shape, got {a.shape} and {b.shape}")
    if a.dtype != np.uint8 or b.dtype != np.uint8:
        raise ValueError(f"images must be uint8 RGB, got {a.dtype} and {b.dtype}")
    return a, b


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """Peak signal-to-noise ratio (dB) of two (h, w, 3) uint8 images; ``PSNR_CAP`` when identical."""
    a, b = _pair(a, b)
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    if mse == 0.0:
        return PSNR_CAP
    return float(min(PSNR_CAP, 10.0 * np.log10(255.0 ** 2 / mse)))


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    """Structural similarity of two (h, w, 3) uint8 images (≥ 7 × 7), averaged over the channels."""
    from skimage.metrics import structural_similarity

    a, b = _pair(a, b)
    return float(structural_similarity(a, b, channel_axis=2, data_range=255))


def flip_map(reference: np.ndarray, test: np.ndarray) -> np.ndarray:
    """(h, w) float32 LDR-FLIP error per pixel in [0, 1] of ``test`` against ``reference`` (both uint8 sRGB)."""
    import flip_evaluator

    reference, test = _pair(reference, test)
    error, _, _ = flip_evaluator.evaluate(reference.astype(np.float32) / 255.0, test.astype(np.float32) / 255.0,
                                          "LDR", applyMagma=False, computeMeanError=False)
    return np.asarray(error, np.float32).reshape(reference.shape[:2])


def flip(reference: np.ndarray, test: np.ndarray) -> float:
    """Mean LDR-FLIP of ``test`` (the drawn frame) against ``reference`` (full detail); 0 when identical."""
    return float(flip_map(reference, test).mean())


def change(a: np.ndarray, b: np.ndarray) -> float:
    """Mean absolute difference of two (h, w, 3) uint8 images, over pixels and RGB channels (0–255)."""
    a, b = _pair(a, b)
    return float(np.mean(np.abs(a.astype(np.int16) - b.astype(np.int16))))


def popping(drawn_prev: np.ndarray, drawn_now: np.ndarray, full_prev: np.ndarray, full_now: np.ndarray) -> float:
    """The excess frame-to-frame change of the drawn frames over the full-detail ones, ≥ 0 (0–255 scale).

    max(0, change(drawn_prev, drawn_now) − change(full_prev, full_now)), ``change`` being the mean
    absolute RGB difference. Camera motion changes both sequences alike; what the drawn one changes
    more is what its level (and algorithm) switches added — popping. A drawn sequence that changes
    less than full detail (a coarse, blurred scene) scores 0, not a credit.
    """
    return max(0.0, change(drawn_prev, drawn_now) - change(full_prev, full_now))


def measure(replayer, traces: Sequence, *, every: int = 10, warmup: float = 2.0,
            progress: Callable[[int, int], None] | None = None, samples: int | None = None,
            seed: int = 0) -> dict:
    """Image error and popping of every ``every``-th traced frame from ``warmup`` s on (the schema's "quality").

    ``samples`` caps the frames measured (FLIP alone takes about half a second a frame): they are then the
    frames at ``samples`` tour times spread evenly from the warm-up to the run's last frame, so runs of
    every method (whose frame rates differ) are compared at the same viewpoints — picked by frame count,
    a slow method's samples would lie further along the tour than a fast one's. ``seed`` shifts the times
    (or, without ``samples``, the stride's offset), so the same seed measures the same views.

    replayer : ``bench.replay.Replayer`` on the run's scene, viewport and fov
    traces   : the run's ``ClientRun.trace`` (one per frame, so a trace's index is its frame's)
    progress : called as progress(done, total) after each sample
    Returns {"t", "frame", "flip", "psnr", "ssim", "popping"} as plain lists. Each sample draws
    frame i as traced and at full detail (``Replayer.full`` with the frame's own algorithms), and
    for popping frame i − 1 likewise — its full-detail frame also with frame i's algorithms, so the
    reference change is camera motion alone. The first frame of a run has no predecessor: popping 0.
    """
    if every < 1:
        raise ValueError(f"every must be ≥ 1, got {every}")
    if samples is not None and samples < 1:
        raise ValueError(f"samples must be ≥ 1, got {samples}")
    eligible = [i for i, tr in enumerate(traces) if tr.t >= warmup]
    if samples is None or not eligible:
        picked = eligible[seed % every::every]
    else:
        n = min(samples, -(-len(eligible) // every))
        t = np.array([traces[i].t for i in eligible], np.float64)
        shift = (seed * 0.6180339887498949) % 1.0  # the golden ratio: seeds spread their times
        want = t[0] + (np.arange(n) + shift) * (t[-1] - t[0]) / n
        at = np.clip(np.searchsorted(t, want - 1e-9), 0, t.size - 1)
        picked = [eligible[k] for k in np.unique(at)]
    out: dict[str, list] = {k: [] for k in ("t", "frame", "flip", "psnr", "ssim", "popping")}
    for done, i in enumerate(picked, start=1):
        tr = traces[i]
        drawn = replayer.drawn(tr)
        full = replayer.full(tr.eye, tr.forward, tr.up, algorithms_from=tr)
        pop = 0.0
        if i > 0:
            prev = traces[i - 1]
            pop = popping(replayer.drawn(prev), drawn,
                          replayer.full(prev.eye, prev.forward, prev.up, algorithms_from=tr), full)
        out["t"].append(float(tr.t))
        out["frame"].append(int(i))
        out["flip"].append(flip(full, drawn))
        out["psnr"].append(psnr(full, drawn))
        out["ssim"].append(ssim(full, drawn))
        out["popping"].append(float(pop))
        if progress is not None:
            progress(done, len(picked))
    return out


def summary(quality: dict) -> dict:
    """{"flip_mean", "psnr_mean", "ssim_mean", "popping_mean"} over a ``measure`` result's samples (NaN if none)."""
    def mean(key: str) -> float:
        values = quality.get(key) or []
        return float(np.mean(values)) if len(values) else float("nan")

    return {f"{k}_mean": mean(k) for k in ("flip", "psnr", "ssim", "popping")}


def false_colour_images(replayer, traces_by_method: dict[str, Sequence], at_t: float, out_dir: str | Path,
                        label: str) -> dict[str, str]:
    """Level false-colour images at tour time ``at_t``: each method's traced frame nearest to it, and full detail.

    Saved as PNG in ``out_dir`` as ``{label}-{method}.png`` and ``{label}-full.png``; the full-detail
    frame is drawn from the camera of the frame (over all methods) nearest to ``at_t``. Methods
    without traces are left out. Returns {"full": file name, method: file name, ...} (names, not paths).
    Colours as the client's false-colour mode: level 0 blue through level 5 and finer red, morphing
    draws striped magenta; tree splats keep their colours.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    names: dict[str, str] = {}
    best = None
    for method, traces in traces_by_method.items():
        if not traces:
            continue
        times = np.array([tr.t for tr in traces], np.float64)
        tr = traces[int(np.argmin(np.abs(times - at_t)))]
        if best is None or abs(tr.t - at_t) < abs(best.t - at_t):
            best = tr
        names[method] = f"{label}-{method}.png"
        _save(replayer.drawn(tr, false_colour=True), out_dir / names[method])
    if best is not None:
        names = {"full": f"{label}-full.png", **names}
        _save(replayer.full(best.eye, best.forward, best.up, algorithms_from=best, false_colour=True),
              out_dir / names["full"])
    return names


def _save(image: np.ndarray, path: Path) -> None:
    try:
        from PIL import Image
    except ImportError:
        import matplotlib.pyplot as plt

        plt.imsave(str(path), image)
    else:
        Image.fromarray(image).save(str(path))
