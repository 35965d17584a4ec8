"""Recording a tour in the window: a key marks the current pose as a stop; the stops are written on exit.

``walkstream client --window --record-tour out.toml``: fly (or walk) to a view, press M or Space, go on.
The file holds ``stops = [...]`` in the form a kiosk tour's ``file`` reads (``client.kiosk.config.load_stops``):
TOML, or JSON when the name ends in ``.json``; each stop with the default dwell and an empty caption,
for the author to fill in.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = ["StopRecorder", "DWELL_S"]

#: The dwell a marked stop gets (s).
DWELL_S = 6.0


def _vec(v) -> list[float]:
    return [round(float(x), 4) for x in np.asarray(v, np.float64).reshape(3)]


class StopRecorder:
    """The stops marked so far, as (eye, forward, up) lists."""

    def __init__(self, dwell_s: float = DWELL_S) -> None:
        self.dwell_s = float(dwell_s)
        self.stops: list[dict] = []

    def mark(self, pose: tuple) -> None:
        """Mark ``pose`` ((eye, forward, up), (3,) each) as the next stop."""
        eye, forward, up = pose
        self.stops.append({"eye": _vec(eye), "forward": _vec(forward), "up": _vec(up), "dwell_s": self.dwell_s,
                           "caption": {}})

    def text(self, json_format: bool = False) -> str:
        """The stops as a tour file's text (TOML, or JSON)."""
        if json_format:
            return json.dumps({"stops": self.stops}, indent=2) + "\n"
        out = ["# walkstream tour stops (walkstream client --record-tour); a kiosk tour reads them with",
               "# file = \"<this file>\". Fill in the captions, e.g. caption = { en = \"...\", de = \"...\" }.", ""]
        for s in self.stops:
            out += ["[[stops]]", f"eye = {s['eye']}", f"forward = {s['forward']}", f"up = {s['up']}",
                    f"dwell_s = {s['dwell_s']}", "caption = {}", ""]
        return "\n".join(out)

    def write(self, path: str | Path) -> Path:
        """Write the stops to ``path`` (TOML, or JSON for a .json name); returns the path."""
        path = Path(path)
        path.write_text(self.text(path.suffix.lower() == ".json"), encoding="utf-8")
        return path
