"""The kiosk config: the example is valid, every error names its key in one line, tour files are read."""

from __future__ import annotations

import json

import numpy as np
import pytest

from client.kiosk.config import ConfigError, load_config, load_stops
from client.kiosk.example import EXAMPLE
from client.kiosk.record import StopRecorder


def _write(tmp_path, text: str, name: str = "kiosk.toml"):
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def _edit(old: str, new: str) -> str:
    assert old in EXAMPLE, old
    return EXAMPLE.replace(old, new, 1)


def test_the_example_is_valid_and_its_stops_look_somewhere(tmp_path):
    config = load_config(_write(tmp_path, EXAMPLE))
    assert config.kiosk.scene == "auditorium" and config.kiosk.languages == ["en", "de"]
    stops = config.playlist[0].stops
    assert len(stops) == 5 and all(s.caption["en"] and s.caption["de"] for s in stops)
    for s in stops:  # a look_at is turned into a unit direction towards it
        d = s.direction
        assert np.isclose(np.linalg.norm(d), 1.0)
        np.testing.assert_allclose(d, (np.subtract(s.look_at, s.eye)) / np.linalg.norm(np.subtract(s.look_at, s.eye)))
    nav = config.navigation_message()
    assert nav.mode == "walk" and nav.bounds == config.navigation.bounds


@pytest.mark.parametrize("old, new, message", [
    ("countdown_s = 20.0", "countdown_s = 5.0", "kiosk.toml: idle.countdown_s: must be at least 20 (WCAG 2.2.1)"),
    ("idle_s = 90.0", "idle_s = 10.0", "kiosk.toml: idle.idle_s: must be at least 30"),
    ('id = "lobby-1"', 'id = "lobby 1"', "kiosk.toml: kiosk.id: 'lobby 1' does not match"),
    ("cache_mb = 256", "cache_mb = 256\ncachemb = 3", "kiosk.toml: kiosk.cachemb: unknown key"),
    ('servers = ["ws://127.0.0.1:8765/ws"]', 'servers = ["ws://127.0.0.1:8765/ws", "http://x/ws"]',
     "kiosk.toml: kiosk.servers[1]: bad URL 'http://x/ws'"),
    ('playlist = ["highlights"]', 'playlist = ["highlights", "museum"]',
     "kiosk.toml: attract.playlist[1]: no tour named 'museum'"),
    ('de = "Der Flügel"', 'fr = "Le piano"', "kiosk.toml: tours[0].stops[2].caption.fr: not one of kiosk.languages"),
    ("look_at = [3.5, -13.0, 1.7]", "look_at = [3.5, -13.0]", "kiosk.toml: tours[0].stops[3].look_at: needs at least 3"),
    ("look_at = [3.5, -13.0, 1.7]", "look_at = [3.5, -8.4, 2.4]", "kiosk.toml: tours[0].stops[3]: forward is zero"),
    ("look_at = [3.5, -13.0, 1.7]", "look_at = [3.5, -13.0, 1.7]\n  forward = [0.0, 1.0, 0.0]",
     "kiosk.toml: tours[0].stops[3]: give exactly one of forward and look_at"),
    ("dwell_s = 6.0\n  caption = { en = \"The lectern\"", "dwell_s = -1.0\n  caption = { en = \"The lectern\"",
     "kiosk.toml: tours[0].stops[3].dwell_s: must be at least 0"),
    ("max_speed = 2.0", 'max_speed = "fast"', "kiosk.toml: navigation.max_speed: must be a float"),
    ("mode = \"walk\"  ", "mode = \"run\"  ", "kiosk.toml: navigation.mode: must be one of"),
    ("bounds = [[-14.5, -17.5, 0.2], [14.5, 17.5, 10.5]]", "bounds = [[1, 1, 1], [0, 2, 2]]",
     "kiosk.toml: navigation.bounds: must be []"),
    ('open = "00:00"', 'open = "25:00"', "kiosk.toml: schedule.open: '25:00' does not match"),
    ('closed = "dim"', 'closed = "off"', "kiosk.toml: schedule.closed: must be one of"),
    ('font = ""', 'font = "/nowhere/Font.ttf"', "kiosk.toml: kiosk.font: no font file at '/nowhere/Font.ttf'"),
    ("speed = 3.0", "speed = 0.0", "kiosk.toml: tours[0].speed: must be more than 0"),
    ('name = "highlights"', 'name = "highlights"\nfile = "stops.toml"',
     "kiosk.toml: tours[0]: give the stops inline"),
    ("[attract]\nplaylist = [\"highlights\"]", "", "kiosk.toml: attract: missing (required)"),
])
def test_each_error_names_its_key_in_one_line(tmp_path, old, new, message):
    with pytest.raises(ConfigError) as err:
        load_config(_write(tmp_path, _edit(old, new)))
    text = str(err.value)
    assert text.startswith(message), text
    assert "\n" not in text


def test_not_toml_and_missing_files_are_one_line(tmp_path):
    with pytest.raises(ConfigError, match=r"^kiosk.toml: not valid TOML: .*line 1"):
        load_config(_write(tmp_path, "[kiosk\n"))
    with pytest.raises(ConfigError, match=r"^gone.toml: cannot read it"):
        load_config(tmp_path / "gone.toml")


def test_test_mode_allows_short_idle_but_not_none(tmp_path):
    short = _edit("idle_s = 90.0", "idle_s = 2.0").replace("countdown_s = 20.0", "countdown_s = 1.0")
    with pytest.raises(ConfigError, match="idle.idle_s: must be at least 30"):
        load_config(_write(tmp_path, short))
    test = short.replace("log_backups = 3", "log_backups = 3\ntest_mode = true")
    config = load_config(_write(tmp_path, test))
    assert (config.idle.idle_s, config.idle.countdown_s) == (2.0, 1.0)
    with pytest.raises(ConfigError, match=r"idle.countdown_s: must be at least 0.5 \(WCAG"):
        load_config(_write(tmp_path, test.replace("countdown_s = 1.0", "countdown_s = 0.1")))


@pytest.mark.parametrize("suffix", [".toml", ".json"])
def test_a_tour_file_as_recorded_is_read_relative_to_the_config(tmp_path, suffix):
    rec = StopRecorder()
    rec.mark((np.array([1.0, 2.0, 3.0]), np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])))
    rec.mark((np.array([4.0, 5.0, 6.0]), np.array([1.0, 0.0, -0.1]), np.array([0.0, 0.0, 1.0])))
    (tmp_path / "tours").mkdir()
    rec.write(tmp_path / "tours" / f"recorded{suffix}")
    stops = load_stops(tmp_path / "tours" / f"recorded{suffix}")
    assert [s.eye for s in stops] == [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]
    assert all(s.dwell_s == 6.0 and s.caption == {} for s in stops)
    text = EXAMPLE.split("  [[tours.stops]]")[0].replace('# file = "highlights.toml"', f'file = "tours/recorded{suffix}"')
    config = load_config(_write(tmp_path, text))
    assert [s.eye for s in config.tours[0].stops] == [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]
    # An error inside the file names the config's key and the file's.
    bad = {"stops": [{"eye": [0, 0, 0], "forward": [0, 1, 0], "dwell": 3}]}
    (tmp_path / "tours" / f"recorded{suffix}").write_text(
        json.dumps(bad) if suffix == ".json" else "[[stops]]\neye = [0, 0, 0]\nforward = [0, 1, 0]\ndwell = 3\n")
    with pytest.raises(ConfigError, match=rf"^kiosk.toml: tours\[0\].file: recorded{suffix}: stops\[0\].dwell: unknown key"):
        load_config(tmp_path / "kiosk.toml")
