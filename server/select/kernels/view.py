"""Compiled per-box and per-tuple loops of one selection (numba): culling, projection, benefit.

A selection looks at every box from several cameras (an ``Interval``: the
predicted samples and the conservative camera). In numpy each quantity —
frustum test, eight projected corners for the screen size, the projected
centre for Focus and Motion, then every F&S factor over (n, K) — is its own
pass with its own temporaries, and at a few thousand boxes the passes cost
more than the arithmetic. These kernels do it in one pass per box, and
compute exactly what ``camera`` and ``benefit`` compute (same formulas, same
order of operations; they stay the reference the tests compare with).

Pure functions of arrays (no clock, no I/O), compiled with the solvers' kernels by
``kernels.warm_up``; the selection uses them once that is done and the numpy path
until then.
"""

from __future__ import annotations

import math

import numpy as np

from ..benefit import BASE_ERROR, MIN_FACTOR
from ..camera import SPEED_LIMIT_NDC
from .jit import jit

__all__ = ["ACCURACY_OFF", "ACCURACY_FS", "ACCURACY_ZACH", "ACCURACY_SSE", "cull_any", "project", "cull_project_many",
           "benefit_sum", "compile_all"]

ACCURACY_OFF, ACCURACY_FS, ACCURACY_ZACH, ACCURACY_SSE = 0, 1, 2, 3


@jit()
def cull_any(lo, hi, planes, visible):
    """visible[i] = box i passes every plane of at least one camera; planes (C, 6, 4) (``camera.cull_boxes``)."""
    n, c = lo.shape[0], planes.shape[0]
    for i in range(n):
        visible[i] = _inside_any(lo, hi, i, planes, c)


@jit(inline="always")
def _inside(lo, hi, i, planes, j):
    for p in range(6):
        a, b, c, d = planes[j, p, 0], planes[j, p, 1], planes[j, p, 2], planes[j, p, 3]
        px = np.float64(hi[i, 0]) if a >= 0 else np.float64(lo[i, 0])
        py = np.float64(hi[i, 1]) if b >= 0 else np.float64(lo[i, 1])
        pz = np.float64(hi[i, 2]) if c >= 0 else np.float64(lo[i, 2])
        if not (a * px + b * py + c * pz + d >= 0):
            return False
    return True


@jit(inline="always")
def _inside_any(lo, hi, i, planes, c):
    for j in range(c):
        if _inside(lo, hi, i, planes, j):
            return True
    return False


@jit(inline="always")
def _centre(cx, cy, cz, m, limit):
    """NDC x, y of a point under clip matrix m, clamped to ±limit; behind the eye: on the clamp border."""
    x = cx * m[0, 0] + cy * m[0, 1] + cz * m[0, 2] + m[0, 3]
    y = cx * m[1, 0] + cy * m[1, 1] + cz * m[1, 2] + m[1, 3]
    w = cx * m[3, 0] + cy * m[3, 1] + cz * m[3, 2] + m[3, 3]
    return _ndc(x, y, w, limit)


@jit(inline="always")
def _ndc(x, y, w, limit):
    """``_centre`` from the point's clip coordinates. Every case is computed and one selected (no branches),
    so that the loops calling it run several points at once; a case not selected may divide by zero."""
    reach = max(abs(x), abs(y))
    s = max(reach, 1e-300)
    front, far = w > 1e-9, reach > 1e-12
    nx = min(max(x / w, -limit), limit) if front else (x / s * limit if far else limit)
    ny = min(max(y / w, -limit), limit) if front else (y / s * limit if far else limit)
    return nx, ny


@jit()
def project(lo, hi, rows, clips, planes, widths, heights, cull, before, has_before, size, offset, moved):
    """Per camera j and row i of ``rows``: screen size, centre offset and centre travel since ``before``.

    lo, hi : (N, 3) boxes; rows : (v,) int64 indices into them
    clips, planes : (C, 4, 4) world → clip, (C, 6, 4) frustum planes; widths, heights : (C,) float64 pixels
    cull : zero the size of boxes outside camera j's frustum (``camera.cull_boxes``)
    before : (4, 4) the previous view's clip matrix, used iff ``has_before``
    size, offset, moved : (C, v) outputs — ``camera.screen_size`` (0 when culled), ``camera.centre_offset``,
        and the pixel distance ``screen_speed`` divides by dt (0 without ``before``)
    The rows' corners, extents and centres are gathered once into float64 rows (``g``); then each camera
    streams over them in branch-free loops (``_sizes``, ``_offsets``), which the compiler runs several boxes
    at a time.
    """
    nc, v = clips.shape[0], rows.shape[0]
    lim = SPEED_LIMIT_NDC
    g = np.empty((12, v))  # lo x, y, z; hi x, y, z; extent x, y, z; centre x, y, z
    was = np.zeros((2, v))  # where the centres were on screen under ``before``, in NDC
    for q in range(v):
        i = rows[q]
        for a in range(3):
            l, h = np.float64(lo[i, a]), np.float64(hi[i, a])
            g[a, q], g[3 + a, q], g[6 + a, q], g[9 + a, q] = l, h, h - l, (l + h) * 0.5
        if has_before:
            was[0, q], was[1, q] = _centre(g[9, q], g[10, q], g[11, q], before, lim)
    for j in range(nc):
        _sizes(g, clips[j], planes[j], widths[j], heights[j], cull, size[j])
        _offsets(g, clips[j], widths[j], heights[j], has_before, was, lim, offset[j], moved[j])


@jit()
def _sizes(g, m, pl, wd, ht, cull, out):
    """``project``'s screen sizes for one camera: the eight corners' clip coordinates from the lo corner plus
    the edges along the set bits; 0 outside the frustum when ``cull`` (``_inside``'s plane test)."""
    v = g.shape[1]
    m00, m01, m02, m03 = m[0, 0], m[0, 1], m[0, 2], m[0, 3]
    m10, m11, m12, m13 = m[1, 0], m[1, 1], m[1, 2], m[1, 3]
    m30, m31, m32, m33 = m[3, 0], m[3, 1], m[3, 2], m[3, 3]
    full = float(wd * ht)
    lx, ly, lz, hx, hy, hz, ex, ey, ez = g[0], g[1], g[2], g[3], g[4], g[5], g[6], g[7], g[8]
    # Each plane's corner farthest along its normal: hi where the normal's component is ≥ 0.
    up = np.empty((6, 3), np.bool_)
    for p in range(6):
        for a in range(3):
            up[p, a] = pl[p, a] >= 0
    for q in range(v):
        inside = True
        for p in range(6):
            px = hx[q] if up[p, 0] else lx[q]
            py = hy[q] if up[p, 1] else ly[q]
            pz = hz[q] if up[p, 2] else lz[q]
            inside &= pl[p, 0] * px + pl[p, 1] * py + pl[p, 2] * pz + pl[p, 3] >= 0
        b0 = lx[q] * m00 + ly[q] * m01 + lz[q] * m02 + m03
        b1 = lx[q] * m10 + ly[q] * m11 + lz[q] * m12 + m13
        b3 = lx[q] * m30 + ly[q] * m31 + lz[q] * m32 + m33
        xa, ya, wa = ex[q] * m00, ex[q] * m10, ex[q] * m30  # the edge along x, in clip x, y, w
        xb, yb, wb = ey[q] * m01, ey[q] * m11, ey[q] * m31
        xc, yc, wc = ez[q] * m02, ez[q] * m12, ez[q] * m32
        x_lo = y_lo = 1.0
        x_hi = y_hi = -1.0
        behind = False
        for k in range(8):
            sx, sy, sw = 0.0, 0.0, 0.0
            if k & 4:
                sx += xa
                sy += ya
                sw += wa
            if k & 2:
                sx += xb
                sy += yb
                sw += wb
            if k & 1:
                sx += xc
                sy += yc
                sw += wc
            w = b3 + sw
            behind |= not (w > 1e-6)
            iw = 1.0 / w
            x, y = (b0 + sx) * iw, (b1 + sy) * iw
            x_lo, x_hi = min(x_lo, x), max(x_hi, x)
            y_lo, y_hi = min(y_lo, y), max(y_hi, y)
        # Clamped to the screen once: clamping each corner first gives the same bounds (both are monotone).
        x_lo, x_hi, y_lo, y_hi = max(x_lo, -1.0), min(x_hi, 1.0), max(y_lo, -1.0), min(y_hi, 1.0)
        sz = full if behind else (x_hi - x_lo) * (y_hi - y_lo) * 0.25 * wd * ht
        out[q] = sz if inside or not cull else 0.0


@jit()
def _offsets(g, m, wd, ht, has_before, was, lim, offset, moved):
    """``project``'s Focus offsets and Motion travel for one camera."""
    v = g.shape[1]
    m00, m01, m02, m03 = m[0, 0], m[0, 1], m[0, 2], m[0, 3]
    m10, m11, m12, m13 = m[1, 0], m[1, 1], m[1, 2], m[1, 3]
    m30, m31, m32, m33 = m[3, 0], m[3, 1], m[3, 2], m[3, 3]
    hw, hh = wd * 0.5, ht * 0.5
    diag = math.sqrt(hw * hw + hh * hh)
    cx, cy, cz = g[9], g[10], g[11]
    for q in range(v):
        # Focus: the centre's distance from the screen centre over the half diagonal.
        px = cx[q] * m00 + cy[q] * m01 + cz[q] * m02 + m03  # (``_centre``'s sums: the centre's clip coordinates)
        py = cx[q] * m10 + cy[q] * m11 + cz[q] * m12 + m13
        pw = cx[q] * m30 + cy[q] * m31 + cz[q] * m32 + m33
        nx, ny = _ndc(px, py, pw, 1.0)
        dx, dy = (nx + 1.0) * 0.5 * wd - hw, (ny + 1.0) * 0.5 * ht - hh
        offset[q] = min(max(math.sqrt(dx * dx + dy * dy) / diag, 0.0), 1.0)
        # Motion: how far the centre (clamped at ±SPEED_LIMIT_NDC) moved on screen since ``before``.
        if has_before:
            ax, ay = _ndc(px, py, pw, lim)
            dx = (ax + 1.0) * 0.5 * wd - (was[0, q] + 1.0) * 0.5 * wd
            dy = (ay + 1.0) * 0.5 * ht - (was[1, q] + 1.0) * 0.5 * ht
            moved[q] = math.sqrt(dx * dx + dy * dy)
        else:
            moved[q] = 0.0


@jit()
def cull_project_many(lo, hi, planes, clips, widths, heights, cam_start, cull, befores, has_before):
    """``cull_any`` and ``project`` for the selections of several sessions over one scene, in one pass.

    Session b's cameras are cam_start[b] .. cam_start[b + 1] − 1 of planes (C, 6, 4), clips (C, 4, 4), widths
    and heights (C,); cull, has_before (B,) bool and befores (B, 4, 4) are ``project``'s per session.
    Returns (rows, row_start, size, offset, moved, out_start): session b's visible rows are
    rows[row_start[b]:row_start[b + 1]] (v_b of them, in order) and its (C_b, v_b) outputs are
    size[out_start[b]:out_start[b + 1]] (and offset, moved) in row-major order — the numbers ``cull_any`` and
    ``project`` give for that session alone, as the same code computes them.
    """
    n, nb = lo.shape[0], cam_start.shape[0] - 1
    visible = np.empty(n, np.bool_)
    row_start = np.zeros(nb + 1, np.int64)
    rows = np.empty(nb * n, np.int64)
    for b in range(nb):
        c0, c1 = cam_start[b], cam_start[b + 1]
        cull_any(lo, hi, planes[c0:c1], visible)
        t = row_start[b]
        for i in range(n):
            if visible[i]:
                rows[t] = i
                t += 1
        row_start[b + 1] = t
    out_start = np.zeros(nb + 1, np.int64)
    for b in range(nb):
        out_start[b + 1] = out_start[b] + (cam_start[b + 1] - cam_start[b]) * (row_start[b + 1] - row_start[b])
    total = out_start[nb]
    size, offset, moved = np.empty(total), np.empty(total), np.empty(total)
    for b in range(nb):
        c0, c1, r0, r1, o0, o1 = cam_start[b], cam_start[b + 1], row_start[b], row_start[b + 1], out_start[b], \
            out_start[b + 1]
        shape = (c1 - c0, r1 - r0)
        project(lo, hi, rows[r0:r1], clips[c0:c1], planes[c0:c1], widths[c0:c1], heights[c0:c1], cull[b],
                befores[b], has_before[b], size[o0:o1].reshape(shape), offset[o0:o1].reshape(shape),
                moved[o0:o1].reshape(shape))
    return rows[: row_start[nb]].copy(), row_start, size, offset, moved, out_start


@jit(inline="always")
def _pow(x, m):
    if m == 1.0:
        return x
    if m == 2.0:
        return x * x
    return x**m


@jit()
def benefit_sum(size, offset, speed, moving, weight, faces, vertices, valid, per_vertex, exponent, n_alg,
                accuracy_mode, original, error, extent, use_size, importance, focus_strength, motion_strength, frame_time, previous,
                level_weight, algorithm_weight, appearance, out):
    """out[i, k] = Σ_j weight[j] · Benefit_j(i, k) over valid options, 0 elsewhere (``benefit.benefit_matrix``).

    size, offset, speed : (C, v) per camera (speed in px/s); an empty ``offset`` (shape (0, 0)) switches
        Focus off, an empty ``importance`` / ``previous`` Importance / Hysteresis
    moving : (C,) bool — Motion on for camera j (its speed was measured)
    faces, vertices : (v, K); valid : (v, K) bool
    per_vertex, exponent : (R,) F&S Samples (vertices, not faces) and m per algorithm; option k uses k % R
    accuracy_mode : ACCURACY_OFF, ACCURACY_FS, ACCURACY_ZACH or ACCURACY_SSE
    original : (v,) Zach's #originalFaces per row (``benefit.original_faces``); empty: each row's most faces
    error, extent : (v, K) geometric error per option, (v,) box diagonal per row — screen-space error
        accuracy (``benefit.projected_error``); empty otherwise
    appearance : (v, K) the accuracy each option's algorithm leaves to a textured representation
        (``benefit.texture_accuracy``); empty (0, 0): nothing is textured
    focus_strength, motion_strength : the factors' slopes (used only when their input is given)
    The factors multiply in ``benefit_matrix``'s order, so the sums are the same to the last bit; what
    does not depend on the camera (hysteresis weights, accuracy below the pixel cap) is computed once per row,
    a camera in which the row covers no pixels adds exactly nothing (with Size on) and is skipped, and only
    the row's valid options (and its previous one) are priced: a view's rows have up to K options, most far fewer.
    """
    nc = size.shape[0]
    v, kk = faces.shape
    use_focus = offset.shape[0] > 0
    use_importance = importance.shape[0] > 0
    use_hysteresis = previous.shape[0] > 0
    use_appearance = appearance.shape[0] > 0
    b = np.empty(kk)
    samples = np.empty(kk)
    acc = np.empty(kk)
    capped = np.empty(n_alg)
    keep = np.ones(kk)
    ks = np.empty(kk, np.int64)
    # The factors of a row at a camera, the same for all its options (Focus, Motion, pixels per metre of the
    # box for screen-space error): computed first, camera by camera in branch-free loops over the rows, which
    # the compiler runs several rows at a time.
    fo_all, mo_all, pm_all = np.ones((nc, v)), np.ones((nc, v)), np.zeros((nc, v))
    for j in range(nc):
        if use_focus:
            for i in range(v):
                fo_all[j, i] = max(1.0 - focus_strength * min(max(offset[j, i], 0.0), 1.0), MIN_FACTOR)
        if moving[j]:
            for i in range(v):
                polygon_px = size[j, i] / max(np.float64(faces[i, 0]), 1.0)
                edge = math.sqrt(max(polygon_px, 1.0))
                mo_all[j, i] = 1.0 / (1.0 + motion_strength * max(speed[j, i], 0.0) * frame_time / edge)
        if accuracy_mode == ACCURACY_SSE:
            for i in range(v):
                pm_all[j, i] = math.sqrt(2.0 * max(size[j, i], 0.0)) / max(extent[i], 1e-12)
    for i in range(v):
        # The options worth pricing: valid ones, and the previous one (hysteresis reads its benefit).
        prev = previous[i] if use_hysteresis else -1
        nk = 0
        for k in range(kk):
            out[i, k] = 0.0
            if valid[i, k] or k == prev:
                ks[nk] = k
                nk += 1
        orig = 0.0
        if accuracy_mode == ACCURACY_ZACH:
            if original.shape[0] > 0:
                orig = np.float64(original[i])
            else:
                orig = np.float64(faces[i, 0])
                for k in range(1, kk):
                    orig = max(orig, np.float64(faces[i, k]))
            orig = max(orig, 1.0)
        elif accuracy_mode == ACCURACY_FS:
            for t in range(nk):
                k = ks[t]
                r = k % n_alg
                samples[k] = np.float64(vertices[i, k]) if per_vertex[r] else np.float64(faces[i, k])
                acc[k] = 1.0 - BASE_ERROR / _pow(max(samples[k], 1.0), exponent[r])
        hysteresis = prev >= 0 and prev < kk
        if hysteresis:
            for t in range(nk):
                k = ks[t]
                d_level = abs(k // n_alg - prev // n_alg)
                d_alg = abs(k % n_alg - prev % n_alg)
                keep[k] = 1.0 / (1.0 + level_weight * d_level + algorithm_weight * d_alg)
        for j in range(nc):
            s = size[j, i]
            if use_size and s == 0.0:
                continue
            cap = max(s, 1.0)
            if accuracy_mode == ACCURACY_FS:  # the accuracy of an option whose Samples exceed the pixels
                for r in range(n_alg):
                    capped[r] = 1.0 - BASE_ERROR / _pow(cap, exponent[r])
            imp = importance[i] if use_importance else 1.0
            fo, mo, per_m = fo_all[j, i], mo_all[j, i], pm_all[j, i]
            for t in range(nk):
                k = ks[t]
                # benefit_matrix's order: Size, Accuracy (the texture's share last), Importance, Focus, Motion.
                x = 1.0
                if use_size:
                    x *= s
                if accuracy_mode == ACCURACY_FS:
                    x *= acc[k] if samples[k] <= cap else capped[k % n_alg]  # Samples never over the pixels
                elif accuracy_mode == ACCURACY_ZACH:
                    f = max(np.float64(faces[i, k]), 1.0)
                    x *= max(1.0, s / orig) / max(1.0, s / f)
                elif accuracy_mode == ACCURACY_SSE:
                    px = max(np.float64(error[i, k]), 0.0) * per_m
                    x *= 1.0 / (1.0 + px)
                if use_appearance:
                    x *= appearance[i, k]
                if use_importance:
                    x *= imp
                if use_focus:
                    x *= fo
                if moving[j]:
                    x *= mo
                b[k] = x
            if hysteresis:
                at_prev = b[prev]
                for t in range(nk):
                    k = ks[t]
                    b[k] = b[k] - (1.0 - keep[k]) * abs(b[k] - at_prev)
            wj = weight[j]
            for t in range(nk):
                k = ks[t]
                if valid[i, k]:
                    out[i, k] += wj * b[k]


@jit()
def tuple_cost(c_poly, c_vert, c_pixel, c_draw, faces, vertices, pixels, alg, valid, out):
    """out[i, k] = max(C1·faces + C2·vertices, C3·pixels) + C0 of option k's algorithm alg[k] for valid options,
    inf elsewhere (``predict_terms`` with one draw each, in its order of operations). pixels: (v,)."""
    v, kk = faces.shape
    for i in range(v):
        p = pixels[i]
        for k in range(kk):
            if valid[i, k]:
                a = alg[k]
                geometry = c_poly[a] * np.float64(faces[i, k]) + c_vert[a] * np.float64(vertices[i, k])
                fill = c_pixel[a] * p
                out[i, k] = (geometry if geometry >= fill else fill) + c_draw * 1.0
            else:
                out[i, k] = np.inf


def compile_all() -> None:
    """Call every kernel once with the argument types the selection passes."""
    clips = np.tile(np.eye(4), (2, 1, 1))
    planes = np.zeros((2, 6, 4))
    rows = np.arange(2, dtype=np.int64)
    wh = np.ones(2)
    size, offset, moved = np.empty((2, 2)), np.empty((2, 2)), np.empty((2, 2))
    for box_dtype in (np.float32, np.float64):  # scene indexes hold float32 boxes, hand-made views float64
        lo, hi = np.zeros((2, 3), box_dtype), np.ones((2, 3), box_dtype)
        cull_any(lo, hi, planes, np.empty(2, bool))
        frozen = clips[0].copy()
        frozen.flags.writeable = False  # ``View.matrix()`` is read-only: numba types it apart
        for flag in (True, False):
            for before in (clips[0], frozen):
                project(lo, hi, rows, clips, planes, wh, wh, flag, before, flag, size, offset, moved)
        cull_project_many(lo, hi, np.concatenate([planes, planes]), np.concatenate([clips, clips]),
                          np.ones(4), np.ones(4), np.array([0, 2, 4], np.int64), np.array([True, False]),
                          np.tile(np.eye(4), (2, 1, 1)), np.array([True, False]))
    out = np.empty((2, 3))
    empty2, empty1 = np.zeros((0, 0)), np.zeros(0)
    valid = np.ones((2, 3), bool)
    pv, ex = np.zeros(1, np.bool_), np.ones(1)
    for f_dtype in (np.int64, np.int32):
        f = np.ones((2, 3), f_dtype)
        tuple_cost(ex, ex, ex, 1.0, f, f, wh, np.zeros(3, np.int64), valid, out)
        for moving in (np.ones(2, bool), np.zeros(2, bool)):
            benefit_sum(size, offset, moved, moving, wh, f, f, valid, pv, ex, 1, ACCURACY_FS, empty1, empty2, empty1,
                        True, wh, 0.3, 0.5, 0.05, rows, 0.1, 0.1, empty2, out)
            benefit_sum(size, empty2, moved, moving, wh, f, f, valid, pv, ex, 1, ACCURACY_ZACH, wh, empty2, empty1,
                        True, empty1, 0.3, 0.5, 0.05, np.zeros(0, np.int64), 0.1, 0.1, empty2, out)
            benefit_sum(size, offset, moved, moving, wh, f, f, valid, pv, ex, 1, ACCURACY_SSE, empty1,
                        np.ones((2, 3)), wh, True, wh, 0.3, 0.5, 0.05, rows, 0.1, 0.1, np.ones((2, 3)), out)
