"""The governor's ladder: what each selected object's neighbouring levels are worth, per second of frame time.

The server's selection is a plan for an interval that starts a round trip
later; the client's frame governor (``client.governor``) corrects it every frame
along this ladder. For each selected mesh the ladder offers up to two steps:
down to the next coarser level the client holds, and up to the next finer level
it holds or is sent ahead (``prefetch``). Each step carries its cost change
(model seconds, from the cost model's F&S terms at the pixels the object covers)
and its value, the benefit change per second (F&S's Value = Benefit ÷ Cost of an
increment), so the client can take decrements of lowest value and increments of
highest value, F&S's incremental step, without knowing the scene.

Pure numpy over the scene's representation arrays: no I/O, no clock.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .benefit import accuracy
from .camera import screen_size

__all__ = ["Ladder", "MAX_VALUE", "MIN_COST", "build_ladder", "prefetch", "step_gain"]

#: A step's cost change is at least this (s): a fill-bound object's levels cost the same, and a value must be finite.
MIN_COST = 1.0e-7
#: Values above this are this (a step whose benefit comes at no measurable cost).
MAX_VALUE = 1.0e12


@dataclass(frozen=True)
class Ladder:
    """The steps of one selection, lowest value first.

    rep : (k,) int64 the selected representation a step starts from
    to  : (k,) int64 where it goes (``rep − 1`` down, ``rep + 1`` up: adjacent levels only)
    cost : (k,) float64 model seconds the step saves (down) or spends (up), > 0
    value : (k,) float64 benefit change per second of the step, ≥ 0
    base : model seconds of the selection as drawn (with the model's fixed per-frame cost)
    """

    rep: np.ndarray
    to: np.ndarray
    cost: np.ndarray
    value: np.ndarray
    base: float

    def __len__(self) -> int:
        return int(self.rep.size)

    @classmethod
    def empty(cls, base: float = 0.0) -> "Ladder":
        z = np.zeros(0)
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), z, z, float(base))


def step_gain(size: np.ndarray, faces_from: np.ndarray, faces_to: np.ndarray) -> np.ndarray:
    """(s,) |F&S benefit change| from ``faces_from`` to ``faces_to`` at ``size`` pixels covered (samples capped at
    the pixels, as the gate and the solvers count them)."""
    cap = np.maximum(size, 1.0)
    return size * np.abs(accuracy(np.minimum(faces_to, cap)) - accuracy(np.minimum(faces_from, cap)))


def build_ladder(reps: np.ndarray, algorithm: np.ndarray | None, cam, cost, *, rep_object: np.ndarray,
                 rep_faces: np.ndarray, rep_vertices: np.ndarray, object_lo: np.ndarray, object_hi: np.ndarray,
                 resident: np.ndarray, eligible: np.ndarray, pixel_scale: float = 1.0) -> Ladder:
    """The ladder of the selection ``reps`` (s,) drawn with ``algorithm`` (s,) or all flat, seen from ``cam``.

    cost : the session's ``FrameCostModel``; resident : (m,) bool what the client holds after this delta
    (adds included); eligible : (m,) bool representations a step may start from or go to (meshes).
    """
    reps = np.asarray(reps, np.int64)
    s, m = reps.size, resident.size
    alg = np.zeros(s, np.int64) if algorithm is None else np.asarray(algorithm, np.int64)
    obj = rep_object[reps]
    size = screen_size(object_lo[obj], object_hi[obj], cam.matrix(), cam.width, cam.height)
    pixels = size * pixel_scale
    here = cost.predict_terms(rep_faces[reps], rep_vertices[reps], pixels, alg, 1.0)
    base = float(here.sum()) + float(cost.overhead)
    down, up = reps - 1, reps + 1
    ok_down = (down >= 0) & eligible[reps]
    ok_down &= rep_object[np.maximum(down, 0)] == obj
    ok_down &= resident[np.maximum(down, 0)] & eligible[np.maximum(down, 0)]
    ok_up = (up < m) & eligible[reps]
    ok_up &= rep_object[np.minimum(up, m - 1)] == obj
    ok_up &= resident[np.minimum(up, m - 1)] & eligible[np.minimum(up, m - 1)]
    cols = []
    for ok, to, sign in ((ok_down, down, -1.0), (ok_up, up, 1.0)):
        i = np.nonzero(ok)[0]
        t = to[i]
        there = cost.predict_terms(rep_faces[t], rep_vertices[t], pixels[i], alg[i], 1.0)
        dc = np.maximum(sign * (there - here[i]), MIN_COST)
        db = step_gain(size[i], rep_faces[reps[i]], rep_faces[t])
        cols.append((reps[i], t, dc, np.minimum(db / dc, MAX_VALUE)))
    rep, to, dc, value = (np.concatenate(c) for c in zip(*cols))
    order = np.argsort(value, kind="stable")
    return Ladder(rep[order], to[order].astype(np.int64), dc[order].astype(np.float64),
                  value[order].astype(np.float64), base)


def prefetch(reps: np.ndarray, cam, *, rep_object: np.ndarray, rep_faces: np.ndarray, rep_bytes: np.ndarray,
             object_lo: np.ndarray, object_hi: np.ndarray, resident: np.ndarray, eligible: np.ndarray,
             left: float) -> np.ndarray:
    """Finer levels to send ahead with the bytes a delta leaves over: for each selected mesh whose next finer
    level the client lacks, that level, most benefit per byte first, while the running total fits ``left``."""
    reps = np.asarray(reps, np.int64)
    m = resident.size
    if reps.size == 0 or left <= 0 or m == 0:
        return np.zeros(0, np.int64)
    up = reps + 1
    upc = np.minimum(up, m - 1)
    ok = (up < m) & eligible[reps] & eligible[upc] & (rep_object[upc] == rep_object[reps]) & ~resident[upc]
    if not ok.any():
        return np.zeros(0, np.int64)
    r, u = reps[ok], up[ok]
    obj = rep_object[r]
    size = screen_size(object_lo[obj], object_hi[obj], cam.matrix(), cam.width, cam.height)
    nbytes = np.maximum(rep_bytes[u], 1).astype(np.float64)
    value = step_gain(size, rep_faces[r], rep_faces[u]) / nbytes
    order = np.argsort(-value, kind="stable")
    fits = np.cumsum(nbytes[order]) <= left
    return np.sort(u[order][fits])
