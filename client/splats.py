"""Vegetation as point splats: tree groups drawn at a continuous resolution x (ZMK 2002, §5).

A tree model is a list of splats in prefix order (``server.scene.points``): any
prefix of n points is a coarser model of the tree. A group of ≤ 64 trees gets
one resolution x ∈ [0, 1] per frame, and each of its trees draws the prefix of

    n = clamp(floor(x · model_points + ½), 1, model_points)

points of its model (half-up rounding, so x = ½ of 4096 is exactly 2048). The
cost model is cost(x) = c_splat · N_splats · x + c_tree (N_splats: the group's
points at x = 1). "A group whose budget cannot give every tree one splat draws
only the fraction it can" (ZMK §5.4): when x · N_splats < trees, only

    t = max(1, floor(x · N_splats))

trees draw, one splat each. x = 0 draws nothing (the solver's way of culling
a group); any x > 0 draws at least one tree, because a group the solver kept
should not vanish. The t trees are spread over the group rather than taken from
one corner: they are the t first of the group's arrival order (Morton, from the
server) in van der Corput (bit-reversed) order. Instances are stored sorted by
model and then by that rank, so each (group, model) run's share of the t trees
is a prefix of the run — one draw command still serves it.

GPU layout, three buffers for everything: all models' points (a model's points
contiguous, in prefix order; ``POINT``, 28 bytes), all groups' instances (each
group's sorted by model id, so (group, model) runs are contiguous; ``INSTANCE``,
52 bytes: the 3 × 4 matrix rows and the matrix's scale) and, per frame, the
indirect draw commands with one float per command, the splat's world radius at
that prefix length (read by ``gl_DrawIDARB`` from a storage buffer). A frame is
one ``render_indirect`` with one DrawArraysIndirectCommand per (group, model)
run: count n (or 1), instanceCount, first point of the model, baseInstance = the
run's first instance. The commands are built with numpy from flat per-run
tables — no Python loop over groups per frame. Adds and frees only mark the
tables dirty; they are rebuilt and re-uploaded once, at the next
``set_resolutions`` (uploads are rare, frames are many).

Splat size: the world radius of a prefix of n points is radius_full · √(N / n)
(radius_full: the payload's radius of the full set, ``Points.radius[-1]``; N:
the model's points), so n discs cover the same area as the N: coarser prefixes
still close the crown. Projected with the viewport height and fov_y to a
diameter in pixels and clamped to ``SIZE_RANGE``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import moderngl
import numpy as np

from proto.points import Instances, Points

__all__ = ["SplatLayer", "POINT", "INSTANCE", "SIZE_RANGE", "DRAW_BINDING"]

_SHADERS = Path(__file__).with_name("shaders")

#: Per-point vertex layout: model-space position, unit normal, rgb + pad (normalised bytes). 28 bytes.
POINT = np.dtype([("position", "<f4", 3), ("normal", "<f4", 3), ("color", "u1", 4)])
#: Per-instance layout: rows 0–2 of the model → world matrix and its uniform scale cbrt|det|. 52 bytes.
INSTANCE = np.dtype([("rows", "<f4", (3, 4)), ("scale", "<f4")])
#: gl_PointSize clamp in pixels: at least a pixel, and near splats do not flood the fill rate.
SIZE_RANGE = (1.0, 64.0)
#: Storage-buffer binding of the per-draw radii (splat.vert.glsl).
DRAW_BINDING = 5
# moderngl 5.13 steps through indirect commands 20 bytes at a time even for
# glMultiDrawArraysIndirect (stride 0, i.e. 16 bytes): pad each command to 5 words.
_WORDS = 5
_RANKS = 1 << 21  # > proto.points.MAX_INSTANCES


@dataclass
class _Group:
    """A resident group, kept on the CPU so the instance buffer can be rebuilt."""

    instances: np.ndarray  # (k,) INSTANCE, sorted by model, then by rank
    rank: np.ndarray       # (k,) int64 the instances' van der Corput ranks (a permutation of 0..k−1)
    run_model: np.ndarray  # (r,) int64 model id of each (group, model) run
    run_start: np.ndarray  # (r,) int64 first instance of the run within the group
    run_count: np.ndarray  # (r,) int64 instances in the run


@dataclass
class _Plan:
    """One frame's draws: commands (m, 5) uint32, radius (m,) float32, and what they draw."""

    commands: np.ndarray
    radius: np.ndarray
    splats: int
    trees: int
    missing: int


def _spread_rank(k: int) -> np.ndarray:
    """(k,) int64: each arrival index's position in the van der Corput (bit-reversed) sequence of 0..k−1.

    The t instances of smallest rank are spread evenly over the arrival order;
    the server sends a group's trees in Morton order, so they are spread over the
    group's area too (a partial group is not one corner).
    """
    i = np.arange(k, dtype=np.int64)
    bits = max(1, int(k - 1).bit_length())
    rev = np.zeros(k, np.int64)
    for b in range(bits):
        rev |= ((i >> b) & 1) << (bits - 1 - b)
    rank = np.empty(k, np.int64)
    rank[np.argsort(rev)] = i
    return rank


class SplatLayer:
    """Tree models and tree groups resident on the GPU, drawn as round splats with one multi-draw.

    ctx needs GL ≥ 4.3 with GL_ARB_shader_draw_parameters (llvmpipe: 4.5). Call
    ``set_resolutions`` before the frame (it builds and uploads the draw
    commands) and ``render`` inside it, with the target framebuffer bound and
    the depth test on.
    """

    def __init__(self, ctx: moderngl.Context) -> None:
        self.ctx = ctx
        self.sun: np.ndarray | None = None
        """(3,) world direction towards the sun (the meshes' ``Renderer.sun``), or None: as
        ``client.shading.key_light``, carried with the camera."""
        if ctx.version_code < 430 or "GL_ARB_shader_draw_parameters" not in ctx.extensions:
            raise RuntimeError(
                f"splats need GL ≥ 4.3 with GL_ARB_shader_draw_parameters, got {ctx.version_code}"
            )
        self.program = ctx.program(
            vertex_shader=(_SHADERS / "splat.vert.glsl").read_text(),
            fragment_shader=(_SHADERS / "splat.frag.glsl").read_text(),
        )
        self._points = ctx.buffer(reserve=POINT.itemsize * 64)
        self._instances = ctx.buffer(reserve=INSTANCE.itemsize * 64)
        self._commands = ctx.buffer(reserve=4 * _WORDS * 64)
        self._radius = ctx.buffer(reserve=4 * 64)
        self.vao = ctx.vertex_array(
            self.program,
            [
                (self._points, "3f 3f 4f1", "in_pos", "in_normal", "in_color"),
                (self._instances, "4f 4f 4f 1f/i", "in_row0", "in_row1", "in_row2", "in_scale"),
            ],
        )
        self._models: dict[int, tuple[np.ndarray, float]] = {}  # id → (POINT array, radius_full)
        self._groups: dict[int, _Group] = {}
        self._models_dirty = self._groups_dirty = False
        self._tables: dict[str, np.ndarray] = {}
        self._build_tables()
        self._draws = 0
        self._splats = 0
        self._frame: tuple[np.ndarray, np.ndarray] | None = None  # last set_resolutions, for re-planning
        self._stale = False
        self.missing = 0
        """Draw requests for groups not resident, in total (skipped, never drawn)."""
        self._warm_up()

    def _warm_up(self) -> None:
        """Draw one splat into a scratch target, so the shader's compile at its first draw is not in frame 0."""
        point = np.zeros(1, POINT)
        point["normal"] = (0, 0, 1)
        inst = np.zeros(1, INSTANCE)
        inst["rows"] = np.eye(4, dtype=np.float32)[:3]
        inst["scale"] = 1.0
        self._points.write(point.tobytes())
        self._instances.write(inst.tobytes())
        self._commands.write(np.array([1, 1, 0, 0, 0], np.uint32).tobytes())
        self._radius.write(np.float32(0.1).tobytes())
        self._draws = 1
        color = self.ctx.renderbuffer((4, 4))
        depth = self.ctx.depth_renderbuffer((4, 4))
        fbo = self.ctx.framebuffer(color_attachments=[color], depth_attachment=depth)
        try:
            with self.ctx.scope(fbo, moderngl.DEPTH_TEST):
                fbo.clear(depth=1.0)
                vp = np.eye(4)
                vp[3] = (0, 0, -1, 0)  # a perspective divide; the point sits at the eye + (0, 0, −1)
                self._draw(vp, np.array([0.0, 0.0, 1.0]), (4, 4), 60.0)
            self.ctx.finish()
        finally:
            fbo.release()
            color.release()
            depth.release()
            self._draws = 0
        self._models_dirty = True  # overwrite the scratch data at the next sync

    # ----------------------------------------------------------------- resident data

    def add_model(self, model: int, points: Points) -> None:
        """Make a tree model's prefix-ordered points resident (replacing any with the same id)."""
        model = int(model)
        if model < 0:
            raise ValueError(f"model ids are non-negative, got {model}")
        n = len(points)
        if n == 0:
            raise ValueError(f"model {model} has no points")
        data = np.zeros(n, POINT)
        data["position"] = points.positions
        data["normal"] = points.normals
        data["color"][:, :3] = points.colors
        radius = np.asarray(points.radius, np.float64).reshape(-1)
        if radius.shape != (n,) or not np.isfinite(data["position"]).all() or not np.isfinite(radius).all():
            raise ValueError(f"model {model}: positions and radius must be finite, radius ({n},)")
        self._models[model] = (data, float(radius[-1]))
        self._models_dirty = True

    def has_model(self, model: int) -> bool:
        """Whether ``model`` has been added (groups may only use such models)."""
        return int(model) in self._models

    def add_group(self, rep: int, instances: Instances) -> None:
        """Make a tree group resident (replacing any with the same id).

        instances.model (k,) int, instances.matrix (k, 4, 4) float (model → world;
        row 3 is ignored). Raises ValueError naming the models not yet added.
        """
        model = np.asarray(instances.model).reshape(-1).astype(np.int64)
        matrix = np.asarray(instances.matrix, np.float64)
        k = model.size
        if k == 0 or matrix.shape != (k, 4, 4):
            raise ValueError(f"group {rep}: need k > 0 instances with (k, 4, 4) matrices, got {matrix.shape}")
        if not np.isfinite(matrix[:, :3]).all():
            raise ValueError(f"group {rep}: instance matrices are not finite")
        ids = np.unique(model)
        unknown = [int(m) for m in ids if int(m) not in self._models]
        if unknown:
            raise ValueError(f"group {rep} uses models not added yet: {unknown}")
        rank = _spread_rank(k)
        order = np.lexsort((rank, model))
        model, matrix, rank = model[order], matrix[order], rank[order]
        data = np.zeros(k, INSTANCE)
        data["rows"] = matrix[:, :3]
        data["scale"] = np.cbrt(np.abs(np.linalg.det(matrix[:, :3, :3])))
        start = np.flatnonzero(np.r_[True, model[1:] != model[:-1]])
        self._groups[int(rep)] = _Group(data, rank, model[start], start, np.diff(np.r_[start, k]))
        self._groups_dirty = True

    def free_group(self, rep: int) -> None:
        """Forget a group; unknown ids are ignored."""
        if self._groups.pop(int(rep), None) is not None:
            self._groups_dirty = True

    # ----------------------------------------------------------------- tables

    def _sync(self) -> None:
        """Rebuild the flat tables and re-upload the buffers that changed since the last frame."""
        if not (self._models_dirty or self._groups_dirty):
            return
        if self._models_dirty and self._models:
            data = np.concatenate([self._models[m][0] for m in sorted(self._models)])
            self._upload(self._points, data)
        if self._groups_dirty and self._groups:
            data = np.concatenate([self._groups[r].instances for r in sorted(self._groups)])
            self._upload(self._instances, data)
        self._build_tables()
        self._models_dirty = self._groups_dirty = False
        self._stale = True

    def _build_tables(self) -> None:
        """Per-group and per-run arrays that ``_plan`` indexes with numpy."""
        mids = np.array(sorted(self._models), np.int64)
        m_n = np.array([self._models[m][0].size for m in mids.tolist()], np.int64)
        m_r = np.array([self._models[m][1] for m in mids.tolist()], np.float64)
        m_first = np.cumsum(m_n) - m_n
        reps = np.array(sorted(self._groups), np.int64)
        groups = [self._groups[r] for r in reps.tolist()]
        g_trees = np.array([g.instances.size for g in groups], np.int64)
        g_runs = np.array([g.run_model.size for g in groups], np.int64)
        cat = (lambda a: np.concatenate(a)) if groups else (lambda a: np.zeros(0, np.int64))
        run_model = cat([g.run_model for g in groups])
        run_start = cat([g.run_start for g in groups])
        run_count = cat([g.run_count for g in groups])
        rank = cat([g.rank for g in groups])
        m = np.searchsorted(mids, run_model)  # every run's model is resident (add_group checks)
        run_points = m_n[m]
        g_points = np.add.reduceat(run_points * run_count, np.cumsum(g_runs) - g_runs) if reps.size else run_points
        self._tables = {
            "rep": reps,                                         # (G,) sorted resident group ids
            "g_run0": np.cumsum(g_runs) - g_runs,                # (G,) first run of the group
            "g_runs": g_runs,                                    # (G,) runs of the group
            "g_trees": g_trees,                                  # (G,) T
            "g_points": g_points,                                # (G,) N_splats at x = 1
            "r_first": m_first[m],                               # (R,) first point of the model
            "r_points": run_points,                              # (R,) points of the model
            "r_radius": m_r[m],                                  # (R,) full-set splat radius
            "r_base": np.repeat(np.cumsum(g_trees) - g_trees, g_runs) + run_start,  # (R,) baseInstance
            "r_count": run_count,                                # (R,) instances of the run
            # (K,) run index · 2^21 + rank, ascending: run r's instances of rank < t are a
            # prefix of the run, found for all runs at once by one searchsorted.
            "i_key": np.repeat(np.arange(run_count.size, dtype=np.int64), run_count) * _RANKS + rank,
        }

    @staticmethod
    def _upload(buffer: moderngl.Buffer, data: np.ndarray) -> None:
        if data.nbytes > buffer.size:
            buffer.orphan(max(data.nbytes, 2 * buffer.size))
        buffer.write(np.ascontiguousarray(data).tobytes())

    # ----------------------------------------------------------------- planning

    @staticmethod
    def _validate(reps: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r = np.asarray(reps).reshape(-1)
        xs = np.asarray(x, dtype=np.float64).reshape(-1)
        if r.size and r.dtype.kind not in "iu":
            raise ValueError(f"group ids must be integers, got {r.dtype}")
        if xs.shape != r.shape:
            raise ValueError(f"x must be aligned with reps ({r.size},), got {np.shape(x)}")
        if not np.isfinite(xs).all() or (xs < 0).any() or (xs > 1).any():
            raise ValueError("resolutions x must be finite and in [0, 1]")
        return r.astype(np.int64), xs

    def _plan(self, reps: np.ndarray, x: np.ndarray) -> _Plan:
        """The draw commands for groups ``reps`` (s,) at resolutions ``x`` (s,), all in numpy."""
        tb = self._tables
        pos = np.minimum(np.searchsorted(tb["rep"], reps), max(tb["rep"].size - 1, 0))
        found = (tb["rep"][pos] == reps) if tb["rep"].size else np.zeros(reps.size, bool)
        g, xg = pos[found], x[found]
        nr = tb["g_runs"][g]
        gi = np.repeat(np.arange(g.size), nr)
        r = np.repeat(tb["g_run0"][g] - (np.cumsum(nr) - nr), nr) + np.arange(int(nr.sum()))
        xr = xg[gi]
        n_model, count = tb["r_points"][r], tb["r_count"][r]
        want = xr * tb["g_points"][g][gi]
        trees = tb["g_trees"][g][gi]
        partial = want < trees
        n = np.clip(np.floor(xr * n_model + 0.5).astype(np.int64), 1, n_model)
        drawn = np.maximum(np.floor(want).astype(np.int64), 1)  # trees of a partial group
        base = tb["r_base"][r]
        share = np.searchsorted(tb["i_key"], r * _RANKS + drawn) - base  # run instances of rank < drawn
        splats = np.where(partial, 1, n)
        instances = np.where(xr > 0, np.where(partial, share, count), 0)
        keep = instances > 0
        splats, instances, r = splats[keep], instances[keep], r[keep]
        commands = np.zeros((r.size, _WORDS), np.uint32)
        commands[:, 0] = splats
        commands[:, 1] = instances
        commands[:, 2] = tb["r_first"][r]
        commands[:, 3] = base[keep]
        radius = (tb["r_radius"][r] * np.sqrt(n_model[keep] / splats)).astype(np.float32)
        return _Plan(commands, radius, int((splats * instances).sum()), int(instances.sum()),
                     int((~found).sum()))

    def set_resolutions(self, reps: np.ndarray, x: np.ndarray) -> None:
        """Choose this frame's groups: ``reps`` (s,) int and their resolutions ``x`` (s,) float in [0, 1].

        Builds and uploads the draw commands (call it before the timed frame).
        Groups not resident are skipped and counted in ``missing``. Raises
        ValueError on x outside [0, 1], non-finite or misaligned.
        """
        r, xs = self._validate(reps, x)
        self._sync()
        plan = self._plan(r, xs)
        self.missing += plan.missing
        self._frame = (r, xs)
        self._load(plan)

    def _load(self, plan: _Plan) -> None:
        if plan.commands.size:
            self._upload(self._commands, plan.commands)
            self._upload(self._radius, plan.radius)
        self._draws, self._splats = int(plan.commands.shape[0]), plan.splats
        self._stale = False

    def counts(self, reps: np.ndarray, x: np.ndarray) -> tuple[int, int]:
        """(splats, trees) that ``render`` would draw for groups ``reps`` at resolutions ``x``."""
        r, xs = self._validate(reps, x)
        self._sync()
        plan = self._plan(r, xs)
        return plan.splats, plan.trees

    # ----------------------------------------------------------------- drawing

    def render(self, view_projection: np.ndarray, eye: np.ndarray, viewport: tuple[int, int], fov_y: float) -> int:
        """Draw the groups of the last ``set_resolutions`` into the bound framebuffer; returns splats drawn.

        view_projection : (4, 4) float, camera-relative position (world − eye) → clip
                          space, row-major (``projection_matrix @ view_matrix(0, …)``)
        eye             : (3,) float world-space eye
        viewport        : (width, height) in pixels (the height sets the splat size)
        fov_y           : vertical field of view in degrees, as in ``proto.camera``
        Leaves GL_PROGRAM_POINT_SIZE enabled.
        """
        vp = np.asarray(view_projection, np.float64)
        if vp.shape != (4, 4) or not np.isfinite(vp).all():
            raise ValueError(f"view_projection must be a finite (4, 4) matrix, got {vp.shape}")
        if not 0 < float(fov_y) < 180 or int(viewport[1]) <= 0:
            raise ValueError(f"need 0 < fov_y < 180 degrees and a positive viewport, got {fov_y}, {viewport}")
        self._sync()
        if self._stale and self._frame is not None:  # groups or models changed since set_resolutions
            self._load(self._plan(*self._frame))
        if self._draws == 0:
            return 0
        self._draw(vp, np.asarray(eye, np.float64), viewport, float(fov_y))
        return self._splats

    def _draw(self, vp: np.ndarray, eye: np.ndarray, viewport: tuple[int, int], fov_y: float) -> None:
        # The camera frame from the matrix rows: row 0 ∝ right, row 1 ∝ up, row 3 = forward
        # (perspective: w = −z_eye); an orthographic matrix has forward in −row 2.
        right, up, forward = vp[0, :3], vp[1, :3], vp[3, :3]
        if np.linalg.norm(forward) < 1e-12:
            forward = -vp[2, :3]
        right, up, forward = (v / max(np.linalg.norm(v), 1e-300) for v in (right, up, forward))
        sun = -forward + 0.6 * up + 0.35 * right if self.sun is None else np.asarray(self.sun, np.float64)
        prog = self.program
        prog["u_view_projection"].write(vp.T.astype("f4").tobytes())
        prog["u_eye"].value = tuple(eye)
        prog["u_pixel_scale"].value = float(viewport[1]) / math.tan(math.radians(fov_y) / 2)
        prog["u_size_range"].value = SIZE_RANGE
        prog["u_up"].value = tuple(up)
        prog["u_sun"].value = tuple(sun / np.linalg.norm(sun))
        self._radius.bind_to_storage_buffer(DRAW_BINDING)
        self.ctx.enable(moderngl.PROGRAM_POINT_SIZE)
        self.vao.render_indirect(self._commands, moderngl.POINTS, count=self._draws)

    def release(self) -> None:
        """Release the GL objects (not the context)."""
        self.vao.release()
        for buffer in (self._points, self._instances, self._commands, self._radius):
            buffer.release()
        self.program.release()
        self._models.clear()
        self._groups.clear()
