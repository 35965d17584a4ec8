"""LOD chains whose coarse levels keep their shape: decimation beside the city-modelling ladder.

``lod.build_chain`` simplifies by quadric decimation only, and for closed,
box-like buildings that collapses the walls first. Here every coarser level is
chosen among candidates, each measured against the finest level
(``fidelity``: area ratio, least silhouette IoU over six directions, FLIP at the
level's switching distance):

- buildings: a decimation step of the level before, the finest level with its
  small shells pruned (facade and roof detail: LoD2 → LoD2.0), the LoD1 block
  model and the oriented box (``blocks``) — the ladder LoD2 → LoD1 → box;
- other meshes: a decimation step (borders pinned, which keeps open boundaries
  and volume), pruning, then the convex hull and the oriented box at the bottom.

A candidate counts only if it saves ``min_saving`` of the faces of the level
before and passes the ``Bounds``; among those passing the one with the best
silhouette is kept (among those within ``IOU_TIE`` of it, the one with the
fewest faces). Pruning takes the weakest reach (``PRUNE_REACH``) whose
result fits the faces. When decimation was tried and failed but a later method
passed, the level was *regenerated*; when every candidate failed it is
*dropped* and the chain ends there. Once the chain leaves decimation it only
descends the ladder (stronger pruning → block → box), since those proxies are
made from the finest level, not from the level before.

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
from .fidelity import Bounds, Fidelity, area_ratio, flip_error, reference, silhouette_iou
from .lod import Chain, _prepare, _simplify_step, clean_mesh, geometric_error, nearest_vertex_map

__all__ = ["ShapedChain", "shaped_chain", "shaped_source_chain", "LADDER"]

#: Methods that make a coarser level, in ladder order.
LADDER = ("decimate", "prune", "block", "box", "hull")

#: Silhouette IoUs within this of the best are as good (a pixel of edge on a 64-pixel mask moves
#: an object's IoU by a few hundredths): among them the candidate with the fewest faces is kept.
IOU_TIE = 0.02

#: How far (share of the diagonal) a shell may stand out of a bigger one and still be pruned,
#: weakest first: each coarser level prunes no less than the one before.
PRUNE_REACH = (1 / 64, 1 / 32, 1 / 16, 1 / 8)


@dataclass
class ShapedChain:
    """A chain plus, per level, its measures (``Fidelity``) and how many levels were regenerated/dropped."""

    chain: Chain
    fidelity: list[Fidelity]
    regenerated: int = 0
    dropped: int = 0
    failed: list[str] = field(default_factory=list)
    box: tuple | None = None  # the oriented box made from the finest level, when the ladder made one


def _proxy(method: str, fine: tuple[np.ndarray, np.ndarray], reach: float = 0.0, shells=None,
           roof: float | None = None):
    """A ladder proxy made from the finest level, cleaned (``_prepare`` orders it once it is kept)."""
    p, f = fine
    if method == "prune":
        out = None if shells is None else blocks.pruned(p, f, reach, shells)
    elif method == "hull":
        out = blocks.convex_hull(p)
    else:
        out = {"block": blocks.block_model, "box": blocks.oriented_box}[method](p, f, roof)
    if out is None:
        return None
    out = clean_mesh(*out)
    return out if out[1].shape[0] else None


def _shape(ref, level, method: str, bounds: Bounds) -> tuple[bool, Fidelity]:
    """The cheap measures, cheapest first: area (closed meshes), then the silhouettes."""
    area = area_ratio(ref, level[0], level[1])
    fid = Fidelity(area, float("nan"), float("nan"), method)
    if ref.closed and not min(area, 1.0 / max(area, 1e-12)) >= bounds.area:
        return False, fid
    fid = Fidelity(area, silhouette_iou(ref, level[0], level[1]), float("nan"), method)
    return bounds.passes(fid, ref.closed), fid


def _measured(ref, level, error, method: str, bounds: Bounds) -> tuple[bool, Fidelity, float]:
    """Area, silhouettes, then FLIP at the switching error ``error()`` gives — called only for a
    level whose area and silhouette pass. Returns (passes, measures, error — NaN when not needed)."""
    ok, fid = _shape(ref, level, method, bounds)
    if not ok:
        return False, fid, float("nan")
    err = error()
    fid = Fidelity(fid.area_ratio, fid.iou, flip_error(ref, level[0], level[1], err), method)
    return bounds.passes(fid, ref.closed), fid, err


def shaped_chain(positions: np.ndarray, faces: np.ndarray, *, building: bool, bounds: Bounds = Bounds(),
                 min_saving: float = 0.4, floor_faces: int = 12, max_levels: int = 8, ratio: float = 0.5,
                 preserve_border: bool = True, samples: int = 2000) -> ShapedChain:
    """The chain of one mesh, coarsest → finest, every coarse level measured and within ``bounds``.

    Each step measures every candidate's area and silhouettes, then renders FLIP (and samples the
    geometric error it needs) only for those that pass them, best silhouette first, until one passes.
    """
    fine = _prepare(positions, faces)
    ref = reference(*fine)
    diag = float(np.linalg.norm(ref.hi - ref.lo))
    fine_first = [fine]
    maps: list[np.ndarray | None] = []  # maps[j]: fine_first[j] → fine_first[j + 1] (None: nearest rule)
    fids = [Fidelity(1.0, 1.0, float("nan"), "source")]
    errors = [0.0]
    ladder = ("decimate", "prune", "block", "box") if building else ("decimate", "prune", "hull", "box")
    stage = 0  # position in the ladder the next candidates start from
    reach = 0  # the next prune candidates start at PRUNE_REACH[reach]
    made: dict[tuple, tuple | None] = {}  # (method, reach) → the proxy made from the finest level
    shells = blocks.shell_reach(*fine) if "prune" in ladder else None
    roof = blocks.roof_height(*fine) if building else None  # block and box share it
    shaped: dict[tuple, tuple] = {}  # (method, reach) → its cheap measures
    raw_error: dict[tuple, float] = {}  # (method, reach) → its geometric error
    regenerated = dropped = 0
    while len(fine_first) < max_levels:
        pos, fac = fine_first[-1]
        m = fac.shape[0]
        limit = int(np.floor((1.0 - min_saving) * m))
        if limit < floor_faces and stage == 0:
            break
        tried, candidates = [], []
        for method in ladder[stage:]:
            if method == "decimate":
                if limit < floor_faces:
                    continue
                target = min(limit, max(floor_faces, int(round(ratio * m))))
                cp, cf, vmap = _simplify_step(pos, fac, target, preserve_border)
                if not floor_faces <= cf.shape[0] <= limit:
                    continue
                level: tuple | None = (cp, cf)
                key: tuple = ("decimate", m)
                ok, fid = _shape(ref, level, method, bounds)
            else:
                # prune: the weakest reach that fits the limit; the others are one proxy each
                reaches = range(reach, len(PRUNE_REACH)) if method == "prune" else (0,)
                level = None
                for r in reaches:
                    key = (method, r)
                    if key not in made:
                        made[key] = _proxy(method, fine, PRUNE_REACH[r] * diag, shells, roof)
                    if made[key] is not None and made[key][1].shape[0] <= limit:
                        level = made[key]
                        break
                if level is None:
                    continue
                vmap = None
                if key not in shaped:  # a proxy is the same mesh at every step: measure it once
                    shaped[key] = _shape(ref, level, method, bounds)
                ok, fid = shaped[key]
            tried.append(method)
            if ok:
                candidates.append((fid.iou, -level[1].shape[0], method, key, level, vmap, fid))
        chosen = None
        # Those within IOU_TIE of the best silhouette first, fewest faces first; then the rest, best first.
        top = max((c[0] for c in candidates), default=0.0)
        order = sorted(candidates, key=lambda c: (c[0] >= top - IOU_TIE, c[1] if c[0] >= top - IOU_TIE else c[0]),
                       reverse=True)
        for _, _, method, key, level, vmap, fid in order:
            if key not in raw_error:
                raw_error[key] = geometric_error(fine[0], level[0], level[1], samples)
            err = max(raw_error[key], errors[-1])
            fid = Fidelity(fid.area_ratio, fid.iou, flip_error(ref, level[0], level[1], err), method)
            if bounds.passes(fid, ref.closed):
                chosen = (method, key, level, vmap, fid, err)
                break
        if chosen is None:
            dropped += bool(tried)
            break
        method, key, level, vmap, fid, err = chosen
        if tried and tried[0] == "decimate" and method != "decimate":
            regenerated += 1
        if method != "decimate":  # a decimated level is ordered already (its collapse map refers to it)
            level = _prepare(*level)
        fine_first.append(level)
        maps.append(vmap)
        fids.append(fid)
        errors.append(err)
        if method == "prune":  # a stronger prune may follow, then the rest of the ladder
            stage, reach = ladder.index("prune"), key[1] + 1
            if reach >= len(PRUNE_REACH):
                stage += 1
        else:
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
    return ShapedChain(chain, fids[::-1], regenerated, dropped, box=made.get(("box", 0)))


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
                return max(geometric_error(fine[0], level[0], level[1], samples), errors[-1])

            ok, fid, err = _measured(ref, level, error, method, bounds)
            if ok:
                chosen = (_prepare(*level) if method != "source" else level, fid, err)
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
