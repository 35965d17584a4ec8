"""Where the shared real data lives (``../shared/data`` beside the project, see its README).

Looked up in order: ``$WALKSTREAM_DATA``, ``<project root>/../shared/data``,
``/work/shared/data``. Nothing from there is copied into the project.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["data_dir", "data_file"]

_ROOT = Path(__file__).resolve().parents[2]


def data_dir() -> Path:
    """The shared data directory; ``FileNotFoundError`` lists where it was looked for."""
    candidates = []
    env = os.environ.get("WALKSTREAM_DATA")
    if env:
        candidates.append(Path(env))
    candidates += [_ROOT.parent / "shared" / "data", Path("/work/shared/data")]
    for c in candidates:
        if c.is_dir():
            return c
    raise FileNotFoundError("shared data not found; looked in " + ", ".join(map(str, candidates))
                            + " (set WALKSTREAM_DATA)")


def data_file(relative: str) -> Path:
    """A file under the shared data directory, e.g. ``data_file("city/DenHaag_01.city.json")``."""
    path = data_dir() / relative
    if not path.is_file():
        raise FileNotFoundError(f"{path}: shared data file missing")
    return path
