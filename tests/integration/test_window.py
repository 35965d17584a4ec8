"""The window: the real client in a real glfw window on a virtual X display (Xvfb), against a real server.

Each client runs in its own process (glfw initialises once per process, and a
display is per process too); Xvfb is started once for the module and tells us
its display number through ``-displayfd`` when it is ready to accept clients.
"""

from __future__ import annotations

import ctypes.util
import json
import os
import select
import shutil
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from bench.demo import ServerProcess
from client.renderer import BACKGROUND
from server.scene.store import SceneStore

XVFB = shutil.which("Xvfb")
ROOT = Path(__file__).resolve().parents[2]


# --------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def display(tmp_path_factory):
    """A fresh Xvfb; yields its DISPLAY (":N") once it accepts clients, terminates it afterwards."""
    log = tmp_path_factory.mktemp("xvfb") / "xvfb.log"
    read, write = os.pipe()
    with open(log, "wb") as err:
        proc = subprocess.Popen([XVFB, "-displayfd", str(write), "-screen", "0", "1280x800x24", "-nolisten", "tcp"],
                                pass_fds=(write,), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err)
    os.close(write)
    try:
        number = b""
        deadline = time.monotonic() + 30
        while not number.endswith(b"\n"):  # Xvfb writes the number when it is ready, then a newline
            ready, _, _ = select.select([read], [], [], max(0.0, deadline - time.monotonic()))
            chunk = os.read(read, 64) if ready else b""
            if not chunk:
                proc.kill()
                pytest.fail(f"Xvfb did not report a display: {log.read_text(errors='replace')[-2000:]}")
            number += chunk
    finally:
        os.close(read)
    try:
        yield f":{int(number)}"
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _env(display: str | None) -> dict[str, str]:
    """This process's environment with only ``display`` to draw on (no Wayland, so glfw takes X11)."""
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "XDG_SESSION_TYPE")}
    if display is not None:
        env["DISPLAY"] = display
    env["PYTHONUNBUFFERED"] = "1"
    return env


@pytest.fixture(scope="module")
def server(auditorium_store, denhaag_store):
    with ServerProcess([auditorium_store, denhaag_store]) as srv:
        yield srv


@pytest.fixture(scope="module")
def scenes(auditorium_store, denhaag_store) -> dict[str, str]:
    """Scene names as served, by fixture."""
    names = {}
    for key, path in (("auditorium", auditorium_store), ("denhaag", denhaag_store)):
        with SceneStore.open(path) as s:
            names[key] = s.index.name
    return names


def _read_png(path: Path) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(path).convert("RGB"))


def _assert_drawn(image: np.ndarray) -> None:
    """Not the empty sky: ≥ 5 % of the pixels differ from the background and there are several colours."""
    sky = np.round(np.asarray(BACKGROUND) * 255)
    drawn = (np.abs(image.astype(np.int16) - sky).max(axis=2) > 3).mean()
    colours = len(np.unique(image.reshape(-1, 3), axis=0))
    assert drawn >= 0.05, f"only {drawn:.1%} of the pixels differ from the background"
    assert colours >= 8, f"only {colours} distinct colours"


# --------------------------------------------------------------------------- the CLI in a window


@pytest.mark.parametrize("which, navigate, extra", [
    ("auditorium", "tour", []),
    ("denhaag", "walk", ["--false-colour"]),
])
def test_window_client_draws_the_scene(display, server, scenes, tmp_path, which, navigate, extra):
    shot = tmp_path / f"{which}.png"
    # Applying a large delta holds the loop for a while on a loaded machine, so frames after the warm-up
    # (the summary's "frames") may be few: the run is longer than the warm-up by more than such a hold, and
    # what is asserted is that frames were drawn at all ("drawn").
    done = subprocess.run(
        [sys.executable, "-m", "walkstream", "client", server.url, "--scene", scenes[which], "--window",
         "--navigate", navigate, "--duration", "5", "--width", "320", "--height", "180", "--screenshot", str(shot),
         *extra],
        capture_output=True, text=True, timeout=60, env=_env(display), cwd=ROOT,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    assert summary["deltas"] >= 1 and summary["errors"] == 0 and summary["drawn"] > 0
    assert summary["triangles_mean"] > 0
    image = _read_png(shot)
    assert image.shape == (180, 320, 3)
    _assert_drawn(image)


def test_window_needs_a_display(monkeypatch):
    done = subprocess.run(
        [sys.executable, "-m", "walkstream", "client", "ws://127.0.0.1:9/ws", "--window", "--duration", "1"],
        capture_output=True, text=True, timeout=60, env=_env(None), cwd=ROOT,
    )
    assert done.returncode == 2
    assert "xvfb-run" in done.stderr and "DISPLAY" in done.stderr and "Traceback" not in done.stderr
    done = subprocess.run([sys.executable, "-m", "walkstream", "client", "--navigate", "fly"],
                          capture_output=True, text=True, timeout=60, env=_env(None), cwd=ROOT)
    assert done.returncode != 0 and "--window" in done.stderr

    from client.window import Window, WindowError

    for name in ("DISPLAY", "WAYLAND_DISPLAY", "XDG_SESSION_TYPE"):
        monkeypatch.delenv(name, raising=False)
    with pytest.raises(WindowError, match="xvfb-run"):
        Window(64, 64)


# --------------------------------------------------------------------------- what the window shows, and input

# Runs the real client in a window, with ``Window.present`` wrapped to check, every frame, that the
# window's back buffer holds exactly the renderer's image, to log the navigator's pose, and to feed
# input through the window's glfw-independent entry points (on_key, on_drag) at fixed frames.
_PROBE = textwrap.dedent('''
    import json, sys
    from pathlib import Path
    import numpy as np
    from PIL import Image
    import client.window as W
    from client.app import run_client

    url, scene, mode, out = sys.argv[1:5]
    out = Path(out)
    PRESS, RELEASE, DRAG, FALSE, SHOT = 2, 8, 9, 10, 11
    key = {"walk": "w", "fly": "e"}[mode]
    log = {"frames": 0, "mismatched": 0, "t": [], "eye": [], "forward": [], "up": [], "mode": []}
    present = W.Window.present

    def probe(self, renderer):
        n = log["frames"]
        self.blit(renderer)
        screen, image = self.read_screen(), renderer.read_image()
        log["mismatched"] += int(not np.array_equal(screen, image))
        nav = self.controller
        eye, forward, up = nav.pose
        log["t"].append(nav.t); log["eye"].append(eye.tolist()); log["forward"].append(forward.tolist())
        log["up"].append(up.tolist()); log["mode"].append(nav.mode)
        if n == PRESS:
            self.on_key(key, True)
        elif n == RELEASE:
            self.on_key(key, False)
        elif n == DRAG:
            self.on_drag(100, 0)  # 15 degrees to the right at 0.15 degrees a pixel
        elif n == FALSE:
            before = bool(getattr(renderer, "false_colour", False))
            self.on_key("f", True); self.on_key("f", False)
            log["false_colour"] = [before, bool(getattr(renderer, "false_colour", False))]
            self.on_key("f", True)  # and back
        elif n == SHOT:
            self.screenshot_dir = out
            self.on_key("p", True); self.on_key("p", False)
        present(self, renderer)
        if n == SHOT:
            shot = np.asarray(Image.open(self.screenshots[-1]).convert("RGB"))
            log["shot_matches"] = bool(np.array_equal(shot, image))
            log["shot"] = str(self.screenshots[-1])
        log["frames"] += 1

    W.Window.present = probe
    run = run_client(url, scene, duration=4.0, viewport=(320, 180), window=True, navigate=mode,
                     screenshot=out / "last.png")
    log.update(deltas=run.deltas_received, errors=[e.message for e in run.errors], press=PRESS, release=RELEASE,
               drag=DRAG)
    print(json.dumps(log))
''')


def _probe(display: str, url: str, scene: str, mode: str, out: Path) -> dict:
    done = subprocess.run([sys.executable, "-c", _PROBE, url, scene, mode, str(out)], capture_output=True,
                          text=True, timeout=60, env=_env(display), cwd=ROOT)
    assert done.returncode == 0, done.stderr[-3000:]
    log = json.loads(done.stdout.strip().splitlines()[-1])
    assert log["frames"] > 16, f"only {log['frames']} frames in 4 s"
    assert log["errors"] == [] and log["deltas"] >= 1
    return log


@pytest.mark.parametrize("mode", ["walk", "fly"])
def test_window_shows_the_frame_and_input_moves_the_camera(display, server, scenes, tmp_path, mode):
    log = _probe(display, server.url, scenes["auditorium"], mode, tmp_path)
    # Every frame the window's default framebuffer received exactly the renderer's image ...
    assert log["mismatched"] == 0
    # ... including what the last frame showed, which is a drawn auditorium.
    _assert_drawn(_read_png(tmp_path / "last.png"))
    # P wrote the window's content, F toggled false colour.
    assert log["shot_matches"] and Path(log["shot"]).parent == tmp_path
    assert log["false_colour"] == [False, True]
    t, eye, forward, up = (np.array(log[k], dtype=float) for k in ("t", "eye", "forward", "up"))
    p, r, d = log["press"], log["release"], log["drag"]
    # Before any input the camera holds the welcome's start pose.
    np.testing.assert_allclose(eye[:p + 1], np.repeat(eye[:1], p + 1, axis=0))
    assert set(log["mode"]) == {mode}
    moved = eye[r] - eye[p]
    if mode == "walk":  # W: level, along the start heading, at the walking speed (2 m/s)
        heading = forward[p] * [1, 1, 0] / np.linalg.norm(forward[p][:2])
        np.testing.assert_allclose(moved, 2.0 * (t[r] - t[p]) * heading, atol=1e-9)
        assert moved[2] == 0 and np.all(eye[:, 2] == eye[0, 2])
    else:  # E: up along the camera's up at the flying speed (8 m/s)
        np.testing.assert_allclose(moved, 8.0 * (t[r] - t[p]) * up[p], atol=1e-9)
    np.testing.assert_allclose(eye[r:], np.repeat(eye[r:r + 1], len(eye) - r, axis=0))  # released: stops
    # The drag turned the camera 15° to the right (walking: about the world's up), no faster than 90°/s.
    f0, f1 = forward[d], forward[-1]
    if mode == "walk":
        f0, f1 = f0 * [1, 1, 0], f1 * [1, 1, 0]
    turned = np.degrees(np.arctan2(np.linalg.norm(np.cross(f0, f1)), np.dot(f0, f1)))
    assert turned == pytest.approx(15.0, abs=1e-6)
    assert np.dot(f1, np.cross(f0, up[d])) > 0  # to the right
    steps = np.degrees(np.arctan2(np.linalg.norm(np.cross(forward[:-1], forward[1:]), axis=1),
                                  np.sum(forward[:-1] * forward[1:], axis=1)))
    assert np.all(steps <= 90.0 * np.diff(t) + 1e-6)


# --------------------------------------------------------------------------- real X input through glfw

_XTEST = ctypes.util.find_library("Xtst")

# Real key and pointer events, sent through the X server's XTEST extension, reach the controller
# through glfw's callbacks: W, a left-button drag, Tab, F, P and Escape.
_X_INPUT = textwrap.dedent('''
    import ctypes, json, sys
    from pathlib import Path
    import glfw
    import numpy as np
    from PIL import Image
    from client.navigation import Navigator
    from client.renderer import Renderer
    from client.window import Window
    from proto.geometry import Geometry

    out = Path(sys.argv[1])
    x11, xt = ctypes.CDLL("libX11.so.6"), ctypes.CDLL(sys.argv[2])
    x11.XOpenDisplay.restype, x11.XOpenDisplay.argtypes = ctypes.c_void_p, [ctypes.c_char_p]
    x11.XStringToKeysym.restype, x11.XStringToKeysym.argtypes = ctypes.c_ulong, [ctypes.c_char_p]
    x11.XKeysymToKeycode.restype, x11.XKeysymToKeycode.argtypes = ctypes.c_ubyte, [ctypes.c_void_p, ctypes.c_ulong]
    x11.XSync.argtypes = [ctypes.c_void_p, ctypes.c_int]
    xt.XTestFakeKeyEvent.argtypes = [ctypes.c_void_p, ctypes.c_uint, ctypes.c_int, ctypes.c_ulong]
    xt.XTestFakeMotionEvent.argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_ulong]
    xt.XTestFakeButtonEvent.argtypes = [ctypes.c_void_p, ctypes.c_uint, ctypes.c_int, ctypes.c_ulong]
    dpy = x11.XOpenDisplay(None)

    def key(name, down):
        xt.XTestFakeKeyEvent(dpy, x11.XKeysymToKeycode(dpy, x11.XStringToKeysym(name.encode())), int(down), 0)
        x11.XSync(dpy, 0)

    def until(window, done):
        for _ in range(100):  # events come asynchronously: wait for them (at most 10 s)
            if done():
                return True
            glfw.wait_events_timeout(0.1)
        return done()

    nav = Navigator(((0.0, 0.0, 1.7), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)), mode="fly")
    log = {}
    with Window(320, 180, controller=nav, screenshot_dir=out) as window:
        renderer = Renderer(320, 180, ctx=window.ctx)
        tri = Geometry(np.array([[-1, -1, -5], [1, -1, -5], [0, 1, -5]], np.float32), np.array([[0, 1, 2]], np.uint32))
        renderer.upload(0, tri, object_id=7)
        renderer.draw(np.array([0]), np.zeros(3), np.array([0.0, 0.0, -1.0]), np.array([0.0, 1.0, 0.0]), 0.1, 10.0)
        window.present(renderer)
        x, y = glfw.get_window_pos(window._handle)
        xt.XTestFakeMotionEvent(dpy, -1, x + 160, y + 90, 0)  # no window manager: focus follows the pointer
        x11.XSync(dpy, 0)
        key("w", True)
        log["w_held"] = until(window, lambda: "w" in nav.controller.held)
        key("w", False)
        log["w_released"] = until(window, lambda: "w" not in nav.controller.held)
        xt.XTestFakeButtonEvent(dpy, 1, 1, 0)
        xt.XTestFakeMotionEvent(dpy, -1, x + 260, y + 90, 0)
        xt.XTestFakeButtonEvent(dpy, 1, 0, 0)
        x11.XSync(dpy, 0)
        log["dragged"] = until(window, lambda: nav.controller._look.any())
        log["pending_turn"] = nav.controller._look.tolist()
        key("Tab", True); key("Tab", False)
        until(window, lambda: nav.mode == "walk")
        log["mode"] = nav.mode
        key("f", True); key("f", False)
        until(window, lambda: bool(getattr(renderer, "false_colour", False)))
        log["false_colour"] = bool(getattr(renderer, "false_colour", False))
        key("p", True); key("p", False)
        until(window, lambda: window._want_shot)
        window.present(renderer)
        log["shots"] = [str(p) for p in window.screenshots]
        shot = np.asarray(Image.open(window.screenshots[0]).convert("RGB")) if window.screenshots else None
        log["shot_matches"] = shot is not None and bool(np.array_equal(shot, renderer.read_image()))
        key("Escape", True); key("Escape", False)
        log["closed"] = until(window, lambda: window.should_close)
        renderer.release()
    print(json.dumps(log))
''')


def test_real_x_events_reach_the_controller(display, tmp_path):
    done = subprocess.run([sys.executable, "-c", _X_INPUT, str(tmp_path), _XTEST], capture_output=True, text=True,
                          timeout=60, env=_env(display), cwd=ROOT)
    assert done.returncode == 0, done.stderr[-3000:]
    log = json.loads(done.stdout.strip().splitlines()[-1])
    assert log["w_held"] and log["w_released"]
    assert log["dragged"] and log["pending_turn"] == [15.0, 0.0]  # 100 px right at 0.15°/px
    assert log["mode"] == "walk"
    assert log["false_colour"] is True
    assert len(log["shots"]) == 1 and log["shot_matches"]
    assert log["closed"]
