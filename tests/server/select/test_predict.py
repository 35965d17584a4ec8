"""Linear path prediction and the conservative camera (Zach 2002, 3.3 and 4.3)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from server.select.camera import View, cull_boxes, frustum_planes
from server.select.predict import MotionLimits, Pose, Predictor, conservative_camera

RATE = 20.0
UP = np.array([0.0, 0.0, 1.0])
X = np.array([1.0, 0.0, 0.0])


def straight(t, v=(5.0, 1.0, 0.0), start=(0.0, 0.0, 2.0)):
    """(n, 3) eyes of a straight walk at constant velocity."""
    return np.asarray(start) + np.asarray(t)[:, None] * np.asarray(v)


def feed(p: Predictor, t, eyes, forwards=None, ups=None) -> list[bool]:
    n = len(t)
    forwards = np.tile(X, (n, 1)) if forwards is None else forwards
    ups = np.tile(UP, (n, 1)) if ups is None else ups
    return [p.add(float(ti), e, f, u) for ti, e, f, u in zip(t, eyes, forwards, ups)]


def angle_deg(a, b) -> float:
    return math.degrees(math.acos(float(np.clip(np.dot(a, b), -1.0, 1.0))))


def times(seconds: float, t0: float = 0.0) -> np.ndarray:
    return t0 + np.arange(int(round(seconds * RATE))) / RATE


# ----------------------------------------------------------------------------- prediction


def test_straight_line_is_predicted_exactly():
    t = times(2.0)
    p = Predictor()
    feed(p, t, straight(t))
    for h in (0.0, 0.5, 1.5, 3.0):
        q = p.pose(t[-1] + h)
        np.testing.assert_allclose(q.eye, straight(np.array([t[-1] + h]))[0], atol=1e-9)
        np.testing.assert_allclose(q.forward, X, atol=1e-12)
        np.testing.assert_allclose(q.up, UP, atol=1e-12)
    assert p.theta == pytest.approx(math.hypot(5.0, 1.0))
    assert p.latest == t[-1] and p.resets == 0


def test_linear_direction_change_is_followed():
    """forward and up extrapolate as vectors, then are normalised and up made orthogonal."""
    t = times(2.0)
    w = math.radians(20.0)
    f = np.stack([np.cos(w * t), np.sin(w * t), np.zeros_like(t)], axis=1)
    p = Predictor()
    feed(p, t, straight(t), f)
    q = p.pose(t[-1] + 1.0)
    assert abs(np.linalg.norm(q.forward) - 1) < 1e-12 and abs(np.linalg.norm(q.up) - 1) < 1e-12
    assert abs(np.dot(q.forward, q.up)) < 1e-12
    assert angle_deg(q.forward, X) > angle_deg(f[-1], X)  # it keeps turning


def test_constant_turn_error_grows_with_horizon():
    t = times(3.0)
    w = math.radians(30.0)
    f = np.stack([np.cos(w * t), np.sin(w * t), np.zeros_like(t)], axis=1)
    p = Predictor()
    feed(p, t, straight(t), f)
    errors = []
    for h in (0.25, 0.5, 1.0, 1.5, 2.0):
        a = w * (t[-1] + h)
        errors.append(angle_deg(p.pose(t[-1] + h).forward, [math.cos(a), math.sin(a), 0.0]))
    assert errors[0] < 1.0 and errors[2] < 5.0  # close for a short horizon
    assert all(b > a for a, b in zip(errors, errors[1:]))
    assert errors[-1] < math.degrees(w * 2.0)  # and better than holding the direction
    assert math.degrees(p.omega) == pytest.approx(30.0, rel=0.05)


def test_jitter_is_not_amplified():
    sigma = 0.05
    t = times(3.0)
    errs = []
    for seed in range(20):
        rng = np.random.default_rng(seed)
        p = Predictor()
        feed(p, t, straight(t) + rng.normal(0.0, sigma, (len(t), 3)))
        errs.append([np.linalg.norm(p.pose(t[-1] + h).eye - straight(np.array([t[-1] + h]))[0]) for h in (0.0, 0.5, 1.5)])
    mean = np.mean(errs, axis=0)
    noise = sigma * math.sqrt(3)  # the expected size of one sample's error
    assert mean[0] < noise and mean[1] < 1.5 * noise and mean[2] < 3 * noise
    # a line through the last two samples would be off by ~ noise·√2 / dt · h = 30 noise at 1.5 s


def test_jittered_directions_stay_unit_and_orthogonal():
    rng = np.random.default_rng(1)
    t = times(2.0)
    f = np.tile(X, (len(t), 1)) + rng.normal(0, 0.02, (len(t), 3))
    u = np.tile(UP, (len(t), 1)) + rng.normal(0, 0.02, (len(t), 3))
    p = Predictor()
    feed(p, t, straight(t), f, u)
    q = p.pose(t[-1] + 1.5)
    assert abs(np.linalg.norm(q.forward) - 1) < 1e-12 and abs(np.dot(q.forward, q.up)) < 1e-12
    assert angle_deg(q.forward, X) < 3.0


@pytest.mark.parametrize("k", [-20, -10, -5])
def test_single_outlier_is_ignored(k):
    t = times(3.0)
    eyes = straight(t)
    eyes[k] += [0.0, 3.0, 0.0]  # 3 m off: 60 m/s, no teleport
    p = Predictor()
    feed(p, t, eyes)
    truth = straight(np.array([t[-1] + 1.5]))[0]
    assert np.linalg.norm(p.pose(t[-1] + 1.5).eye - truth) < 0.01
    assert p.resets == 0


def test_outlier_view_direction_is_ignored():
    t = times(3.0)
    f = np.tile(X, (len(t), 1))
    f[-8] = [math.cos(0.5), math.sin(0.5), 0.0]  # 29° off for one sample
    p = Predictor()
    feed(p, t, straight(t), f)
    assert angle_deg(p.pose(t[-1] + 1.5).forward, X) < 0.1


def _stream(seed: int, n: int = 40):
    rng = np.random.default_rng(seed)
    t = times(n / RATE, t0=10.0)
    w = math.radians(25.0)
    f = np.stack([np.cos(w * t), np.sin(w * t), 0.1 * np.ones_like(t)], axis=1)
    return t, straight(t) + rng.normal(0, 0.02, (len(t), 3)), f


def _final(order, t, eyes, f) -> Predictor:
    p = Predictor()
    for i in order:
        p.add(float(t[i]), eyes[i], f[i], UP)
    return p


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 1000), delays=st.lists(st.floats(0.0, 3.0), min_size=40, max_size=40),
       dups=st.lists(st.integers(0, 39), max_size=10))
def test_duplicated_and_reordered_samples_predict_as_the_ordered_stream(seed, delays, dups):
    t, eyes, f = _stream(seed)
    clean = _final(range(len(t)), t, eyes, f)
    # each sample arrives up to 3 sample steps late; some arrive twice (the copy a little later)
    arrival = [(i + d, i) for i, d in enumerate(delays)] + [(i + 1.5, i) for i in dups]
    arrival.append((len(t) + 10.0, len(t) - 1))  # the newest once more, last
    messy = _final([i for _, i in sorted(arrival)], t, eyes, f)
    assert messy.resets == 0 and messy.latest == clean.latest
    for h in (0.0, 0.75, 1.5):
        a, b = clean.pose(t[-1] + h), messy.pose(t[-1] + h)
        np.testing.assert_allclose(b.eye, a.eye, atol=1e-9)
        np.testing.assert_allclose(b.forward, a.forward, atol=1e-9)
        np.testing.assert_allclose(b.up, a.up, atol=1e-9)


def test_duplicate_time_keeps_the_last_received():
    p = Predictor(MotionLimits(speed=50.0))  # no clamp: the first samples have not shown θ yet
    p.add(0.0, [0, 0, 0], X, UP)
    p.add(0.05, [1, 0, 0], X, UP)
    p.add(0.05, [0.25, 0, 0], X, UP)
    np.testing.assert_allclose(p.pose(0.1).eye, [0.5, 0, 0], atol=1e-9)


def test_samples_older_than_the_window_are_ignored():
    t = times(2.0)
    p = Predictor(window=1.0)
    feed(p, t, straight(t))
    before = p.pose(t[-1] + 1.0).eye
    assert p.add(t[-1] - 1.5, [100.0, 100.0, 100.0], X, UP) is False
    np.testing.assert_allclose(p.pose(t[-1] + 1.0).eye, before, atol=1e-12)


def test_gap_resets_velocity():
    t = times(1.0)
    p = Predictor(gap=0.5)
    feed(p, t, straight(t))
    t_after = t[-1] + 0.8
    e_after = straight(np.array([t_after]))[0]
    assert p.add(t_after, e_after, X, UP) is True
    assert p.resets == 1
    # one sample after the gap: the newest pose is held
    np.testing.assert_allclose(p.pose(t_after + 1.0).eye, e_after, atol=1e-12)
    # a late sample from before the gap is stale
    assert p.add(t[-1], straight(t[-1:])[0], X, UP) is False
    np.testing.assert_allclose(p.pose(t_after + 1.0).eye, e_after, atol=1e-12)
    # two samples again: moving again
    p.add(t_after + 0.05, e_after + [0.25, 0.05, 0], X, UP)
    np.testing.assert_allclose(p.pose(t_after + 0.15).eye, e_after + [0.75, 0.15, 0], atol=1e-9)


@pytest.mark.parametrize("jump, turn", [(np.array([500.0, 0.0, 0.0]), False), (np.zeros(3), True)])
def test_teleport_resets(jump, turn):
    t = times(1.0)
    p = Predictor()
    resets = feed(p, t, straight(t))
    assert not any(resets)
    t_new = t[-1] + 0.05
    e_new = straight(t[-1:])[0] + jump
    f_new = np.array([-1.0, 0.0, 0.0]) if turn else X
    assert p.add(t_new, e_new, f_new, UP) is True
    assert p.resets == 1 and p.latest == t_new
    q = p.pose(t_new + 1.0)
    np.testing.assert_allclose(q.eye, e_new, atol=1e-12)
    np.testing.assert_allclose(q.forward, f_new, atol=1e-12)
    # the next samples build a new line from the new place only
    p.add(t_new + 0.05, e_new + [0, 0.25, 0], f_new, UP)
    np.testing.assert_allclose(p.pose(t_new + 0.1).eye, e_new + [0, 0.5, 0], atol=1e-9)


def test_a_fast_but_possible_turn_is_no_teleport():
    p = Predictor()
    for i, a in enumerate(np.radians([0.0, 20.0, 40.0, 60.0, 80.0])):
        assert p.add(i * 0.05, [0, 0, 0], [math.cos(a), math.sin(a), 0.0], UP) is False
    assert p.resets == 0


def test_teleport_with_a_speed_limit():
    p = Predictor(MotionLimits(speed=2.0))
    p.add(0.0, [0, 0, 0], X, UP)
    assert p.add(0.5, [7.9, 0, 0], X, UP) is False  # under 3·2·0.5 + 5 = 8 m
    assert p.add(1.0, [16.0, 0, 0], X, UP) is True


def test_stop_converges():
    t_move = times(2.0)
    p = Predictor(window=1.0)
    feed(p, t_move, straight(t_move))
    stop = straight(t_move[-1:])[0]
    t_stop = t_move[-1] + np.arange(1, int(1.0 * RATE) + 2) / RATE  # a little over one window
    feed(p, t_stop, np.tile(stop, (len(t_stop), 1)))
    for h in (0.0, 1.5, 5.0):
        assert np.linalg.norm(p.pose(t_stop[-1] + h).eye - stop) < 1e-3


def test_speed_clamped_to_limits():
    t = times(2.0)
    w = math.radians(90.0)
    f = np.stack([np.cos(w * t), np.sin(w * t), np.zeros_like(t)], axis=1)
    p = Predictor(MotionLimits(speed=2.0, turn=math.radians(30.0)))
    feed(p, t, straight(t, v=(10.0, 0.0, 0.0)), f)
    assert p.theta == 2.0 and p.omega == pytest.approx(math.radians(30.0))
    now, later = p.pose(t[-1]), p.pose(t[-1] + 1.0)
    assert np.linalg.norm(later.eye - now.eye) == pytest.approx(2.0, rel=1e-9)
    assert angle_deg(later.forward, now.forward) <= 30.0 + 1e-9


def test_observed_maxima_and_floors():
    p = Predictor(min_speed=1.0, min_turn_deg=10.0)
    assert p.theta == 1.0 and p.omega == pytest.approx(math.radians(10.0))
    t = times(2.0)
    feed(p, t, straight(t, v=(0.2, 0.0, 0.0)))
    assert p.theta == 1.0  # a slow walk stays at the floor
    t = times(2.0, t0=2.0)
    feed(p, t, straight(t, v=(4.0, 0.0, 0.0), start=(0.4 - 8.0, 0.0, 2.0)))
    assert p.theta == pytest.approx(4.0, rel=1e-6)
    assert p.omega == pytest.approx(math.radians(10.0))  # never turned


def test_samples_at_interval_midpoints():
    t = times(1.0)
    p = Predictor()
    feed(p, t, straight(t))
    got = p.samples(2.0, 3.5, k=3)
    assert [s for s, _ in got] == pytest.approx([2.25, 2.75, 3.25])
    for s, q in got:
        np.testing.assert_allclose(q.eye, straight(np.array([s]))[0], atol=1e-9)


def test_bad_input():
    p = Predictor()
    with pytest.raises(ValueError):
        p.pose(0.0)
    with pytest.raises(ValueError):
        p.add(float("nan"), [0, 0, 0], X, UP)
    with pytest.raises(ValueError):
        p.add(0.0, [0, float("inf"), 0], X, UP)
    with pytest.raises(ValueError):
        p.add(0.0, [0, 0, 0], [0, 0, 0], UP)
    with pytest.raises(ValueError):
        p.add(0.0, [0, 0], X, UP)
    with pytest.raises(ValueError):
        Predictor(window=0.0)
    with pytest.raises(ValueError):
        MotionLimits(speed=-1.0)
    assert p.latest is None
    p.add(0.0, [0, 0, 0], X, X)  # an up along forward gets some perpendicular
    q = p.pose(1.0)
    assert abs(np.dot(q.forward, q.up)) < 1e-12 and abs(np.linalg.norm(q.up) - 1) < 1e-12


# ----------------------------------------------------------------------------- conservative camera

POSE = Pose(eye=np.array([1.0, 2.0, 3.0]), forward=np.array([0.0, 1.0, 0.0]), up=UP)


@pytest.mark.parametrize("stages", [3, 2])
def test_conservative_camera_formula(stages):
    tau, theta, omega, fov = 0.5, 4.0, math.radians(10.0), 60.0
    pose, fov2 = conservative_camera(POSE, fov, 1.0, tau, theta, omega, stages=stages)
    assert fov2 == pytest.approx(fov + math.degrees(2 * stages * tau * omega))
    back = stages * tau * theta / math.sin(math.radians(fov) / 2 + stages * tau * omega)
    np.testing.assert_allclose(pose.eye, POSE.eye - back * POSE.forward)
    np.testing.assert_allclose(pose.forward, POSE.forward)
    np.testing.assert_allclose(pose.up, POSE.up)


def test_conservative_camera_still_user_is_the_camera():
    pose, fov = conservative_camera(POSE, 60.0, 1.5, 0.5, 0.0, 0.0)
    assert fov == pytest.approx(60.0)
    np.testing.assert_allclose(pose.eye, POSE.eye)


def test_conservative_camera_wide_viewport():
    tau, omega, fov, aspect = 0.5, math.radians(10.0), 60.0, 16 / 9
    a = 3 * tau * omega
    _, fov2 = conservative_camera(POSE, fov, aspect, tau, 1.0, omega)
    half_x = math.atan(aspect * math.tan(math.radians(fov) / 2))
    # both angles widen by 3τω: vertically at least, horizontally at the same aspect
    assert math.radians(fov2) / 2 >= math.radians(fov) / 2 + a - 1e-12
    assert math.atan(aspect * math.tan(math.radians(fov2) / 2)) >= half_x + a - 1e-12


def test_conservative_camera_cap():
    pose, fov = conservative_camera(POSE, 90.0, 1.0, 0.5, 2.0, math.radians(120.0))
    assert fov == pytest.approx(170.0)
    back = 3 * 0.5 * 2.0 / math.sin(math.radians(85.0))
    np.testing.assert_allclose(pose.eye, POSE.eye - back * POSE.forward)
    _, fov = conservative_camera(POSE, 90.0, 1.0, 0.5, 2.0, math.radians(120.0), max_fov_deg=120.0)
    assert fov == pytest.approx(120.0)


def test_conservative_camera_bad_input():
    with pytest.raises(ValueError):
        conservative_camera(POSE, 0.0, 1.0, 0.5, 1.0, 1.0)
    with pytest.raises(ValueError):
        conservative_camera(POSE, 60.0, 1.0, 0.5, -1.0, 1.0)


BOUNDS = np.array([[-2000.0, -2000.0, -2000.0], [2000.0, 2000.0, 2000.0]])
VIEWPORT = {1.0: (400, 400), 16 / 9: (640, 360), 0.6: (300, 500)}


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    x, y, z = axis / np.linalg.norm(axis)
    k = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def _points_in_view(eye, forward, up, fov_y, aspect, rng, n=400) -> np.ndarray:
    """(n, 3) world points inside a camera's pyramid at depths 1..300 m, the corners over-represented."""
    f = forward / np.linalg.norm(forward)
    s = np.cross(f, up)
    s /= np.linalg.norm(s)
    u = np.cross(s, f)
    ty = math.tan(math.radians(fov_y) / 2)
    tx = aspect * ty
    ndc = rng.uniform(-1, 1, (n, 2))
    ndc[: n // 2] = np.sign(ndc[: n // 2]) * 0.999  # corners: the hardest points
    depth = rng.uniform(1.0, 300.0, n)
    return eye + depth[:, None] * (f + ndc[:, :1] * tx * s + ndc[:, 1:] * ty * u)


def _inside(points: np.ndarray, pose: Pose, fov_y: float, aspect: float) -> np.ndarray:
    view = View.of_pose(pose.eye, pose.forward, pose.up, fov_y, VIEWPORT[aspect], BOUNDS)
    return cull_boxes(points, points, frustum_planes(view.matrix()))


def _frame(rng):
    f = rng.normal(size=3)
    f /= np.linalg.norm(f)
    up = UP - np.dot(UP, f) * f
    if np.linalg.norm(up) < 0.1:
        up = np.array([1.0, 0.0, 0.0]) - f[0] * f
    up /= np.linalg.norm(up)
    return f, up


@pytest.mark.parametrize("aspect", [1.0, 16 / 9, 0.6])
def test_conservative_frustum_holds_yawed_and_pitched_cameras(aspect):
    """Zach's camera: every camera moved up to 3τθ and turned (yaw or pitch) up to 3τω sees only points in it."""
    rng = np.random.default_rng(7)
    for _ in range(40):
        fov, tau = rng.uniform(30, 75), 0.5
        theta, omega = rng.uniform(0.5, 10.0), math.radians(rng.uniform(2.0, 20.0))
        f, up = _frame(rng)
        pose = Pose(eye=rng.uniform(-50, 50, 3), forward=f, up=up)
        cons, fov2 = conservative_camera(pose, fov, aspect, tau, theta, omega)
        right = np.cross(f, up)
        for _ in range(10):
            axis = up if rng.random() < 0.5 else right
            rot = _rotation(axis, rng.uniform(-1, 1) * 3 * tau * omega)
            d = rng.normal(size=3)
            eye = pose.eye + d / np.linalg.norm(d) * rng.uniform(0, 1) * 3 * tau * theta
            pts = _points_in_view(eye, rot @ f, rot @ up, fov, aspect, rng)
            assert _inside(pts, cons, fov2, aspect).all()


@pytest.mark.parametrize("aspect", [1.0, 16 / 9, 0.6])
def test_strict_conservative_frustum_holds_any_turn(aspect):
    """strict=True: turns about any axis (roll and corner-wise turns too) stay inside."""
    rng = np.random.default_rng(11)
    for _ in range(40):
        fov, tau = rng.uniform(30, 75), 0.5
        theta, omega = rng.uniform(0.5, 10.0), math.radians(rng.uniform(2.0, 20.0))
        f, up = _frame(rng)
        pose = Pose(eye=rng.uniform(-50, 50, 3), forward=f, up=up)
        cons, fov2 = conservative_camera(pose, fov, aspect, tau, theta, omega, strict=True)
        loose, fov_loose = conservative_camera(pose, fov, aspect, tau, theta, omega)
        assert fov2 >= fov_loose - 1e-9
        for _ in range(10):
            rot = _rotation(rng.normal(size=3), rng.uniform(-1, 1) * 3 * tau * omega)
            d = rng.normal(size=3)
            eye = pose.eye + d / np.linalg.norm(d) * rng.uniform(0, 1) * 3 * tau * theta
            pts = _points_in_view(eye, rot @ f, rot @ up, fov, aspect, rng)
            assert _inside(pts, cons, fov2, aspect).all()


def test_paper_widening_can_miss_a_corner_turn():
    """Why ``strict`` exists: a turn that moves a corner straight out leaves the paper's pyramid."""
    fov, aspect, tau, omega = 60.0, 16 / 9, 0.5, math.radians(20.0)
    pose = Pose(eye=np.zeros(3), forward=np.array([0.0, 1.0, 0.0]), up=UP)
    cons, fov2 = conservative_camera(pose, fov, aspect, tau, 0.0, omega)
    ty = math.tan(math.radians(fov) / 2)
    corner = np.array([aspect * ty, 1.0, ty])  # right, forward, up
    top = np.array([0.0, -ty, 1.0])  # the top side plane's outward normal
    far = _rotation(np.cross(corner, top), 3 * tau * omega) @ corner * 1000.0  # the corner turned straight out
    assert not _inside(far[None], cons, fov2, aspect)[0]
    strict, fov3 = conservative_camera(pose, fov, aspect, tau, 0.0, omega, strict=True)
    assert _inside(far[None], strict, fov3, aspect)[0]


def test_jittered_still_camera_does_not_drift():
    """Rates no larger than the noise explains are shrunk away, so a still camera is predicted still."""
    sigma = 0.05
    errs, turns = [], []
    for seed in range(20):
        rng = np.random.default_rng(seed)
        t = times(3.0)
        still = np.tile([3.0, 4.0, 2.0], (len(t), 1))
        f = np.tile(X, (len(t), 1)) + rng.normal(0, 0.01, (len(t), 3))
        p = Predictor()
        feed(p, t, still + rng.normal(0.0, sigma, still.shape), f)
        q = p.pose(t[-1] + 2.0)
        errs.append(np.linalg.norm(q.eye - still[0]))
        turns.append(angle_deg(q.forward, X))
    assert np.mean(errs) < 1.5 * sigma * math.sqrt(3)
    assert np.mean(turns) < 1.0


def test_a_fast_tour_is_not_a_string_of_teleports() -> None:
    """St. Helens' flyover moves at about 1.2 km/s: with the tour's own speed it predicts, without it every sample resets."""
    from server.select.predict import tour_speed

    keys = [{"t": i * 0.05, "eye": [i * 60.0, 0.0, 1000.0], "forward": [1.0, 0.0, 0.0], "up": [0.0, 0.0, 1.0]}
            for i in range(60)]
    assert tour_speed(keys) == pytest.approx(1200.0)
    assert tour_speed(keys[:1]) == 0.0 and tour_speed([]) == 0.0

    def resets(teleport: float) -> int:
        p = Predictor(MotionLimits(), teleport_speed=teleport)
        for k in keys:
            p.add(k["t"], k["eye"], k["forward"], k["up"])
        return p.resets

    assert resets(200.0) >= len(keys) - 2
    assert resets(max(200.0, 3.0 * tour_speed(keys))) <= 1


_VEC = st.lists(st.floats(-1e4, 1e4, allow_nan=False, width=64), min_size=3, max_size=3)


@given(_VEC, _VEC, _VEC)
@example([0.0, 0.0, 0.0], [1.2303856820395125e-05, 0.00390625, 453.0], [0.0, 0.00390625, 451.0])  # up ≈ forward
@settings(max_examples=300, deadline=None)
def test_a_sample_is_the_pose_with_unit_forward_and_an_orthogonal_unit_up(eye, forward, up):
    """The scalar sample agrees with the vector formulas it restates: unit forward, Gram-Schmidt up."""
    from server.select.predict import _orthogonal_up, _sample, _unit

    f, n = _unit(np.array(forward))
    if n <= 1e-9:
        with pytest.raises(ValueError, match="forward"):
            _sample(eye, forward, up)
        return
    u = np.array(up)
    # Up nearly along forward leaves a small remainder of a difference of nearly equal numbers: the two
    # formulas' rounding then differs by about eps × |up| ÷ |remainder|, and near the degenerate threshold
    # they may even take different branches.
    rest = float(np.linalg.norm(u - np.dot(u, f) * f))
    slack = 1e-12 * max(float(np.linalg.norm(u)), 1.0)
    assume(abs(rest - 1e-9) > slack)
    x = _sample(eye, forward, up)
    want = np.concatenate([eye, f, _orthogonal_up(f, u)])
    np.testing.assert_allclose(x[:6], want[:6], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(x[6:], want[6:], rtol=1e-9, atol=1e-9 + (slack / rest if rest > 1e-9 else 0.0))
    assert abs(np.linalg.norm(x[3:6]) - 1) < 1e-12 and abs(np.linalg.norm(x[6:]) - 1) < 1e-9
    assert abs(np.dot(x[3:6], x[6:])) < 1e-9 + slack / max(rest, 1e-9)


@pytest.mark.parametrize("eye, forward, up, message", [
    ([1, 2], [0, 0, 1], [0, 1, 0], "eye must be 3 numbers"),
    ([0, 0, float("nan")], [1, 0, 0], [0, 1, 0], "eye must be finite"),
    ([0, 0, 0], [1, 0, float("inf")], [0, 1, 0], "forward must be finite"),
    ([0, 0, 0], [1, 0, 0], [0, 1], "up must be 3 numbers"),
    ([0, 0, 0], [0, 0, 0], [0, 1, 0], "forward must not be zero"),
])
def test_a_bad_sample_names_the_vector_that_is_wrong(eye, forward, up, message):
    from server.select.predict import _sample

    with pytest.raises(ValueError, match=message):
        _sample(eye, forward, up)
