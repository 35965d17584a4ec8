"""LOD chains whose coarse levels keep their shape: decimation beside the city-modelling ladder.

``lod.build_chain`` simplifies by quadric decimation only, and for closed,
box-like buildings that collapses the walls first. Here every coarser level is
chosen among candidates, each measured against the finest level
(``fidelity``: area ratio, least silhouette IoU over six directions, FLIP at the
level's switching distance):

- buildings: a decimation step of the level before, the LoD1 block model and
  the oriented box (``blocks``) — the ladder LoD2 → LoD1 → box;
- other meshes: a decimation step (borders pinned, which keeps open boundaries
  and volume), then the convex hull and the oriented box at the bottom.

A candidate counts only if it saves ``min_saving`` of the faces of the level
before and passes the ``Bounds``; among those passing the one with the best
silhouette is kept. When decimation was tried and failed but a later method
passed, the level was *regenerated*; when every candidate failed it is
*dropped* and the chain ends there. Once the chain leaves decimation it only
descends the ladder (block → box), since those proxies are made from the
finest level, not from the level before.

Morph maps come from the simplifier's collapses for decimated levels and from
the nearest rule (Zach 2002) toward a proxy, which has no collapse history.
Source-given chains (CityJSON LoDs) are measured the same way: a given level
below the bounds is replaced by the first ladder proxy that passes, or dropped.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from . import blocks
from .fidelity import Bounds, Fidelity, flip_error, reference, silhouette_iou, surface_area
from .lod import Chain, _prepare, _simplify_step, geometric_error, nearest_vertex_map

__all__ = ["ShapedChain", "shaped_chain", "shaped_source_chain", "LADDER"]

#: Methods that make a coarser level, in ladder order.
LADDER = ("decimate", "block", "box", "hull")


@dataclass
class ShapedChain:
    """A chain plus, per level, its measures (``Fidelity``) and how many levels were regenerated/dropped."""

    chain: Chain
    fidelity: list[Fidelity]
    regenerated: int = 0
    dropped: int = 0
    failed: list[str] = field(default_factory=list)


def _proxy(method: str, fine: tuple[np.ndarray, np.ndarray]):
    p, f = fine
    made = {"block": blocks.block_model, "box": blocks.oriented_box}.get(method)
    out = made(p, f) if made is not None else blocks.convex_hull(p)
    if out is None:
        return None
    try:
        return _prepare(*out)
    except ValueError:
        return None


def _measured(ref, level, error, method: str, bounds: Bounds) -> tuple[bool, Fidelity, float]:
    """Cheapest measure first: area (closed meshes), then the silhouettes, then FLIP.

    ``error`` gives the level's switching error; it is called only for a level whose area and
    silhouette pass (only those are rendered for FLIP or can be kept). Returns (passes, measures,
    raw error — NaN when not needed).
    """
    area = surface_area(level[0], level[1]) / max(ref.area, 1e-30)
    fid = Fidelity(area, float("nan"), float("nan"), method)
    if ref.closed and not min(area, 1.0 / max(area, 1e-12)) >= bounds.area:
        return False, fid, float("nan")
    fid = Fidelity(area, silhouette_iou(ref, level[0], level[1]), float("nan"), method)
    if not bounds.passes(fid, ref.closed):
        return False, fid, float("nan")
    raw, err = error()
    fid = Fidelity(area, fid.iou, flip_error(ref, level[0], level[1], err), method)
    return bounds.passes(fid, ref.closed), fid, raw


def shaped_chain(positions: np.ndarray, faces: np.ndarray, *, building: bool, bounds: Bounds = Bounds(),
                 min_saving: float = 0.4, floor_faces: int = 12, max_levels: int = 8, ratio: float = 0.5,
                 preserve_border: bool = True, samples: int = 2000) -> ShapedChain:
    """The chain of one mesh, coarsest → finest, every coarse level measured and within ``bounds``."""
    fine = _prepare(positions, faces)
    ref = reference(*fine)
    fine_first = [fine]
    kinds = ["source"]  # how each level was made
    maps: list[np.ndarray | None] = []  # maps[j]: fine_first[j] → fine_first[j + 1] (None: nearest rule)
    fids = [Fidelity(1.0, 1.0, float("nan"), "source")]
    errors = [0.0]
    ladder = ("decimate", "block", "box") if building else ("decimate", "hull", "box")
    stage = 0  # position in the ladder the next candidates start from
    cache: dict[str, tuple | None] = {}
    measured: dict[str, tuple] = {}
    regenerated = dropped = 0
    while len(fine_first) < max_levels:
        pos, fac = fine_first[-1]
        m = fac.shape[0]
        limit = int(np.floor((1.0 - min_saving) * m))
        if limit < floor_faces and stage == 0:
            break
        tried, passing = [], []
        for method in ladder[stage:]:
            if method == "decimate":
                if limit < floor_faces:
                    continue
                target = min(limit, max(floor_faces, int(round(ratio * m))))
                cp, cf, vmap = _simplify_step(pos, fac, target, preserve_border)
                if not floor_faces <= cf.shape[0] <= limit:
                    continue
                level: tuple | None = (cp, cf)
            else:
                if method not in cache:
                    cache[method] = _proxy(method, fine)
                level, vmap = cache[method], None
                if level is None or level[1].shape[0] > limit:
                    continue
            if method == "decimate" or method not in measured:
                def error(level=level):
                    raw = geometric_error(fine[0], level[0], level[1], samples)
                    return raw, max(raw, errors[-1])

                ok, fid, raw = _measured(ref, level, error, method, bounds)
                if method != "decimate":  # a proxy is the same mesh at every step: measure it once
                    measured[method] = (raw, ok, fid)
            else:
                raw, ok, fid = measured[method]
            err = max(raw, errors[-1])
            tried.append(method)
            if ok:
                passing.append((fid.iou, -level[1].shape[0], method, level, vmap, fid, err))
        if not passing:
            dropped += bool(tried)
            break
        best = max(passing, key=lambda c: (c[0], c[1]))
        _, _, method, level, vmap, fid, err = best
        if tried and tried[0] == "decimate" and method != "decimate":
            regenerated += 1
        fine_first.append(level)
        maps.append(vmap)
        kinds.append(method)
        fids.append(fid)
        errors.append(err)
        stage = ladder.index(method) + (method != "decimate")
        if stage >= len(ladder):
            break
    levels = fine_first[::-1]
    morphs: list[np.ndarray | None] = [None]
    for k in range(1, len(levels)):
        vmap = maps[len(levels) - 1 - k]
        morphs.append(vmap if vmap is not None else nearest_vertex_map(levels[k][0], levels[k - 1][0]))
    kind = "collapse" if all(v is not None for v in maps) else "nearest"
    chain = Chain(levels, morphs, errors[::-1], kind)
    return ShapedChain(chain, fids[::-1], regenerated, dropped)


def shaped_source_chain(levels: Sequence[tuple[np.ndarray, np.ndarray]], *, building: bool,
                        bounds: Bounds = Bounds(), samples: int = 2000) -> ShapedChain:
    """A source-given chain (coarsest → finest), each coarse level measured, failing ones regenerated."""
    prepared = [_prepare(p, f) for p, f in levels]
    fine = prepared[-1]
    ref = reference(*fine)
    ladder = ("block", "box") if building else ("hull", "box")
    kept = [fine]
    fids = [Fidelity(1.0, 1.0, float("nan"), "source")]
    errors = [0.0]
    regenerated = dropped = 0
    for p, f in reversed(prepared[:-1]):
        if f.shape[0] >= kept[-1][1].shape[0]:
            continue  # dominated: no fewer faces than a finer level
        candidates = [("source", (p, f))] + [(m, _proxy(m, fine)) for m in ladder]
        chosen = None
        for method, level in candidates:
            if level is None or level[1].shape[0] >= kept[-1][1].shape[0]:
                continue
            def error(level=level):
                err = max(geometric_error(fine[0], level[0], level[1], samples), errors[-1])
                return err, err

            ok, fid, err = _measured(ref, level, error, method, bounds)
            if ok:
                chosen = (level, fid, err)
                regenerated += method != "source"
                break
        if chosen is None:
            dropped += 1
            continue
        kept.append(chosen[0])
        fids.append(chosen[1])
        errors.append(chosen[2])
    out = kept[::-1]
    morphs: list[np.ndarray | None] = [None] + [nearest_vertex_map(out[k][0], out[k - 1][0])
                                                for k in range(1, len(out))]
    return ShapedChain(Chain(out, morphs, errors[::-1], "nearest"), fids[::-1], regenerated, dropped)
