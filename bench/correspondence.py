"""Geomorph correspondences side by side: Zach's nearest-vertex rule against the stored collapse maps.

Zach (2002, 4.4) maps each vertex of level k to the nearest vertex of level
k − 1 and notes that such maps do not preserve topology, so the half-way
morphs show artefacts (5, "visual artefacts are the result"). The scene store
keeps, for every level built by edge collapses, the map those collapses define
(``server.scene.lod``, ``morph="collapse"``). This benchmark measures both on a
real scene with the real client renderer.

For each sampled level pair (k − 1, k) of one object, the object is drawn
alone, framed from a fixed oblique direction, four times: the coarse level, the
fine level, and the fine level morphed half-way (w = 0.5) with each map. A
morph that behaves like a smooth in-between should look like the cross-fade of
its end states, so each half-way image is compared with the pixel blend
0.5 · coarse + 0.5 · fine:

- ``mad``: mean absolute difference (0–255, averaged over the channels) over
  the pixels where any of the four images shows the object (the union: a
  silhouette that tears counts);
- ``artefacts``: the fraction of those pixels that differ by more than
  ``ARTEFACT_LEVEL`` (32) levels in some channel.

The reference, measured on the same pixels of the same run, is the pop a switch
without morphing shows: the difference between the coarse and fine images.

``measure`` returns the per-pair rows, a summary and readable lines;
``render_images`` is the drawing step alone (tests use it for the end states).
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Callable

import numpy as np

__all__ = [
    "ARTEFACT_LEVEL", "VIEW_DIRECTION", "View", "sample_pairs", "load_pair", "frame_box", "render_images",
    "compare", "measure",
]

#: A pixel whose channels differ by more than this (of 255) counts as an artefact pixel.
ARTEFACT_LEVEL = 32
#: Direction from the object's centre toward the eye, in (east, north, up) terms: oblique, from above.
VIEW_DIRECTION = (0.55, -0.70, 0.45)

Progress = Callable[[str, int, int], None]
View = tuple[np.ndarray, np.ndarray, np.ndarray, float, float]  # eye, forward, up, near, far


# ----------------------------------------------------------------------------- what to measure

def sample_pairs(index, pairs: int = 40, seed: int = 0) -> list[tuple[int, int]]:
    """Up to ``pairs`` level pairs (object, k) — k ≥ 1 with a stored morph map onto level k − 1 — spread over objects.

    Objects are ordered by the vertices of their finest morphing level (ties
    in a seeded random order) and picked evenly along a coordinate that is half
    their rank and half their log vertex count in that order — rank alone would
    mirror a city's many plain boxes, log size alone its few detailed buildings
    — one pair each, at a seeded random level; when ``pairs`` exceeds the
    objects, further rounds take further levels. Returns them in (object, k) order.
    """
    if pairs < 1:
        raise ValueError(f"pairs must be ≥ 1, got {pairs}")
    reps = np.nonzero(np.asarray(index.rep_morph, bool) & (np.asarray(index.rep_level) >= 1))[0]
    if reps.size == 0:
        return []
    objects = np.asarray(index.rep_object)[reps]
    order = np.argsort(objects, kind="stable")
    reps, objects = reps[order], objects[order]
    uniq, start = np.unique(objects, return_index=True)
    groups = np.split(reps, start[1:])
    rng = np.random.default_rng(seed)
    size = np.array([int(np.asarray(index.rep_vertices)[g].max()) for g in groups])
    by_size = np.lexsort((rng.random(uniq.size), size))
    remaining = [list(rng.permutation(g)) for g in groups]
    chosen: list[int] = []
    while len(chosen) < pairs:
        alive = [i for i in by_size if remaining[i]]
        if not alive:
            break
        want = min(pairs - len(chosen), len(alive))
        chosen += [int(remaining[alive[p]].pop()) for p in _spread(size[alive], want)]
    level = np.asarray(index.rep_level)
    obj = np.asarray(index.rep_object)
    return sorted((int(obj[r]), int(level[r])) for r in chosen)


def _spread(size: np.ndarray, want: int) -> list[int]:
    """``want`` distinct positions into ``size`` (ascending) spread evenly over half rank, half log size."""
    n = size.size
    if want >= n:
        return list(range(n))
    rank = np.arange(n) / max(n - 1, 1)
    log = np.log(size.astype(np.float64))
    span = log[-1] - log[0]
    u = 0.5 * rank + 0.5 * ((log - log[0]) / span if span > 0 else rank)
    free = np.ones(n, bool)
    picks = []
    for target in np.linspace(0.0, 1.0, want):
        candidates = np.nonzero(free)[0]
        p = int(candidates[np.argmin(np.abs(u[candidates] - target))])
        free[p] = False
        picks.append(p)
    return picks


def load_pair(store, obj: int, k: int):
    """(coarse, fine, collapse map) of object ``obj``'s levels k − 1 and k, decoded as the client would.

    coarse, fine : ``proto.geometry.Geometry``; collapse map : (n_fine,) int64 into the coarse vertices.
    """
    from proto.geometry import decode_geometry
    from proto.morph import decode_morph

    index = store.index
    if not 1 <= k < int(index.rep_count[obj]):
        raise ValueError(f"object {obj} has levels 0..{int(index.rep_count[obj]) - 1}; no pair ending at {k}")
    rep = int(index.rep_first[obj]) + k
    coarse, fine = (decode_geometry(b) for b in store.geometries([rep - 1, rep]))
    blob = store.morph(rep)
    if blob is None:
        raise ValueError(f"representation {rep} (object {obj}, level {k}) has no stored morph map")
    vmap = decode_morph(blob, fine.vertices, coarse.vertices).astype(np.int64)
    return coarse, fine, vmap


def frame_box(lo: np.ndarray, hi: np.ndarray, fov_y: float, aspect: float,
              up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> View:
    """A camera looking along ``-VIEW_DIRECTION`` at the box [lo, hi] with its bounding sphere filling the view."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    centre = 0.5 * (lo + hi)
    radius = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-3)
    toward_eye = np.asarray(VIEW_DIRECTION, np.float64)
    toward_eye /= np.linalg.norm(toward_eye)
    half = math.radians(fov_y) / 2
    half = min(half, math.atan(math.tan(half) * aspect))
    distance = 1.05 * radius / math.sin(half)
    eye = centre + distance * toward_eye
    return eye, -toward_eye, np.asarray(up, np.float64), max(distance - 2 * radius, 1e-3 * distance), distance + 2 * radius


def render_images(renderer, coarse, fine, maps: dict[str, np.ndarray], view: View, *, weight: float = 0.5,
                  object_id: int = 0) -> dict[str, np.ndarray]:
    """Draw one level pair alone: ``"coarse"``, ``"fine"`` and, per named map, the fine level morphed at ``weight``.

    renderer : ``client.renderer.Renderer`` (its reps 0, 1, 2, … are used and freed)
    maps     : name → (n_fine,) int map into the coarse vertices
    Returns name → (h, w, 3) uint8 image.
    """
    from client.renderer import morph_targets

    eye, forward, up, near, far = view
    renderer.upload(0, coarse, object_id=object_id)
    reps = {"coarse": 0, "fine": 1}
    renderer.upload(1, fine, object_id=object_id)
    for i, (name, vmap) in enumerate(maps.items(), start=2):
        renderer.upload(i, fine, object_id=object_id)
        renderer.set_morph_target(i, morph_targets(fine.positions, coarse.positions, vmap))
        reps[name] = i
    images = {}
    try:
        for name, rep in reps.items():
            w = None if rep < 2 else np.array([weight])
            renderer.draw(np.array([rep]), eye, forward, up, near, far, weights=w)
            images[name] = renderer.read_image()
    finally:
        for rep in reps.values():
            renderer.free(rep)
    return images


def compare(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """(mean absolute difference 0–255 over the channels, fraction of pixels > ``ARTEFACT_LEVEL`` in a channel) on ``mask``."""
    d = np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64))[mask]
    if d.size == 0:
        return 0.0, 0.0
    return float(d.mean()), float((d.max(axis=1) > ARTEFACT_LEVEL).mean())


def _object_mask(images: list[np.ndarray]) -> np.ndarray:
    from client.renderer import BACKGROUND

    sky = np.round(np.array(BACKGROUND) * 255)
    return np.logical_or.reduce([np.abs(im.astype(np.int16) - sky).max(axis=2) > 1 for im in images])


# ----------------------------------------------------------------------------- the benchmark

def measure(store_path: str | Path, pairs: int = 40, seed: int = 0, viewport: tuple[int, int] = (256, 256),
            progress: Progress | None = None) -> dict:
    """Half-way morphs with collapse maps and with nearest-vertex maps against the cross-fade of their end states.

    store_path : a scene store with morph maps (``walkstream build denhaag``)
    pairs      : level pairs to sample (``sample_pairs``); seed picks them
    viewport   : (width, height) of the offscreen image
    progress   : tick(stage, done, total), stage "pairs"
    Returns {"rows": [...], "summary": {...}, "lines": [...]} — JSON-able. Raises
    ValueError if the store has no morph maps.
    """
    from client.renderer import Renderer
    from server.scene.lod import nearest_vertex_map
    from server.scene.store import SceneStore

    tick = progress or (lambda stage, done, total: None)
    width, height = int(viewport[0]), int(viewport[1])
    t_start = time.perf_counter()
    with SceneStore.open(store_path) as store:
        index = store.index
        chosen = sample_pairs(index, pairs, seed)
        if not chosen:
            raise ValueError(f"{store_path}: no representation has a stored morph map")
        up = np.asarray(index.start.get("up", (0.0, 0.0, 1.0)), np.float64)
        names = store.object_names()
        rows: list[dict] = []
        tick("pairs", 0, len(chosen))
        with Renderer(width, height, fov_y=45.0) as renderer:
            for done, (obj, k) in enumerate(chosen, start=1):
                coarse, fine, collapse = load_pair(store, obj, k)
                nearest = nearest_vertex_map(fine.positions, coarse.positions)
                lo = np.minimum(coarse.positions.min(axis=0), fine.positions.min(axis=0))
                hi = np.maximum(coarse.positions.max(axis=0), fine.positions.max(axis=0))
                view = frame_box(lo, hi, renderer.fov_y, width / height, up)
                images = render_images(renderer, coarse, fine, {"collapse": collapse, "nearest": nearest}, view,
                                       object_id=obj)
                mask = _object_mask(list(images.values()))
                blend = 0.5 * images["coarse"].astype(np.float64) + 0.5 * images["fine"].astype(np.float64)
                pop_mad, pop_art = compare(images["coarse"], images["fine"], mask)
                col_mad, col_art = compare(images["collapse"], blend, mask)
                near_mad, near_art = compare(images["nearest"], blend, mask)
                rows.append({
                    "object": obj, "name": names[obj], "level": k,
                    "coarse_vertices": coarse.vertices, "fine_vertices": fine.vertices,
                    "coarse_faces": coarse.faces, "fine_faces": fine.faces,
                    "maps_agree": float((collapse == nearest).mean()),
                    "pixels": int(mask.sum()),
                    "pop_mad": pop_mad, "pop_artefacts": pop_art,
                    "collapse_mad": col_mad, "collapse_artefacts": col_art,
                    "nearest_mad": near_mad, "nearest_artefacts": near_art,
                })
                tick("pairs", done, len(chosen))
        scene = index.name
    summary = _summary(rows, time.perf_counter() - t_start)
    summary.update(scene=scene, store=str(store_path), seed=seed, viewport=[width, height],
                   artefact_level=ARTEFACT_LEVEL)
    return {"rows": rows, "summary": summary, "lines": _lines(summary)}


def _ratio(a: float, b: float) -> float | None:
    return float(a / b) if b > 0 else None


def _summary(rows: list[dict], seconds: float) -> dict:
    s: dict = {"pairs": len(rows), "objects": len({r["object"] for r in rows}), "seconds": round(seconds, 2)}
    for key in ("pop", "collapse", "nearest"):
        for metric in ("mad", "artefacts"):
            v = np.array([r[f"{key}_{metric}"] for r in rows], np.float64)
            s[f"{key}_{metric}_mean"] = float(v.mean())
            s[f"{key}_{metric}_median"] = float(np.median(v))
    s["maps_agree_mean"] = float(np.mean([r["maps_agree"] for r in rows]))
    differ = [r for r in rows if r["maps_agree"] < 1.0]
    s["differing_pairs"] = len(differ)
    for key in ("collapse", "nearest"):
        s[f"differing_{key}_mad_mean"] = float(np.mean([r[f"{key}_mad"] for r in differ])) if differ else None
    s["differing_ratio_nearest_collapse_mad"] = (
        _ratio(s["differing_nearest_mad_mean"], s["differing_collapse_mad_mean"]) if differ else None)
    s["pairs_maps_identical"] = int(sum(r["maps_agree"] == 1.0 for r in rows))
    s["ratio_nearest_collapse_mad"] = _ratio(s["nearest_mad_mean"], s["collapse_mad_mean"])
    s["ratio_nearest_collapse_artefacts"] = _ratio(s["nearest_artefacts_mean"], s["collapse_artefacts_mean"])
    for key in ("collapse", "nearest"):
        s[f"ratio_{key}_pop_mad"] = _ratio(s[f"{key}_mad_mean"], s["pop_mad_mean"])
    col = np.array([r["collapse_mad"] for r in rows])
    near = np.array([r["nearest_mad"] for r in rows])
    s["pairs_collapse_better"] = int((col < near).sum())
    s["pairs_nearest_better"] = int((near < col).sum())
    s["pairs_tied"] = int((near == col).sum())
    a, b = s["collapse_mad_mean"], s["nearest_mad_mean"]
    if math.isclose(a, b, rel_tol=0.01, abs_tol=1e-9):
        s["winner"], s["margin"] = "tie", 1.0
    else:
        s["winner"] = "collapse" if a < b else "nearest"
        s["margin"] = float(max(a, b) / min(a, b)) if min(a, b) > 0 else math.inf
    return s


def _fmt(x: float | None, spec: str = ".2f") -> str:
    return "n/a" if x is None else format(x, spec)


def _lines(s: dict) -> list[str]:
    lines = [
        f"morph correspondences on {s['scene']!r}: {s['pairs']} level pairs of {s['objects']} objects, "
        f"{s['viewport'][0]}×{s['viewport'][1]} px, half-way morph (w = 0.5) against the blend of its end states",
        f"{'':10s} {'mean |Δ|':>9s} {'median':>8s} {'artefact px':>12s} {'median':>8s}   (|Δ| 0–255; artefact: > {s['artefact_level']})",
    ]
    for key, label in (("pop", "pop"), ("collapse", "collapse"), ("nearest", "nearest")):
        lines.append(
            f"{label:10s} {s[f'{key}_mad_mean']:9.2f} {s[f'{key}_mad_median']:8.2f} "
            f"{100 * s[f'{key}_artefacts_mean']:11.2f}% {100 * s[f'{key}_artefacts_median']:7.2f}%"
        )
    lines.append("(pop: coarse against fine, what switching without a morph shows)")
    lines.append(
        f"nearest / collapse: {_fmt(s['ratio_nearest_collapse_mad'])}× mean |Δ|, "
        f"{_fmt(s['ratio_nearest_collapse_artefacts'])}× artefact pixels; against the pop: collapse "
        f"{_fmt(s['ratio_collapse_pop_mad'])}×, nearest {_fmt(s['ratio_nearest_pop_mad'])}×"
    )
    lines.append(
        f"per pair: collapse better {s['pairs_collapse_better']}, nearest better {s['pairs_nearest_better']}, "
        f"tied {s['pairs_tied']} (maps identical in {s['pairs_maps_identical']}; "
        f"on average {100 * s['maps_agree_mean']:.0f}% of vertices map alike)"
    )
    if s["differing_pairs"]:
        lines.append(
            f"on the {s['differing_pairs']} pairs whose maps differ: mean |Δ| collapse "
            f"{s['differing_collapse_mad_mean']:.2f}, nearest {s['differing_nearest_mad_mean']:.2f} "
            f"({_fmt(s['differing_ratio_nearest_collapse_mad'])}×)"
        )
    if s["winner"] == "tie":
        lines.append("winner: neither (mean |Δ| within 1 %)")
    else:
        lines.append(f"winner: {s['winner']} maps, {s['margin']:.2f}× lower mean |Δ| than "
                     f"{'nearest' if s['winner'] == 'collapse' else 'collapse'}")
    return lines
