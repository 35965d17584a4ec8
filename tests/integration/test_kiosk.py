"""The kiosk against the real server: its attract loop, a visitor and the idle countdown, a killed server,
and the example config in a real window on a virtual display.

The kiosk runs headless in this process (``run_kiosk`` over EGL) with its input driven from ``on_frame``
through the director — the calls the window's callbacks make — or as ``walkstream kiosk`` under Xvfb.
Its config is the example ``walkstream kiosk --example`` prints, with the server's URL, a small frame and
(``kiosk.test_mode``) short idle times.
"""

from __future__ import annotations

import json
import math
import os
import select
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from bench.demo import ServerProcess
from client.kiosk.config import DEFAULT_FONT, load_config
from client.kiosk.example import EXAMPLE
from client.kiosk.overlay import Overlay, OverlayState
from client.kiosk.run import run_kiosk

from .sky_pixels import scene_share

ROOT = Path(__file__).resolve().parents[2]
SIZE = (320, 180)
CAPTION_PX = 18


def _config_text(url: str, *, fullscreen: bool = False, idle: float = 4.0, countdown: float = 2.0) -> str:
    edits = [
        ('servers = ["ws://127.0.0.1:8765/ws"]', f'servers = ["{url}"]'),
        ("viewport = [1280, 720]", f"viewport = [{SIZE[0]}, {SIZE[1]}]"),
        ("fullscreen = true", f"fullscreen = {'true' if fullscreen else 'false'}"),
        ("caption_px = 40", f"caption_px = {CAPTION_PX}"),
        ("log_backups = 3", "log_backups = 3\ntest_mode = true"),
        ("idle_s = 90.0", f"idle_s = {idle}"),
        ("countdown_s = 20.0", f"countdown_s = {countdown}"),
        ("dwell_s = 8.0", "dwell_s = 3.0"),
        ("speed = 3.0", "speed = 8.0"),
        ("turn = 45.0", "turn = 90.0"),
    ]
    text = EXAMPLE
    for old, new in edits:
        assert old in text, old
        text = text.replace(old, new)
    return text


@pytest.fixture(scope="module")
def server(auditorium_store):
    with ServerProcess([auditorium_store]) as srv:
        yield srv


def _read(path: Path) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(path).convert("RGB"))


def _glyphs(state: OverlayState, below: int | None = None, above: int | None = None) -> np.ndarray:
    """(h, w) bool: the fully opaque white pixels (glyph cores) the overlay draws for ``state``, in rows [above,
    below) — where the frame must be exactly white if the overlay reached it."""
    ov = Overlay(*SIZE, font=DEFAULT_FONT, caption_px=CAPTION_PX)
    image, _ = ov.image(state)
    mask = (image[..., 3] == 255) & (image[..., :3] == 255).all(axis=2)
    rows = np.zeros(SIZE[1], bool)
    rows[above or 0:below if below is not None else SIZE[1]] = True
    return mask & rows[:, None]


@pytest.fixture
def doomed(auditorium_store):
    """A server of its own for the test that kills it."""
    with ServerProcess([auditorium_store]) as srv:
        yield srv


def test_a_kiosk_plays_its_loop_hands_over_to_a_visitor_comes_back_and_outlives_its_server(doomed, tmp_path):
    server = doomed
    path = tmp_path / "kiosk.toml"
    path.write_text(_config_text(server.url))
    config = load_config(path)
    script: dict = {"phase": "attract", "frames": []}
    layout = Overlay(*SIZE, font=DEFAULT_FONT, caption_px=CAPTION_PX).layout
    buttons = {b.name: (b.x + b.w / 2, b.y + b.h / 2) for b in layout.buttons()}

    def on_frame(record, director) -> None:
        t = record.t
        script["frames"].append((t, director.state, director.stop, director.caption, director.language))
        phase = script["phase"]
        if phase == "attract" and director.stop == 1 and director.caption and t > script.setdefault("at1", t) + 1.0:
            director.tap(*buttons["language"])  # a visitor: German captions, then "next stop"
            director.tap(*buttons["next"])
            script.update(phase="visitor", touched=director.machine.last_input)
        elif phase == "visitor" and director.machine.state == "attract":
            script.update(phase="back", back=t)
        elif phase == "back" and t > script["back"] + 2.0:
            server.kill()  # no goodbye, as when the machine dies
            script.update(phase="outage", killed=t)
        elif phase == "outage" and t > script["killed"] + 6.0:
            director.done = True

    result = run_kiosk(config, headless=True, duration=120.0, screenshot_every=0.5, screenshot_dir=tmp_path / "shots",
                       on_frame=on_frame)
    assert script["phase"] == "outage", f"the script stopped in {script['phase']}"
    assert result.sessions == 1 and result.close_reasons == []
    assert not result.errors, result.errors  # the server took every tour plan and heartbeat
    frames = script["frames"]
    t = np.array([f[0] for f in frames])

    # Attract: the loop moved on from the first stop to the second, each with its caption.
    before = [f for f in frames if f[0] < script["touched"]]
    assert {f[2] for f in before} >= {0, 1}
    assert {f[3] for f in before if f[3]} == {"The auditorium: 440 chairs facing the stage",
                                             "Twenty rows, each a step higher"}
    captioned = [s for s in result.shots if s.state == "attract" and s.caption and s.t > 3.0]
    assert captioned, "no screenshot of a stop with its caption"
    for shot in captioned:
        image = _read(shot.path)
        mask = _glyphs(OverlayState(caption=shot.caption, language="en"), below=layout.caption_bottom)
        assert mask.sum() > 100 and np.all(image[mask] == 255), "the caption's glyphs are not in the frame"
        assert scene_share(image) > 0.3  # and the scene is behind it

    # The visitor: German, flown to the piano with its caption; then idle → countdown → attract, on time.
    visitor = [f for f in frames if script["touched"] <= f[0] < script["back"]]
    assert ("visitor", 2, "Der Flügel", "de") in {f[1:] for f in visitor}
    states = [(when, s) for when, s in result.states if when >= script["touched"] - 0.5]  # from the first tap
    names = [s for _, s in states]
    assert names[:3] == ["visitor", "countdown", "attract"]
    touched = script["touched"]
    assert states[1][0] == pytest.approx(touched + config.idle.idle_s, abs=1e-6)
    assert states[2][0] == pytest.approx(touched + config.idle.idle_s + config.idle.countdown_s, abs=1e-6)
    assert script["back"] <= states[2][0] + 2.0  # drawn as the attract loop within 2 s
    counting = [f for f in frames if f[1] == "countdown"]
    assert counting and all(f[3] == "" for f in counting)
    after = [f for f in frames if f[0] >= script["back"]]
    assert all(f[4] == "en" for f in after)  # the default language again

    # The server killed: frames go on, every one drawn, the reconnecting mark on them.
    outage = t >= script["killed"] + 1.0
    assert outage.sum() >= 10 and {f[1] for f, o in zip(frames, outage) if o} == {"reconnecting"}
    dark = [s for s in result.shots if s.t >= script["killed"] + 1.0]
    assert len(dark) >= 5
    mark = _glyphs(OverlayState(reconnecting=True, buttons=False), below=layout.margin + CAPTION_PX)
    for shot in dark:
        image = _read(shot.path)
        assert image.max() > 0 and scene_share(image) > 0.3, f"{shot.path.name}: a blank frame during the outage"
        assert np.all(image[mark] == 255), f"{shot.path.name}: no reconnecting mark"


# --------------------------------------------------------------------------- the command, in a window


@pytest.fixture(scope="module")
def small_display(tmp_path_factory):
    """An Xvfb the size of the kiosk's frame (its full screen); yields DISPLAY once it accepts clients."""
    log = tmp_path_factory.mktemp("xvfb") / "xvfb.log"
    read, write = os.pipe()
    with open(log, "wb") as err:
        proc = subprocess.Popen([shutil.which("Xvfb") or "Xvfb", "-displayfd", str(write), "-screen", "0",
                                 f"{SIZE[0]}x{SIZE[1]}x24", "-nolisten", "tcp"],
                                pass_fds=(write,), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err)
    os.close(write)
    try:
        number, deadline = b"", time.monotonic() + 30
        while not number.endswith(b"\n"):
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
        proc.wait(timeout=10)


def test_the_example_config_runs_fullscreen_in_a_window(small_display, server, tmp_path):
    path = tmp_path / "kiosk.toml"
    path.write_text(_config_text(server.url, fullscreen=True, idle=30.0, countdown=20.0))
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "XDG_SESSION_TYPE")}
    env.update(DISPLAY=small_display, PYTHONUNBUFFERED="1")
    shots = tmp_path / "shots"
    done = subprocess.run([sys.executable, "-m", "walkstream", "kiosk", str(path), "--duration", "9",
                           "--screenshot-every", "1", "--screenshot-dir", str(shots)],
                          capture_output=True, text=True, timeout=120, env=env, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-3000:]
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    assert summary["frames"] > 20 and summary["sessions"] == 1 and summary["states"] == ["attract"]
    images = [_read(p) for p in sorted(shots.glob("kiosk-*.png"))]
    # One shot a second on the client clock's grid from the first frame to the end (a slow start shifts it).
    assert len(images) >= min(6, math.floor(9 - summary["first_frame_s"]) - 1) >= 4
    assert all(im.shape == (SIZE[1], SIZE[0], 3) for im in images)  # the whole screen
    # The window showed the hall behind the first stop's caption (the dwell: 3 s from the first frame).
    caption = _glyphs(OverlayState(caption="The auditorium: 440 chairs facing the stage"),
                      below=Overlay(*SIZE, font=DEFAULT_FONT, caption_px=CAPTION_PX).layout.caption_bottom)
    with_caption = [im for im in images if np.all(im[caption] == 255)]
    assert with_caption and max(scene_share(im) for im in with_caption) > 0.3
    assert all(scene_share(im) > 0.3 for im in images[3:])  # and the scene on every later frame


def test_the_command_line(tmp_path):
    done = subprocess.run([sys.executable, "-m", "walkstream", "kiosk", "--example"], capture_output=True,
                          text=True, timeout=60, cwd=ROOT)
    assert done.returncode == 0 and done.stdout == EXAMPLE
    bad = tmp_path / "kiosk.toml"
    bad.write_text(EXAMPLE.replace("countdown_s = 20.0", "countdown_s = 10.0"))
    done = subprocess.run([sys.executable, "-m", "walkstream", "kiosk", str(bad), "--headless"],
                          capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert done.returncode == 78  # EX_CONFIG: the systemd unit does not restart a kiosk whose config is wrong
    assert done.stderr.strip() == "error: kiosk.toml: idle.countdown_s: must be at least 20 (WCAG 2.2.1)"


# Records a tour in a real window: W moves the camera, M marks stops (through the window's key entry point,
# as glfw's callback calls it), and the stops are written when the run ends.
_RECORD = '''
import sys
import client.window as W
from client.app import run_client

url, scene, out = sys.argv[1:4]
present, frames = W.Window.present, [0]

def probe(self, renderer):
    n = frames[0]
    if n == 2:
        self.on_key("m", True); self.on_key("m", False)
        self.on_key("w", True)
    elif n == 8:
        self.on_key("w", False)
        self.on_key("space", True); self.on_key("space", False)
    present(self, renderer)
    frames[0] += 1

W.Window.present = probe
run_client(url, scene, duration=3.0, viewport=(320, 180), window=True, navigate="fly", record_tour=out)
'''


def test_a_tour_recorded_in_the_window_is_a_tour_the_kiosk_reads(small_display, server, tmp_path):
    from client.kiosk.config import load_stops

    out = tmp_path / "recorded.toml"
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "XDG_SESSION_TYPE")}
    env.update(DISPLAY=small_display)
    done = subprocess.run([sys.executable, "-c", _RECORD, server.url, "auditorium", str(out)], capture_output=True,
                          text=True, timeout=120, env=env, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-3000:]
    stops = load_stops(out)
    assert len(stops) == 2 and all(s.dwell_s == 6.0 and s.caption == {} for s in stops)
    moved = np.subtract(stops[1].eye, stops[0].eye)
    assert np.linalg.norm(moved) > 0.1 and np.dot(moved, stops[0].forward) > 0  # W flew ahead between the marks
    # The same file as a kiosk tour's ``file``.
    text = _config_text(server.url).split("  [[tours.stops]]")[0].replace('# file = "highlights.toml"',
                                                                         f'file = "{out.name}"')
    (tmp_path / "kiosk.toml").write_text(text)
    assert [s.eye for s in load_config(tmp_path / "kiosk.toml").tours[0].stops] == [s.eye for s in stops]
