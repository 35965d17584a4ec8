"""Cost of drawing a representation, and the feedback and fitting that keep it true.

Two models live here.

Zach 2002 (4.2), the online one: render time = c_vertex · vertices. After each
frame the client reports what it drew and how long it took; c_vertex moves to
the measured time per vertex by a weighted average, so the budget holds on the
client's real machine whatever its speed. Fixed per-frame overheads are
absorbed into c_vertex; the loop still converges (the fixed point of
V ← B·V / (a + b·V) is stable while the overhead a is below the budget B).

Funkhouser & Séquin 1993 (section 4), the predictive one:
Cost(O, L, R) = max(C1·polygons + C2·vertices, C3·pixels) + C0 per draw, with
C1, C2, C3 per rendering algorithm R — the geometry stage or the fill stage,
whichever is the bottleneck. ``fit`` estimates the coefficients from measured
frames and keeps a term at zero when the frames do not need it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np
from scipy.optimize import nnls

from .snapshot import dump_fields, load_fields

__all__ = ["CostModel", "FrameCostModel", "FrameTerms", "ALGORITHM_SCALE"]

#: Default C2 per rendering algorithm relative to c_vertex (flat, lit, textured): guesses
#: until ``fit`` measures them; lighting and texturing cost a little more per vertex.
ALGORITHM_SCALE = (1.0, 1.25, 1.5)


#: What a frame report says was drawn per rendering algorithm: (R,) triangles, vertices, pixels, draws.
FrameTerms = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


@runtime_checkable
class FrameCostModel(Protocol):
    """What a session asks of a cost model: fold in measured frames, price a selection, be saved and restored.

    ``CostModel`` (Zach's running c_vertex) and ``cost_online.OnlineCostModel``
    (F&S's terms fitted online) both implement it; the selection prices options
    with ``predict_terms`` and splats with ``splat_cost`` (``options``, ``selection``).
    """

    #: Frames shorter than this (measured and predicted) are light: the session sets a share of its target.
    tail_min_time: float

    @property
    def c_vertex(self) -> float: ...

    @property
    def updates(self) -> int: ...

    @property
    def overhead(self) -> float:
        """Fixed seconds per frame, spent whatever is drawn."""
        ...

    @property
    def chosen(self) -> str:
        """The name of the model in force."""
        ...

    def predict(self, vertices) -> np.ndarray: ...

    def predict_terms(self, faces, vertices, pixels, algorithm=0, draws=1.0) -> np.ndarray:
        """Seconds per (object, level, algorithm) tuple, F&S's terms, without the frame overhead."""
        ...

    def tuple_coefficients(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """``predict_terms``' coefficients now in force: (R,) C1, C2, C3 per algorithm and C0 per draw."""
        ...

    def splat_cost(self, splats) -> np.ndarray:
        """Seconds to draw that many point splats."""
        ...

    def observe_frame(self, time: float, vertices: int, terms: FrameTerms | None = None, splats: int = 0) -> bool:
        """Fold in one measured frame (its per-algorithm ``terms`` when the client reported them)."""
        ...

    def tail_ratio(self, q: float = 0.95, floor: float = 1.0) -> float:
        """The budget's divisor that makes the q-th percentile frame, not the mean one, meet the target (at least
        ``floor``: below 1 it also corrects a model that prices frames too high)."""
        ...

    def report(self) -> dict | None:
        """Which model is in force and why, with its coefficients; None for a model of one coefficient."""
        ...

    def to_state(self) -> dict: ...

    def from_state(self, state) -> None: ...


def _coeffs(value, r: int, name: str) -> np.ndarray:
    a = np.array(value, np.float64).reshape(-1)
    if a.size == 1:
        a = np.full(r, a[0])
    if a.size != r or not (np.isfinite(a).all() and (a >= 0).all()):
        raise ValueError(f"{name} must be {r} finite non-negative coefficients, got {value!r}")
    return a


@dataclass
class CostModel:
    """Seconds to draw, as the online c_vertex (Zach) and as F&S's per-algorithm terms.

    c_vertex : initial guess, seconds per vertex
    alpha    : weight of the newest measurement in the running average
    min_vertices : frames drawing fewer vertices than this say little about c_vertex
    c_poly, c_vert, c_pixel : (R,) C1, C2, C3 per rendering algorithm. ``c_vert`` None means
        c_vertex · ALGORITHM_SCALE[r], following the online feedback until ``fit`` sets it.
    c_draw : C0, seconds per draw call
    tail_min_time : ``FrameCostModel``'s; Zach's average has no tail to leave light frames out of
    """

    c_vertex: float = 2.0e-7
    alpha: float = 0.2
    min_vertices: int = 1000
    updates: int = 0
    algorithms: int = 3
    c_poly: np.ndarray | None = None
    c_vert: np.ndarray | None = None
    c_pixel: np.ndarray | None = None
    c_draw: float = 0.0
    fitted: dict = field(default_factory=dict)
    tail_min_time: float = 0.0

    def __post_init__(self) -> None:
        r = self.algorithms
        if r < 1:
            raise ValueError(f"algorithms must be ≥ 1, got {r}")
        self.c_poly = _coeffs(0.0 if self.c_poly is None else self.c_poly, r, "c_poly")
        self.c_pixel = _coeffs(0.0 if self.c_pixel is None else self.c_pixel, r, "c_pixel")
        if self.c_vert is not None:
            self.c_vert = _coeffs(self.c_vert, r, "c_vert")
        if not (math.isfinite(self.c_draw) and self.c_draw >= 0):
            raise ValueError(f"c_draw must be finite and non-negative, got {self.c_draw}")

    # ------------------------------------------------------------------ Zach: online c_vertex

    def predict(self, vertices: np.ndarray) -> np.ndarray:
        """Seconds to draw representations with ``vertices`` vertices; shape follows the input."""
        return self.c_vertex * np.asarray(vertices, np.float64)

    def splat_cost(self, splats: np.ndarray) -> np.ndarray:
        """Seconds for that many splats: a splat is priced as a vertex (Zach's model has no term of its own)."""
        return self.predict(splats)

    def update(self, time: float, vertices: int) -> bool:
        """Fold in one measured frame; returns whether it was used."""
        if vertices < self.min_vertices or not np.isfinite(time) or time <= 0:
            return False
        measured = time / vertices
        self.c_vertex += self.alpha * (measured - self.c_vertex)
        self.updates += 1
        return True

    def observe_frame(self, time: float, vertices: int, terms: FrameTerms | None = None, splats: int = 0) -> bool:
        """``FrameCostModel.observe_frame``: Zach's feedback reads the frame's time and vertices alone."""
        return self.update(time, vertices)

    def tail_ratio(self, q: float = 0.95, floor: float = 1.0) -> float:
        """``FrameCostModel.tail_ratio``: the mean frame is budgeted, as Zach does."""
        return 1.0

    @property
    def overhead(self) -> float:
        """``FrameCostModel.overhead``: absorbed into c_vertex."""
        return 0.0

    @property
    def chosen(self) -> str:
        return "zach"

    def report(self) -> dict | None:
        return None

    #: The fields a snapshot holds.
    STATE = ("c_vertex", "alpha", "min_vertices", "updates", "algorithms", "c_poly", "c_vert", "c_pixel", "c_draw",
             "fitted")

    def to_state(self) -> dict:
        """Every coefficient as plain data (``from_state`` reads it back)."""
        return {"kind": "zach", **dump_fields(self, self.STATE)}

    def from_state(self, state) -> None:
        """Take in ``to_state``'s data; ValueError (model unchanged) if it is of another kind or does not fit."""
        if not isinstance(state, dict):
            raise ValueError("cost: expected a map")
        if state.get("kind") != "zach":
            raise ValueError(f"cost: the snapshot's model is {state.get('kind')!r}, this server's 'zach'")
        load_fields(self, state, self.STATE, "cost")

    # ------------------------------------------------------------------ F&S: max of terms

    def vertex_coefficients(self) -> np.ndarray:
        """(R,) C2 per algorithm now in force."""
        if self.c_vert is not None:
            return self.c_vert
        scale = np.array([ALGORITHM_SCALE[min(r, len(ALGORITHM_SCALE) - 1)] for r in range(self.algorithms)])
        return self.c_vertex * scale

    def tuple_coefficients(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """(R,) C1, C2, C3 per algorithm and C0 per draw: ``predict_terms``' coefficients."""
        return self.c_poly, self.vertex_coefficients(), self.c_pixel, float(self.c_draw)

    def predict_terms(
        self,
        faces: np.ndarray,
        vertices: np.ndarray,
        pixels: np.ndarray,
        algorithm: np.ndarray | int = 0,
        draws: np.ndarray | float = 1.0,
    ) -> np.ndarray:
        """Seconds per tuple: max(C1[R]·faces + C2[R]·vertices, C3[R]·pixels) + C0·draws.

        All inputs broadcast together, e.g. faces/vertices (n, K), pixels (n, 1) or (n, K),
        algorithm (K,) or (n, K) int in [0, R). Shape of the result: the broadcast shape.
        """
        alg = np.asarray(algorithm, np.int64)
        if alg.size and (alg.min() < 0 or alg.max() >= self.algorithms):
            raise ValueError(f"algorithm index out of range 0..{self.algorithms - 1}")
        geometry = self.c_poly[alg] * np.asarray(faces, np.float64) + self.vertex_coefficients()[alg] * np.asarray(
            vertices, np.float64
        )
        fill = self.c_pixel[alg] * np.asarray(pixels, np.float64)
        return np.maximum(geometry, fill) + self.c_draw * np.asarray(draws, np.float64)

    def fit(
        self,
        faces: np.ndarray,
        vertices: np.ndarray,
        pixels: np.ndarray,
        draws: np.ndarray,
        times: np.ndarray,
        algorithm: int | None = None,
        max_rounds: int = 20,
    ) -> dict:
        """Fit C1, C2, C3 (and C0) to measured frames; sets them on the model and returns the figures.

        faces, vertices, pixels : per-frame sums, (F,) — or (F, R) sums per rendering algorithm
        draws, times : (F,) draw calls and measured seconds per frame
        algorithm : with (F,) sums, the algorithm every frame was drawn with (None: all
            algorithms get the fitted coefficients)

        The frame model is max(geometry, fill) + C0·draws. Frames are split into
        geometry-bound and fill-bound ones; each side is fitted by non-negative least
        squares on relative error, frames re-assigned to the larger predicted term,
        repeated until the split settles (from several initial splits; the best is
        kept). Terms are then dropped one by one while the Bayesian information
        criterion says the frames do not justify them — model no more than the scene needs.
        Returns rms/max relative residual, frames, fill-bound frames, terms kept, coefficients.
        """
        times = np.asarray(times, np.float64).reshape(-1)
        f = times.size
        cols = [np.asarray(a, np.float64) for a in (faces, vertices, pixels)]
        per_alg = cols[0].ndim == 2
        cols = [c.reshape(f, -1) for c in cols]
        r = cols[0].shape[1]
        if per_alg and r != self.algorithms:
            raise ValueError(f"per-algorithm sums need {self.algorithms} columns, got {r}")
        draws = np.asarray(draws, np.float64).reshape(f)
        if f < 2 or not (np.isfinite(times).all() and (times > 0).all()):
            raise ValueError("fit needs at least two frames with finite positive times")
        # Candidate terms: (kind, column index); kind 0 faces, 1 vertices, 2 pixels, 3 draws.
        terms = [(k, j) for k in range(3) for j in range(r)] + [(3, 0)]
        data = {(k, j): cols[k][:, j] for k in range(3) for j in range(r)}
        data[(3, 0)] = draws
        active = [t for t in terms if np.any(data[t] > 0)]

        def bic(rss: float, k: int) -> float:
            return f * math.log(max(rss / f, 1e-300)) + k * math.log(f)

        best = _fit_piecewise(active, data, times, max_rounds)
        score = bic(best["rss"], len(best["terms"]))
        while len(best["terms"]) > 1:
            trials = []
            for t in best["terms"]:
                sub = _fit_piecewise([u for u in best["terms"] if u != t], data, times, max_rounds)
                trials.append((bic(sub["rss"], len(sub["terms"])), sub))
            s, sub = min(trials, key=lambda p: p[0])
            if s >= score:
                break
            best, score = sub, s

        coef = best["coef"]
        c1 = np.array([coef.get((0, j), 0.0) for j in range(r)])
        c2 = np.array([coef.get((1, j), 0.0) for j in range(r)])
        c3 = np.array([coef.get((2, j), 0.0) for j in range(r)])
        if per_alg:
            self.c_poly, self.c_vert, self.c_pixel = c1, c2, c3
        else:
            c_vert = self.vertex_coefficients().copy()
            targets = range(self.algorithms) if algorithm is None else [int(algorithm)]
            for a in targets:
                self.c_poly[a], c_vert[a], self.c_pixel[a] = c1[0], c2[0], c3[0]
            self.c_vert = c_vert
        self.c_draw = float(coef.get((3, 0), 0.0))
        names = {0: "c_poly", 1: "c_vert", 2: "c_pixel", 3: "c_draw"}
        self.fitted = {
            "frames": f,
            "fill_bound": int(best["fill"].sum()),
            "rms_relative": math.sqrt(best["rss"] / f),
            "max_relative": float(np.abs(best["rel"]).max()),
            "rounds": best["rounds"],
            "terms": sorted(names[k] + (f"[{j}]" if k < 3 else "") for k, j in best["terms"]),
            "c_poly": self.c_poly.tolist(),
            "c_vert": self.c_vert.tolist(),
            "c_pixel": self.c_pixel.tolist(),
            "c_draw": self.c_draw,
        }
        return dict(self.fitted)


def _nnls_rel(columns: list[np.ndarray], times: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Non-negative least squares of relative error on the chosen frames; columns scaled for conditioning."""
    if not columns or not rows.any():
        return np.zeros(len(columns))
    a = np.stack([c[rows] / times[rows] for c in columns], axis=1)
    norm = np.linalg.norm(a, axis=0)
    norm = np.where(norm > 0, norm, 1.0)
    x, _ = nnls(a / norm, np.ones(int(rows.sum())))
    return x / norm


def _fit_piecewise(active: list, data: dict, times: np.ndarray, max_rounds: int) -> dict:
    """Best fit of max(geometry, fill) + C0·draws with the given terms (see ``CostModel.fit``)."""
    geo_t = [t for t in active if t[0] in (0, 1)]
    fill_t = [t for t in active if t[0] == 2]
    draw_t = [t for t in active if t[0] == 3]
    f = times.size

    def evaluate(cg, cf, cd):
        g = sum((c * data[t] for c, t in zip(cg, geo_t)), np.zeros(f))
        p = sum((c * data[t] for c, t in zip(cf, fill_t)), np.zeros(f))
        d = sum((c * data[t] for c, t in zip(cd, draw_t)), np.zeros(f))
        return g, p, d

    def run(fill: np.ndarray):
        rounds = 0
        cg = np.zeros(len(geo_t))
        cf = np.zeros(len(fill_t))
        cd = np.zeros(len(draw_t))
        for rounds in range(1, max_rounds + 1):
            # C0 is shared by both sides: fit it jointly, the side's own terms masked per frame.
            cols = [np.where(~fill, data[t], 0.0) for t in geo_t] + [np.where(fill, data[t], 0.0) for t in fill_t]
            cols += [data[t] for t in draw_t]
            x = _nnls_rel(cols, times, np.ones(f, bool))
            cg, cf, cd = x[: len(geo_t)], x[len(geo_t) : len(geo_t) + len(fill_t)], x[len(geo_t) + len(fill_t) :]
            g, p, _ = evaluate(cg, cf, cd)
            new = p > g
            if (new == fill).all():
                break
            fill = new
        g, p, d = evaluate(cg, cf, cd)
        rel = (np.maximum(g, p) + d) / times - 1.0
        return {"rss": float(rel @ rel), "rel": rel, "fill": p > g, "rounds": rounds,
                "coef": dict(zip(geo_t + fill_t + draw_t, np.concatenate([cg, cf, cd]).tolist()))}

    starts = [np.zeros(f, bool)]
    if fill_t and geo_t:
        # A frame is fill-bound when its pixels are many for its geometry: try splits on that ratio.
        g0, _, _ = evaluate(_nnls_rel([data[t] for t in geo_t], times, np.ones(f, bool)), [], [])
        p0 = sum((data[t] for t in fill_t), np.zeros(f))
        ratio = p0 / np.maximum(g0, 1e-300)
        starts += [ratio > q for q in np.unique(np.quantile(ratio, np.linspace(0.0, 0.9, 10)))]
        starts.append(np.ones(f, bool))
    elif fill_t:
        starts = [np.ones(f, bool)]
    best = min((run(s.copy()) for s in starts), key=lambda b: b["rss"])
    # Terms the fit left at zero are not kept: they do not count towards the model's size.
    best["terms"] = [t for t in active if best["coef"].get(t, 0.0) > 0]
    return best
