"""Kiosk configs for the benchmarks: a store's own tour turned into a kiosk's stops.

The soak and the prediction benchmark run a kiosk on whatever store they are
given, so its stops come from the store: a handful of poses spread over the
scene's tour, each with a dwell and a caption in two languages, and bounds
around the scene and the tour.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = ["store_stops", "soak_config"]


def store_stops(store: Path, n: int = 4) -> tuple[str, list[dict], list[list[float]]]:
    """(scene name, ``n`` stops spread over the store's tour, bounds [[min], [max]] around scene and tour)."""
    from server.scene.store import SceneStore

    with SceneStore.open(store) as s:
        name, keys = s.index.name, [dict(k) for k in s.index.tour]
        bounds = np.asarray(s.index.bounds, np.float64)
        start = dict(s.index.start)
    if not keys:
        keys = [{**start, "t": 0.0}]
    pick = np.unique(np.linspace(0, len(keys) - 1, min(n, len(keys))).round().astype(int))
    stops = [{"eye": [float(v) for v in keys[i]["eye"]], "forward": [float(v) for v in keys[i]["forward"]],
              "up": [float(v) for v in keys[i]["up"]], "dwell_s": 4.0,
              "caption": {"en": f"Stop {j + 1} of {len(pick)}", "de": f"Halt {j + 1} von {len(pick)}"}}
             for j, i in enumerate(pick)]
    eyes = np.array([k["eye"] for k in keys], np.float64).reshape(-1, 3)
    lo, hi = np.minimum(bounds[0], eyes.min(0)), np.maximum(bounds[1], eyes.max(0))
    pad = 0.05 * (hi - lo) + 1.0
    return name, stops, [(lo - pad).tolist(), (hi + pad).tolist()]


def soak_config(store: Path, url: str, *, viewport: tuple[int, int] = (320, 180), kiosk_id: str = "soak-1",
                idle_s: float = 30.0, countdown_s: float = 20.0) -> str:
    """A kiosk config (TOML text) for ``store`` served at ``url``: its tour's stops as the attract loop."""
    name, stops, bounds = store_stops(store)
    lines = [
        "[kiosk]", f'id = "{kiosk_id}"', f"servers = [{json.dumps(url)}]", f'scene = "{name}"',
        f"viewport = [{int(viewport[0])}, {int(viewport[1])}]", "fullscreen = false", "target_ms = 50.0",
        'languages = ["en", "de"]', "heartbeat_s = 5.0", "cache_mb = 256", "",
        "[navigation]", 'mode = "walk"', "eye_height = 1.7", "max_speed = 2.0", "max_turn = 60.0",
        f"bounds = {json.dumps(bounds)}", "",
        "[idle]", f"idle_s = {float(idle_s)}", f"countdown_s = {float(countdown_s)}", "",
        "[attract]", 'playlist = ["soak"]', "",
        "[[tours]]", 'name = "soak"', 'mode = "fly"', "speed = 6.0", "turn = 45.0",
    ]
    for stop in stops:
        cap = ", ".join(f"{k} = {json.dumps(v)}" for k, v in stop["caption"].items())
        lines += ["  [[tours.stops]]", f"  eye = {json.dumps(stop['eye'])}", f"  forward = {json.dumps(stop['forward'])}",
                  f"  up = {json.dumps(stop['up'])}", f"  dwell_s = {stop['dwell_s']}", f"  caption = {{ {cap} }}"]
    return "\n".join(lines) + "\n"
