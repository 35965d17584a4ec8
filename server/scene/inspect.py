"""What a scene store holds, as numbers a person or a script can read (``walkstream inspect``).

Everything comes from the index arrays and the stored walkable grid (no
geometry is decoded), so a megacity store reports in the time its index takes
to load.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from .fidelity import Bounds
from .index import HLOD, KINDS, TERRAIN, TREES
from .store import SceneStore
from .tour import default_tour_name, named_tours

__all__ = ["inspect_store", "format_report"]


def inspect_store(path: str | os.PathLike[str]) -> dict:
    """A JSON-ready report: objects, representations, triangles and bytes per kind and level, depth."""
    started = time.perf_counter()
    with SceneStore.open(path) as store:
        load = time.perf_counter() - started
        idx = store.index
        fid = store.fidelity()
        names = store.object_names() if fid is not None else []
        walkable = _walkable(store.stored_walkable())
    kinds = {}
    for k, kind in enumerate(KINDS):
        objs = np.nonzero(idx.object_kind == k)[0]
        if objs.size == 0:
            continue
        reps = np.nonzero(np.isin(idx.rep_object, objs))[0]
        depth = idx.object_depth[objs]
        # A hierarchy node has one representation; its level is its depth in the tree.
        by_depth = k in (HLOD, TERRAIN) or bool((idx.rep_count[objs] == 1).all() and np.ptp(depth) > 0)
        level = (depth - depth.min())[np.searchsorted(objs, idx.rep_object[reps])] if by_depth else idx.rep_level[reps]
        size = "points" if k == TREES else "triangles"
        amount = idx.rep_vertices[reps] if k == TREES else idx.rep_faces[reps]
        per_level = [
            {"depth" if by_depth else "level": int(lv), "representations": int((level == lv).sum()),
             size: int(amount[level == lv].sum()),
             "vertices": int(idx.rep_vertices[reps][level == lv].sum()),
             "bytes": int(idx.rep_bytes[reps][level == lv].sum()),
             "max_error": float(idx.rep_error[reps][level == lv].max())}
            for lv in np.unique(level)
        ]
        depth = idx.object_depth[objs]
        entry = {
            "objects": int(objs.size),
            "representations": int(reps.size),
            "bytes": int(idx.rep_bytes[reps].sum()),
            "levels": per_level,
            "hierarchy_depth": int(depth.max()) + 1 if objs.size else 0,
            "morph_maps": int(idx.rep_morph[reps].sum()),
        }
        if k != TREES:
            full = idx.rep_first[objs] + idx.rep_count[objs] - 1
            entry["triangles_full_detail"] = int(idx.rep_faces[full].sum())
        shape = None if fid is None else _fidelity(idx, fid, reps, level, by_depth, names)
        if shape is not None and shape["measured"]:  # a kind with nothing measured (trees, terrain) says nothing
            entry["fidelity"] = shape
        kinds[kind] = entry
    classes = np.bincount(idx.object_class, minlength=len(idx.class_names))
    full = idx.rep_first + idx.rep_count - 1
    return {
        "path": str(path),
        "name": idx.name,
        "schema_version": idx.meta.get("schema_version"),
        "generator": idx.meta.get("generator"),
        "seed": idx.meta.get("seed"),
        "crs": idx.meta.get("crs"),
        "origin": idx.meta.get("origin"),
        "file_bytes": Path(path).stat().st_size,
        "index_load_s": round(load, 4),
        "bounds": idx.bounds.tolist(),
        "objects": idx.n_objects,
        "representations": idx.n_representations,
        "triangles_full_detail": int(idx.rep_faces[full[idx.flat]].sum()),
        "hierarchy_depth": idx.height,
        "classes": {name: int(c) for name, c in zip(idx.class_names, classes)},
        "kinds": kinds,
        "tree_models": int(idx.model_points.shape[0]),
        # Stores built before the sources were recorded list the models without one.
        "tree_model_sources": [{"id": i, **m} for i, m in enumerate(idx.meta.get("tree_models") or [])]
        or [{"id": i, "name": None, "source": None, "points": int(n)} for i, n in enumerate(idx.model_points)],
        "tree_instances": int(idx.meta.get("tree_instances", 0)),
        "tour_seconds": float(idx.tour[-1]["t"]) if idx.tour else 0.0,
        "tours": _tours(idx),
        "viewpoints": idx.meta.get("viewpoints") or {},
        "shape_guard": idx.meta.get("shape_guard") or {},
        "walkable": walkable,
    }


def _tours(idx) -> list[dict]:
    """The store's tours: name, kind, duration (s), keys, and which one a client that names none is sent."""
    default = default_tour_name(idx)
    return [{"name": name, "kind": t["kind"], "duration": round(float(t["duration"]), 3), "keys": len(t["keys"]),
             "default": name == default} for name, t in named_tours(idx).items()]


def _walkable(grid) -> dict:
    """The stored walkable grid's shape, cell size and walkable share (``stored`` False: built before grids
    were; a server computes it on first use)."""
    if grid is None:
        return {"stored": False}
    walk = np.isfinite(grid.ground)
    return {"stored": True, "shape": list(grid.shape), "cell": round(grid.cell, 4),
            "walkable_share": round(float(walk.mean()), 4),
            "height": [round(float(grid.ground[walk].min()), 3), round(float(grid.ground[walk].max()), 3)]
            if walk.any() else None}


def _quantiles(x: np.ndarray) -> dict:
    x = x[np.isfinite(x)]
    if x.size == 0:
        return {}
    q = np.quantile(x, [0.0, 0.1, 0.5, 1.0])
    return {"min": round(float(q[0]), 4), "p10": round(float(q[1]), 4), "median": round(float(q[2]), 4),
            "max": round(float(q[3]), 4)}


def _fidelity(idx, fid: dict, reps: np.ndarray, level: np.ndarray, by_depth: bool, names: list[str],
              worst: int = 5) -> dict:
    """Measured shape of the coarse representations of one kind: per level, and the worst by name."""
    bounds = Bounds()
    pos = np.searchsorted(fid["rep"], reps)
    n = fid["rep"].size
    has = (pos < n) & (fid["rep"][np.minimum(pos, max(n - 1, 0))] == reps) if n else np.zeros(reps.size, bool)
    full = idx.rep_first[idx.rep_object[reps]] + idx.rep_count[idx.rep_object[reps]] - 1
    coarse = has & ((reps != full) | by_depth)
    rows = pos[coarse]
    lv = level[coarse]
    iou, area, flip = fid["iou"][rows], fid["area_ratio"][rows], fid["flip"][rows]
    area_score = np.minimum(area, 1.0 / np.maximum(area, 1e-12))
    below = (iou < bounds.iou) | ((area_score < bounds.area) & fid["closed"][rows]) | (flip > bounds.flip)
    per = []
    for v in np.unique(lv):
        s = lv == v
        methods, counts = np.unique(fid["method"][rows][s].astype(str), return_counts=True)
        per.append({"depth" if by_depth else "level": int(v), "measured": int(s.sum()),
                    "below_bounds": int(below[s].sum()), "iou": _quantiles(iou[s]),
                    "area_ratio": _quantiles(area[s]), "flip": _quantiles(flip[s]),
                    "methods": {str(m): int(c) for m, c in zip(methods, counts)}})
    order = np.argsort(iou, kind="stable")[:worst]
    obj = idx.rep_object[reps][coarse]
    return {"measured": int(coarse.sum()), "below_bounds": int(below.sum()), "levels": per,
            "worst": [{"name": names[int(obj[i])], "depth" if by_depth else "level": int(lv[i]),
                       "iou": round(float(iou[i]), 4), "area_ratio": round(float(area[i]), 4),
                       "flip": None if not np.isfinite(flip[i]) else round(float(flip[i]), 4),
                       "method": str(fid["method"][rows][i])} for i in order]}


def _n(x: float) -> str:
    for unit, div in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if abs(x) >= div:
            return f"{x / div:.2f}{unit}"
    return f"{x:.0f}"


def format_report(r: dict) -> list[str]:
    """The report as lines of text for a terminal."""
    lines = [
        f"{r['name']}  ({r['path']}, schema v{r['schema_version']}, {_n(r['file_bytes'])}B, "
        f"index loads in {r['index_load_s'] * 1e3:.0f} ms)",
        f"  {r['objects']} objects, {r['representations']} representations, "
        f"{_n(r['triangles_full_detail'])} triangles at full detail, hierarchy depth {r['hierarchy_depth']}",
        f"  crs {r['crs'] or '-'}, origin {r['origin']}, tour {r['tour_seconds']:.0f} s"
        + (f", viewpoints {r['viewpoints']}" if r["viewpoints"] else ""),
        "  classes: " + ", ".join(f"{k} {v}" for k, v in r["classes"].items()),
        "  tours: " + (", ".join(f"{t['name']} ({t['kind']}, {t['duration']:.0f} s{', default' if t['default'] else ''})"
                                 for t in r["tours"]) or "none"),
    ]
    for kind, e in r["kinds"].items():
        lines.append(f"  {kind}: {e['objects']} objects, {e['representations']} reps, {_n(e['bytes'])}B, "
                     f"depth {e['hierarchy_depth']}, {e['morph_maps']} morph maps")
        for lv in e["levels"]:
            size = lv.get("triangles", lv.get("points"))
            what = "triangles" if "triangles" in lv else "points"
            row = f"depth {lv['depth']}" if "depth" in lv else f"level {lv['level']}"
            lines.append(f"    {row}: {lv['representations']:6d} reps  {_n(size):>8} {what}  "
                         f"{_n(lv['vertices']):>8} vertices  {_n(lv['bytes']):>8}B  max error {lv['max_error']:.3g}")
        f = e.get("fidelity")
        if f:
            verdict = "all within bounds" if f["below_bounds"] == 0 else f"{f['below_bounds']} below bounds"
            lines.append(f"    shape: {f['measured']} coarse representations measured, {verdict}")
            for lv in f["levels"]:
                row = f"depth {lv['depth']}" if "depth" in lv else f"level {lv['level']}"
                q = lambda d: f"{d.get('min', float('nan')):.2f}/{d.get('p10', float('nan')):.2f}/{d.get('median', float('nan')):.2f}"  # noqa: E731
                lines.append(f"      {row}: iou min/p10/med {q(lv['iou'])}  area {q(lv['area_ratio'])}  "
                             f"flip med {lv['flip'].get('median', float('nan')):.3f}  "
                             + ", ".join(f"{m} {c}" for m, c in lv["methods"].items()))
            lines.append("      worst: " + "; ".join(
                f"{w['name']} ({w['method']}) iou {w['iou']:.2f} area {w['area_ratio']:.2f}" for w in f["worst"]))
    guard = r.get("shape_guard") or {}
    if guard:
        lv, px = guard.get("levels", {}), guard.get("proxies")
        line = (f"  shape guard at build: {lv.get('measured', 0)} coarse levels kept, {lv.get('below_bounds', 0)} below "
                f"bounds, {lv.get('regenerated', 0)} regenerated by the ladder, {lv.get('dropped', 0)} dropped")
        if px:
            line += (f"; HLOD proxies: {px['kept']} of {px['nodes']} nodes kept, {px['below_bounds']} below bounds, "
                     f"{px['regenerated']} regenerated, {px['dropped']} not kept (their children stand in)")
        lines.append(line)
    if r["tree_models"]:
        lines.append(f"  tree models: {r['tree_models']}, tree instances: {r['tree_instances']}")
        for m in r["tree_model_sources"]:
            lines.append(f"    model {m['id']}: {m['name'] or '-'}  {m['points']} points  from {m['source'] or '-'}")
    w = r.get("walkable") or {}
    if w.get("stored"):
        ny, nx = w["shape"]
        lines.append(f"  walkable grid: {nx} × {ny} cells of {w['cell']:.3g} m, {100 * w['walkable_share']:.1f} % walkable"
                     + (f", ground {w['height'][0]:.2f} … {w['height'][1]:.2f} m" if w["height"] else ""))
    else:
        lines.append("  walkable grid: not stored (built before walkable grids; the server computes it on first use)")
    return lines
