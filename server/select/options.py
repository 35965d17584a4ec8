"""The options of one selection and what each is worth under the selection's cameras.

Per visible object every option — level × rendering algorithm, F&S's object tuple
(O, L, R) — with its benefit and cost: culling (inside any camera's frustum),
projection (screen size, centre offset and screen speed per camera), F&S's benefit
summed over the cameras, and the cost model's price at the most pixels a sampled
camera sees. Each step runs the compiled kernels (``kernels.view``) once they are
warm and the numpy functions of ``camera`` and ``benefit`` until then; both give
the same numbers.

The views (``selection.Levels``) are read through their fields only; ``cached``
keeps the arrays derived from a view's static fields with the view.
"""

from __future__ import annotations

import numpy as np

from . import kernels
from .benefit import benefit_matrix, importance, with_algorithms
from .camera import centre_offset, cull_boxes, screen_size, screen_speed

__all__ = ["cached", "option_arrays", "cull", "project", "cull_project_many", "benefit_cost", "node_size", "benefit_kernel"]


def cached(lv, key, make):
    """A per-``Levels`` array derived from its static fields, computed once (the views live as long as the scene)."""
    cache = vars(lv).setdefault("_derived", {})
    if key not in cache:
        cache[key] = make()
    return cache[key]


def option_arrays(lv, rows: np.ndarray, algorithms: int = 1):
    """(v, K·R) representation ids, validity, faces and vertices of the given rows' options.

    Option k is level k // R drawn with the k % R-th offered rendering algorithm
    (F&S's tuples (O, L, R)); with R = 1 options are levels. K is the most levels
    among ``rows``. The arrays of all rows are built once per view and gathered.
    """
    def every():
        count = lv.rep_count.astype(np.int64)
        k = int(count.max()) if count.size else 1
        slot = np.arange(k)[None, :]
        valid = slot < count[:, None]
        rep = np.where(valid, lv.rep_first[:, None].astype(np.int64) + slot, 0)
        faces, vertices = np.where(valid, lv.rep_faces[rep], 0), np.where(valid, lv.rep_vertices[rep], 0)
        if algorithms > 1:
            rep, valid, faces, vertices = (np.repeat(a, algorithms, axis=1) for a in (rep, valid, faces, vertices))
        return count, rep, valid, faces, vertices

    count, *arrays = cached(lv, ("options", algorithms), every)
    k = int(np.take(count, rows).max()) if rows.size else 1
    cols = k * algorithms
    out = (np.take(a, rows, axis=0) for a in arrays)  # take: a gather of rows, much cheaper than a[rows, :cols]
    return tuple(a if a.shape[1] == cols else np.ascontiguousarray(a[:, :cols]) for a in out)


def option_errors(lv, rows: np.ndarray, cols: int, algorithms: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(v, cols) the geometric error of the given rows' options (0 where invalid), as ``option_arrays`` lays
    them out, and (v,) the rows' box diagonals: the screen-space error accuracy's inputs, built once per view."""
    def every():
        rep, valid, _, _ = option_arrays(lv, np.arange(lv.n), algorithms)
        extent = np.linalg.norm(lv.object_hi.astype(np.float64) - lv.object_lo, axis=1)
        return np.where(valid, lv.rep_error[rep], 0.0), extent

    error, extent = cached(lv, ("errors", algorithms), every)
    error = np.take(error, rows, axis=0)
    return (error if error.shape[1] == cols else np.ascontiguousarray(error[:, :cols])), np.take(extent, rows)


def _tuple_cost(cost_model, faces, vertices, pixels, alg, valid, kern):
    """(v, K) seconds per option, inf where invalid: the model's F&S terms, one draw each. pixels (v,), alg (K,)."""
    if kern is None:
        return np.where(valid, cost_model.predict_terms(faces, vertices, pixels[:, None], alg[None, :], 1.0), np.inf)
    c_poly, c_vert, c_pixel, c_draw = cost_model.tuple_coefficients()
    if alg.size and (alg.min() < 0 or alg.max() >= c_poly.size):
        raise ValueError(f"algorithm index out of range 0..{c_poly.size - 1}")
    out = np.empty(faces.shape)
    kern.tuple_cost(np.ascontiguousarray(c_poly, np.float64), np.ascontiguousarray(c_vert, np.float64),
                    np.ascontiguousarray(c_pixel, np.float64), float(c_draw), faces, vertices,
                    np.ascontiguousarray(pixels, np.float64), alg, valid, out)
    return out


def _view_kernels():
    """The compiled culling, projection and benefit kernels once they are warm, else None (numpy)."""
    ready = kernels.compiled()
    return ready.view if ready is not None else None


def _stack(cams):
    """(C, 4, 4) clip matrices, (C, 6, 4) planes, (C,) widths and heights of the cameras."""
    clips = np.stack([c.clip for c in cams])
    planes = np.stack([c.planes for c in cams])
    widths = np.array([c.view.width for c in cams], np.float64)
    heights = np.array([c.view.height for c in cams], np.float64)
    return clips, planes, widths, heights


def _before(memory, cams):
    """The previous view's clip matrix and each camera's dt to it (None where motion is not measured)."""
    if memory is None or memory.view is None or memory.t is None:
        return None, [None] * len(cams)
    dts = [c.t - memory.t if c.t is not None and c.t > memory.t else None for c in cams]
    if all(d is None for d in dts):
        return None, dts
    return memory.view.matrix(), dts


def project(lv, rows, cams, before, dts):
    """(C, v) screen size (0 outside a camera's frustum when there are several), centre offset and
    screen speed (None for a camera without a motion measure) of ``rows`` under every camera."""
    kern = _view_kernels()
    many = len(cams) > 1
    if kern is not None:
        clips, planes, widths, heights = _stack(cams)
        c, v = len(cams), rows.size
        size, offset, moved = np.empty((c, v)), np.empty((c, v)), np.empty((c, v))
        kern.project(lv.object_lo, lv.object_hi, rows.astype(np.int64, copy=False), clips, planes, widths, heights,
                     many, clips[0] if before is None else before, before is not None, size, offset, moved)
        return size, offset, _speeds(moved, dts)
    lo, hi = lv.object_lo[rows], lv.object_hi[rows]
    size, offset, speed = [], [], []
    for cam, dt in zip(cams, dts):
        wide, clip = cam.view, cam.clip
        s = screen_size(lo, hi, clip, wide.width, wide.height)
        size.append(np.where(cull_boxes(lo, hi, cam.planes), s, 0.0) if many else s)
        offset.append(centre_offset(lo, hi, clip, wide.width, wide.height))
        speed.append(None if dt is None else screen_speed(lo, hi, clip, before, dt, wide.width, wide.height))
    return np.stack(size), np.stack(offset), speed


def _speeds(moved: np.ndarray, dts) -> list:
    """The screen speed per camera (px/s) from the distance moved, None where motion is not measured."""
    moving = np.array([dt is not None for dt in dts])
    if moving.any():
        moved /= np.array([float(dt) if dt is not None else 1.0 for dt in dts])[:, None]
    return [moved[j] if m else None for j, m in enumerate(moving)]


def cull_project_many(lv, jobs) -> list | None:
    """``cull`` and ``project`` of several selections over one view in one compiled pass (None until the
    kernels are ready): jobs are (cameras, memory) pairs; per job (rows, (size, offset, speed)), the
    numbers ``cull`` and ``project`` give for it alone."""
    kern = _view_kernels()
    if kern is None or not jobs:
        return None
    cams_all = [c for cams, _ in jobs for c in cams]
    clips, planes, widths, heights = _stack(cams_all)
    counts = np.array([len(cams) for cams, _ in jobs], np.int64)
    cam_start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    befores, has_before, dts_all = np.empty((len(jobs), 4, 4)), np.zeros(len(jobs), bool), []
    for b, (cams, memory) in enumerate(jobs):
        before, dts = _before(memory, cams)
        befores[b] = clips[cam_start[b]] if before is None else before
        has_before[b] = before is not None
        dts_all.append(dts)
    rows, row_start, size, offset, moved, out_start = kern.cull_project_many(
        lv.object_lo, lv.object_hi, planes, clips, widths, heights, cam_start, counts > 1, befores, has_before)
    out = []
    for b, dts in enumerate(dts_all):
        shape = (int(counts[b]), int(row_start[b + 1] - row_start[b]))
        o0, o1 = out_start[b], out_start[b + 1]
        out.append((rows[row_start[b]:row_start[b + 1]], (size[o0:o1].reshape(shape), offset[o0:o1].reshape(shape),
                                                         _speeds(moved[o0:o1].reshape(shape), dts))))
    return out


def benefit_cost(lv, rows, scene, cams, cost_model, memory, factors, algorithms=(0,), pixel_scale=1.0,
                 projected=None):
    """Per visible row: (v, K) benefit and cost of each option, with the F&S factors the inputs allow.

    Over several cameras (an ``Interval``) benefit is their weighted sum, a row
    outside a camera's frustum gaining nothing from it, and size the mean over
    the sampled ones; cost is the maximum over the sampled cameras — with a
    fitted fill term it depends on the pixels covered, estimated as the box's
    screen area × ``pixel_scale`` (the measured share of box area really covered).
    ``algorithms`` are the offered rendering algorithms (indices into
    ``proto.messages.ALGORITHMS``); option k draws level k // R with ``algorithms[k % R]``.
    ``projected``: ``project``'s (size, offset, speed) of ``rows``, when a batch computed it already.
    """
    r = len(algorithms)
    rep, valid, faces, vertices = option_arrays(lv, rows, r)
    alg = np.asarray(algorithms, np.int64)[np.arange(faces.shape[1]) % r]
    if r > 1 or tuple(algorithms) != (0,):
        factors = with_algorithms(factors, algorithms)
    previous = None
    if memory is not None and memory.option is not None:
        previous = memory.option[lv.ids[rows]] if lv.ids is not None else memory.option[rows]
    klass = lv.object_class[rows] if lv.object_class is not None and scene.importance is not None else None
    if projected is None:
        before, dts = _before(memory, cams)
        projected = project(lv, rows, cams, before, dts)
    size, offset, speed = projected
    if lv.parent is not None:
        size = node_size(lv, rows, size)
    weight = np.array([cam.weight for cam in cams], np.float64)
    original = lv.original_faces()[rows] if factors.accuracy == "zach" else None
    kern = _view_kernels()
    error = extent = None
    if factors.accuracy == "sse":
        if lv.rep_error is None:
            raise ValueError("screen-space error accuracy needs the view's rep_error (Levels.subset of an index)")
        error, extent = option_errors(lv, rows, faces.shape[1], r)
    # Only a view holding textured representations pays for the texture's share of accuracy.
    textured = (np.take(lv.rep_textured, rep) & valid) if getattr(lv, "rep_textured", None) is not None else None
    if kern is not None:
        imp = None
        if klass is not None and factors.importance:
            table = np.asarray(scene.importance, np.float64)
            every = cached(lv, ("importance", table.tobytes()), lambda: importance(lv.object_class, table))
            imp = np.take(every, rows)  # the rows' class weights, from the view's once per importance table
        benefit = benefit_kernel(kern, size, offset, speed, weight, faces, vertices, valid, r, factors, klass,
                                 scene.importance, previous, original, error, extent, textured, imp)
    else:
        benefit = np.zeros(faces.shape)
        for j in range(len(cams)):
            benefit += weight[j] * benefit_matrix(
                size[j], faces, algorithms=r, factors=factors, vertices=vertices, original_faces=original,
                object_class=klass, importance_table=scene.importance, offset=offset[j], speed=speed[j],
                previous=previous, error=error, extent=extent, textured=textured,
            )
        benefit = np.where(valid, benefit, 0.0)
    sampled = np.array([cam.sampled for cam in cams])
    # Cost is the maximum over the sampled cameras. The models' costs never fall with the pixels covered
    # (non-negative coefficients), so that is the cost at the most pixels any of them sees — to the bit,
    # as rounding is monotone too — and the model runs once.
    pixels = size[sampled].max(axis=0) * pixel_scale if sampled.any() else np.zeros(rows.size)
    cost = _tuple_cost(cost_model, faces, vertices, pixels, alg, valid, kern)
    mean_size = size[sampled].sum(axis=0) / max(int(sampled.sum()), 1) if sampled.any() else np.zeros(rows.size)
    return mean_size, rep, valid, faces, benefit, cost, previous


def node_size(lv, rows: np.ndarray, size: np.ndarray) -> np.ndarray:
    """(C, v) screen size of hierarchy nodes: a node's own box, but never more than its visible children's together.

    A node stands for the objects below it, and its box also covers the gaps between them:
    seen from inside a city the root's box fills the screen while its children's cover half
    of it. Zach's screenSize(o) is the object's, so a split must not lose the gaps' pixels
    (it made splitting the root worth nothing). Bottom-up one depth at a time over ``rows``
    (visible rows: a visible node's parent is among them), every camera at once.
    """
    v = rows.size
    c = size.shape[0]
    local = np.full(lv.n, -1, np.int64)
    local[rows] = np.arange(v)
    up = lv.parent[rows]
    parent = np.where(up >= 0, local[np.maximum(up, 0)], -1)
    if not (parent >= 0).any():
        return size
    depth = lv.depth()[rows]
    has_kids = np.bincount(parent[parent >= 0], minlength=v) > 0
    out = size.copy()
    kids = np.zeros((c, v))
    base = (np.arange(c) * v)[:, None]
    for d in range(int(depth.max()), 0, -1):
        q = np.nonzero(depth == d)[0]  # final: their own children were summed in the previous pass
        q = q[parent[q] >= 0]
        kids += np.bincount((base + parent[q][None, :]).ravel(), weights=out[:, q].ravel(),
                            minlength=c * v).reshape(c, v)
        done = np.nonzero((depth == d - 1) & has_kids)[0]
        out[:, done] = np.minimum(out[:, done], kids[:, done])
    return out


def benefit_kernel(kern, size, offset, speed, weight, faces, vertices, valid, r, factors, klass, table, previous,
                   original=None, error=None, extent=None, textured=None, importance_rows=None):
    """``benefit_matrix`` summed over the cameras in one compiled pass (same factors, same arithmetic).

    original : (v,) Zach's #originalFaces (``benefit_matrix``'s ``original_faces``), None: each row's most faces
    error, extent : (v, K) geometric error per option and (v,) box diagonals, for "sse" accuracy
    textured : (v, K) bool, the option's representation carries a texture (None: none does)
    importance_rows : (v,) the rows' Importance weights when the caller has them (else from ``klass``, ``table``)
    """
    from .benefit import ALGORITHM_SAMPLES, texture_accuracy

    names = factors.algorithm_names
    if r < 1 or r > len(names):
        raise ValueError(f"algorithms must be in 1..{len(names)}, got {r}")
    mode = {"off": kern.ACCURACY_OFF, "fs": kern.ACCURACY_FS, "auto": kern.ACCURACY_FS,
            "zach": kern.ACCURACY_ZACH, "sse": kern.ACCURACY_SSE}[factors.accuracy]
    if mode == kern.ACCURACY_SSE and (error is None or extent is None):
        raise ValueError("screen-space error accuracy needs each option's error and the rows' extent")
    err = np.zeros((0, 0)) if error is None else np.ascontiguousarray(error, np.float64)
    ext = np.zeros(0) if extent is None else np.ascontiguousarray(extent, np.float64)
    orig = np.zeros(0) if original is None else np.ascontiguousarray(original, np.float64)
    if orig.size and orig.shape != faces.shape[:1]:
        raise ValueError(f"original faces must be ({faces.shape[0]},); got {orig.shape}")
    per_vertex = np.array([ALGORITHM_SAMPLES.get(names[a], "faces") == "vertices" for a in range(r)])
    exponent = np.array([float(factors.exponent[names[a]]) for a in range(r)])
    empty2 = np.zeros((0, 0))
    if importance_rows is not None:
        imp = np.asarray(importance_rows, np.float64)
    else:
        imp = (importance(klass, table) if factors.importance and klass is not None and table is not None
               else np.zeros(0))
    off = offset if factors.focus else empty2
    moving = np.array([factors.motion and s is not None for s in speed])
    spd = np.stack([np.zeros(size.shape[1]) if s is None else s for s in speed]) if moving.any() else size
    prev = (np.asarray(previous, np.int64) if factors.hysteresis and previous is not None
            else np.zeros(0, np.int64))
    appearance = (texture_accuracy(textured, r, names) if textured is not None and mode != kern.ACCURACY_OFF
                  else empty2)
    out = np.empty(faces.shape)
    kern.benefit_sum(size, off, spd, moving, weight, faces, vertices, valid, per_vertex, exponent, r, mode, orig,
                     err, ext, factors.size, imp, factors.focus_strength, factors.motion_strength, factors.frame_time, prev,
                     factors.level_weight, factors.algorithm_weight, appearance, out)
    return out


def cull(lv, cams) -> np.ndarray:
    """(n,) bool — rows inside any camera's frustum."""
    kern = _view_kernels()
    if kern is not None:
        visible = np.empty(lv.n, bool)
        kern.cull_any(lv.object_lo, lv.object_hi, np.stack([cam.planes for cam in cams]), visible)
        return visible
    visible = np.zeros(lv.n, bool)
    for cam in cams:
        visible |= cull_boxes(lv.object_lo, lv.object_hi, cam.planes)
    return visible
