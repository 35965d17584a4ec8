"""The governor's ladder: what each selected object's neighbouring levels are worth, per vertex drawn.

The server's selection is a plan for an interval that starts a round trip
later; the client's frame governor (``client.governor``) corrects it every frame
along this ladder. For each selected mesh the ladder offers chains of unit steps:
down through the coarser levels the client holds (as far as they are contiguous,
up to ``LADDER_DEPTH``), and up through the finer ones it holds or is sent ahead
(``prefetch``). A step of depth d goes from level L ∓ (d − 1) to L ∓ d; it
carries its cost change (the vertices it adds or removes) and its value, the
benefit change per vertex (F&S's Value = Benefit ÷ Cost of an increment, the
client measuring what a vertex costs), so the client can take decrements of
lowest value and increments of highest value, F&S's incremental step, without
knowing the scene. Chains deeper than one level matter where the plan meets a
machine or a view heavier than the server foresaw: one level down saves a
fraction of an object's cost, the chain to its coarsest held level most of it.

The benefit of a level is the session's accuracy at the pixels the object
covers: the screen-space error of the level's stored geometric error where the
scene has them (as the selection prices them), F&S's samples otherwise.

Pure numpy over the scene's representation arrays: no I/O, no clock.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from proto.messages import LADDER_DEPTH

from .benefit import accuracy, projected_error, screen_error_accuracy
from .camera import screen_size

__all__ = ["Ladder", "LADDER_DEPTH", "MAX_VALUE", "MIN_COST", "build_ladder", "held_chain", "prefetch", "step_gain"]

#: A step changes at least this many vertices (a level may keep its vertex count while it drops faces), so a
#: value is finite.
MIN_COST = 1.0
#: Values above this are this (a step whose benefit comes at no measurable cost).
MAX_VALUE = 1.0e12


@dataclass(frozen=True)
class Ladder:
    """The steps of one selection, lowest value first.

    rep : (k,) int64 the selected representation whose chain a step belongs to
    to  : (k,) int64 the level the step reaches (``rep ∓ d`` for a step of depth d: the steps of one chain are
        contiguous, each one level beyond the one before)
    cost : (k,) float64 vertices the step removes (down) or adds (up), > 0
    value : (k,) float64 benefit change per vertex of the step, ≥ 0
    base : vertices of the selection as drawn
    """

    rep: np.ndarray
    to: np.ndarray
    cost: np.ndarray
    value: np.ndarray
    base: float

    def __len__(self) -> int:
        return int(self.rep.size)

    @property
    def shed(self) -> float:
        """The share of the selection's vertices its steps down can remove: how far the governor reaches."""
        if self.base <= 0:
            return 0.0
        return float(np.clip(self.cost[self.to < self.rep].sum() / self.base, 0.0, 1.0))

    @classmethod
    def empty(cls, base: float = 0.0) -> "Ladder":
        z = np.zeros(0)
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), z, z, float(base))


def step_gain(size: np.ndarray, faces_from: np.ndarray, faces_to: np.ndarray) -> np.ndarray:
    """(s,) |F&S benefit change| from ``faces_from`` to ``faces_to`` at ``size`` pixels covered (samples capped at
    the pixels, as F&S count them)."""
    cap = np.maximum(size, 1.0)
    return size * np.abs(accuracy(np.minimum(faces_to, cap)) - accuracy(np.minimum(faces_from, cap)))


def _worth(x: np.ndarray, size: np.ndarray, extent: np.ndarray, rep_faces: np.ndarray,
           rep_error: np.ndarray | None) -> np.ndarray:
    """(s,) benefit of drawing level ``x`` of objects covering ``size`` pixels: size × the level's accuracy."""
    if rep_error is not None:
        return size * screen_error_accuracy(projected_error(rep_error[x], size, extent))
    return size * accuracy(np.minimum(rep_faces[x], np.maximum(size, 1.0)))


def held_chain(reps: np.ndarray, sign: int, *, rep_object: np.ndarray, resident: np.ndarray, eligible: np.ndarray,
               depth: int = LADDER_DEPTH) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per depth d = 1 … ``depth``: (rows of ``reps`` whose chain reaches d levels that way, the level it
    reaches) — held (``resident``), of the same object, eligible, and contiguous from the selected level."""
    reps = np.asarray(reps, np.int64)
    m = resident.size
    ok = eligible[reps] if reps.size else np.zeros(0, bool)
    obj = rep_object[reps]
    out = []
    for d in range(1, depth + 1):
        to = reps + sign * d
        inside = (to >= 0) & (to < m)
        toc = np.clip(to, 0, max(m - 1, 0))
        ok = ok & inside & (rep_object[toc] == obj) & resident[toc] & eligible[toc]
        rows = np.nonzero(ok)[0]
        if not rows.size:
            break
        out.append((rows, to[rows]))
    return out


def build_ladder(reps: np.ndarray, cam, *, rep_object: np.ndarray, rep_faces: np.ndarray,
                 rep_vertices: np.ndarray, object_lo: np.ndarray, object_hi: np.ndarray, resident: np.ndarray,
                 eligible: np.ndarray, rep_error: np.ndarray | None = None, depth: int = LADDER_DEPTH) -> Ladder:
    """The ladder of the selection ``reps`` (s,) seen from ``cam``.

    resident : (m,) bool what the client holds after this delta (adds included); eligible : (m,) bool
    representations a step may start from or go to (meshes); rep_error : (m,) geometric errors for
    screen-space error accuracy, or None (F&S's samples).

    A step is priced by the vertices it removes or adds, and nothing else: a step changes an object's
    geometry, not its draw or its pixels. What a vertex costs the client's machine — with the frame's fixed
    part — the client measures itself, frame by frame; priced in the cost model's seconds, each delta would
    carry the model's latest estimate, and the client's measure would be off at every switch to a new one.
    """
    reps = np.asarray(reps, np.int64)
    obj = rep_object[reps]
    lo, hi = object_lo[obj], object_hi[obj]
    size = screen_size(lo, hi, cam.matrix(), cam.width, cam.height)
    extent = np.linalg.norm(hi.astype(np.float64) - lo, axis=1)
    here = rep_vertices[reps].astype(np.float64)
    base = float(here.sum())
    worth = _worth(reps, size, extent, rep_faces, rep_error)
    cols = [(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0))]
    for sign in (-1, 1):
        prev_cost, prev_worth = here.copy(), worth.copy()
        for rows, to in held_chain(reps, sign, rep_object=rep_object, resident=resident, eligible=eligible,
                                   depth=depth):
            there = rep_vertices[to].astype(np.float64)
            w = _worth(to, size[rows], extent[rows], rep_faces, rep_error)
            dc = np.maximum(sign * (there - prev_cost[rows]), MIN_COST)
            db = np.abs(w - prev_worth[rows])
            cols.append((reps[rows], to, dc, np.minimum(db / dc, MAX_VALUE)))
            prev_cost[rows], prev_worth[rows] = there, w
    rep, to, dc, value = (np.concatenate(c) for c in zip(*cols))
    order = np.argsort(value, kind="stable")
    return Ladder(rep[order], to[order].astype(np.int64), dc[order].astype(np.float64),
                  value[order].astype(np.float64), base)


def prefetch(reps: np.ndarray, cam, *, rep_object: np.ndarray, rep_faces: np.ndarray, rep_bytes: np.ndarray,
             object_lo: np.ndarray, object_hi: np.ndarray, resident: np.ndarray, eligible: np.ndarray,
             left: float, rep_error: np.ndarray | None = None) -> np.ndarray:
    """Neighbouring levels to send with the bytes a delta leaves over, so the governor has steps to take.

    First the next coarser level of each selected mesh that lacks it, most frame cost saved (faces) per byte
    first: a step down is what holds the frame when the plan is heavier than the machine. Then, with what
    is left, the next finer level, most benefit per byte first (``rep_error``: as ``build_ladder``). Sorted
    ids, their bytes within ``left``.
    """
    reps = np.asarray(reps, np.int64)
    m = resident.size
    if reps.size == 0 or left <= 0 or m == 0:
        return np.zeros(0, np.int64)
    picked, order_key = [], []
    for sign in (-1, 1):
        to = reps + sign
        toc = np.clip(to, 0, m - 1)
        ok = (to >= 0) & (to < m) & eligible[reps] & eligible[toc] & (rep_object[toc] == rep_object[reps])
        ok &= ~resident[toc]
        if not ok.any():
            continue
        r, t = reps[ok], to[ok]
        nbytes = np.maximum(rep_bytes[t], 1).astype(np.float64)
        if sign < 0:
            per_byte = (rep_faces[r] - rep_faces[t]).astype(np.float64) / nbytes
        else:
            obj = rep_object[r]
            lo, hi = object_lo[obj], object_hi[obj]
            size = screen_size(lo, hi, cam.matrix(), cam.width, cam.height)
            extent = np.linalg.norm(hi.astype(np.float64) - lo, axis=1)
            gain = _worth(t, size, extent, rep_faces, rep_error) - _worth(r, size, extent, rep_faces, rep_error)
            per_byte = np.abs(gain) / nbytes
        order = np.argsort(-per_byte, kind="stable")
        picked.append(t[order])
        order_key.append(nbytes[order])
    if not picked:
        return np.zeros(0, np.int64)
    t, nbytes = np.concatenate(picked), np.concatenate(order_key)
    fits = np.cumsum(nbytes) <= left
    return np.unique(t[fits])
