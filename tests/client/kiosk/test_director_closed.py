"""Outside opening hours the kiosk's attract loop goes on, darkened and slowed; opening again restores it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from client.kiosk.config import load_config
from client.kiosk.director import Director
from client.kiosk.example import EXAMPLE
from client.kiosk.hours import CLOSED_LOOKS


class _Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def director(tmp_path: Path):
    path = tmp_path / "kiosk.toml"
    path.write_text(EXAMPLE)
    clock = _Clock()
    d = Director(load_config(path), clock=clock, size=(320, 180))
    from client.kiosk.stops import Playlist, playlist_stops

    d.playlist = Playlist(playlist_stops(d.config.playlist))  # what begin() sets up, without a session
    d._play(d.playlist.pose(0), 0.0, 0)
    d._pose = d.segment.pose_at(0.0)
    return d, clock


def test_closing_slows_the_loop_from_where_it_is_and_opening_restores_its_pace(director):
    d, clock = director
    open_length = d.segment.end - d.segment.start
    clock.t = 10.0
    d._pose = d.segment.pose_at(clock.t)
    heading = d.segment.stop_at(clock.t)[0]
    d.closed = "dim"
    seg = d.segment
    assert seg.start == 10.0 and np.allclose(seg.eye[0], d._pose[0])  # on from where the camera was
    assert seg.stops[0] == heading
    rate = CLOSED_LOOKS["dim"][1]
    assert seg.end - seg.start > 0.9 * open_length / rate  # a whole loop, slowed
    assert d.overlay_state(clock.t).dim == pytest.approx(1.0 - CLOSED_LOOKS["dim"][0])
    assert d.state == "closed"
    clock.t = 20.0
    d._pose = d.segment.pose_at(clock.t)
    d.closed = None
    assert d.segment.start == 20.0 and d.segment.end - d.segment.start < 1.1 * open_length
    assert d.overlay_state(clock.t).dim == 0.0 and d.state == "attract"
