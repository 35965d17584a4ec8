"""bench.quality: the image metrics, popping, per-run sampling and the false-colour images."""

from __future__ import annotations

import numpy as np
import pytest

from bench import quality
from bench.replay import Replayer
from client.records import FrameTrace
from proto.tour import Tour
from server.scene.store import SceneStore

VIEW = (160, 90)


def _uniform(index, level: int, t: float, pose=None) -> FrameTrace:
    """Every flat object at ``level`` (clamped to its chain), static, from the tour's pose at t (or ``pose``)."""
    obj = np.flatnonzero(index.flat)
    first = index.rep_first[obj].astype(np.int64)
    reps = first + np.minimum(level, index.rep_count[obj] - 1)
    eye, forward, up = Tour(index.tour).pose_at(t) if pose is None else pose
    return FrameTrace(t, first, (reps - first).astype(np.float64), reps, np.ones(reps.size), eye=eye,
                      forward=forward, up=up, drawn=np.ones(reps.size, bool))


@pytest.fixture(scope="module")
def demo(demo_store):
    with SceneStore.open(demo_store) as store, Replayer(store, viewport=VIEW) as replayer:
        yield store.index, replayer


def test_metrics_of_identical_and_different_images() -> None:
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    assert quality.psnr(a, a) == quality.PSNR_CAP
    assert quality.ssim(a, a) == pytest.approx(1.0)
    assert quality.flip(a, a) == 0.0
    b = a.copy()
    b[10:30, 20:40] = 255 - b[10:30, 20:40]
    assert 0.0 < quality.psnr(a, b) < quality.PSNR_CAP and quality.ssim(a, b) < 0.99
    error = quality.flip_map(a, b)
    assert error.shape == (48, 64) and error.dtype == np.float32 and 0.0 <= error.min() <= error.max() <= 1.0
    assert error[40:].mean() < 0.1 * error[10:30, 20:40].mean()  # the error sits where the images differ
    assert quality.flip(a, b) == pytest.approx(float(error.mean()))
    with pytest.raises(ValueError):
        quality.psnr(a, b[:-1])
    with pytest.raises(ValueError):
        quality.ssim(a.astype(np.float32), b)


def test_error_falls_as_levels_rise_and_vanishes_at_full_detail(demo) -> None:
    index, replayer = demo
    t = 3.0
    pose = Tour(index.tour).pose_at(t)
    full = replayer.full(*pose)
    assert quality.flip(full, replayer.full(*pose)) == 0.0
    top = int(index.rep_count.max()) - 1
    errors = []
    for level in (0, top // 2, top):
        drawn = replayer.drawn(_uniform(index, level, t))
        errors.append((quality.flip(full, drawn), quality.psnr(full, drawn), quality.ssim(full, drawn)))
    (f0, p0, s0), (f1, p1, s1), (f2, p2, s2) = errors
    assert f0 > f1 > f2 == 0.0
    assert p0 < p1 < p2 == quality.PSNR_CAP
    assert s0 < s1 < s2 == pytest.approx(1.0)


def test_popping_is_the_change_beyond_full_detail(demo) -> None:
    index, replayer = demo
    tour = Tour(index.tour)
    top = int(index.rep_count.max()) - 1
    # The camera moves; the drawn frames are full detail: the motion alone pops nothing.
    p0, p1 = tour.pose_at(3.0), tour.pose_at(3.5)
    f0, f1 = replayer.full(*p0), replayer.full(*p1)
    assert quality.change(f0, f1) > 0.0
    d0, d1 = replayer.drawn(_uniform(index, top, 3.0, p0)), replayer.drawn(_uniform(index, top, 3.5, p1))
    assert quality.popping(d0, d1, f0, f1) == 0.0
    # Same camera, a level switch between the two frames: all of the change is popping.
    coarse, fine = replayer.drawn(_uniform(index, 0, 3.0, p0)), replayer.drawn(_uniform(index, top, 3.0, p0))
    assert quality.change(coarse, fine) > 0.0
    assert quality.popping(coarse, fine, f0, f0) == pytest.approx(quality.change(coarse, fine))
    # A coarse sequence that changes less than full detail earns no credit.
    assert quality.popping(coarse, coarse, f0, f1) == 0.0


def test_measure_samples_after_warmup_with_progress(demo) -> None:
    index, replayer = demo
    top = int(index.rep_count.max()) - 1
    times = np.arange(8) * 0.5
    pose = Tour(index.tour).pose_at(2.0)  # a still camera: every change between frames is a level switch
    traces = [_uniform(index, top if i % 2 else 0, float(t), pose) for i, t in enumerate(times)]
    ticks = []
    q = quality.measure(replayer, traces, every=2, warmup=1.0, progress=lambda d, n: ticks.append((d, n)))
    assert q["frame"] == [2, 4, 6] and q["t"] == [1.0, 2.0, 3.0]
    assert ticks == [(1, 3), (2, 3), (3, 3)]
    assert set(q) == {"t", "frame", "flip", "psnr", "ssim", "popping"}
    assert all(len(v) == 3 and all(isinstance(x, (int, float)) for x in v) for v in q.values())
    assert all(f > 0 for f in q["flip"]) and all(p > 0 for p in q["popping"])  # coarse after fine: a pop
    moving = [_uniform(index, top, float(t)) for t in times[:4]]
    fine = quality.measure(replayer, moving, every=1, warmup=0.0)  # all at full detail, the camera moving
    assert fine["flip"] == [0.0] * 4 and fine["popping"] == [0.0] * 4 and fine["psnr"] == [quality.PSNR_CAP] * 4
    s = quality.summary(q)
    assert set(s) == {"flip_mean", "psnr_mean", "ssim_mean", "popping_mean"}
    assert s["flip_mean"] == pytest.approx(np.mean(q["flip"]))
    assert np.isnan(quality.summary({"flip": [], "psnr": [], "ssim": [], "popping": []})["flip_mean"])
    with pytest.raises(ValueError):
        quality.measure(replayer, traces, every=0)


def test_capped_samples_are_taken_at_the_same_tour_times_whatever_the_frame_rate(demo) -> None:
    """Two runs of one tour, one at 20 fps and one at 50: with ``samples`` they are measured at the same views
    (within a frame), so their image errors compare the methods and not where along the tour each was."""
    index, replayer = demo
    slow = [_uniform(index, 0, float(t)) for t in np.arange(0.0, 10.0, 0.05)]
    fast = [_uniform(index, 0, float(t)) for t in np.arange(0.0, 10.0, 0.02)]
    a = quality.measure(replayer, slow, every=1, warmup=2.0, samples=4)
    b = quality.measure(replayer, fast, every=1, warmup=2.0, samples=4)
    assert len(a["t"]) == len(b["t"]) == 4 and a["t"][0] == pytest.approx(2.0)
    assert np.allclose(a["t"], b["t"], atol=0.05)
    assert a["t"][-1] > 7.0  # spread over the whole run, not its first frames
    c = quality.measure(replayer, slow, every=1, warmup=2.0, samples=4, seed=1)  # another seed: other views
    assert not np.allclose(a["t"], c["t"], atol=0.05)


def test_false_colour_images_at_a_viewpoint(demo, tmp_path) -> None:
    from PIL import Image

    index, replayer = demo
    top = int(index.rep_count.max()) - 1
    runs = {
        "coarse": [_uniform(index, 0, t) for t in (1.0, 2.0, 3.0)],
        "fine": [_uniform(index, top, t) for t in (1.1, 2.1, 3.1)],
        "empty": [],
    }
    names = quality.false_colour_images(replayer, runs, 2.05, tmp_path / "images", "A")
    assert names == {"full": "A-full.png", "coarse": "A-coarse.png", "fine": "A-fine.png"}
    images = {k: np.asarray(Image.open(tmp_path / "images" / v).convert("RGB")) for k, v in names.items()}
    assert all(im.shape == (VIEW[1], VIEW[0], 3) for im in images.values())
    np.testing.assert_array_equal(images["fine"], replayer.drawn(runs["fine"][1], false_colour=True))
    assert not np.array_equal(images["fine"], replayer.drawn(runs["fine"][1]))  # level colours, not tints
    assert not np.array_equal(images["coarse"], images["fine"])
