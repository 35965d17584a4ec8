"""What a delta may carry over this session's link: benefit gained per byte, within the bytes that arrive in time.

A selection names the representation each object should show; a representation
the client lacks is only worth counting on if its bytes reach the client before
the interval it is drawn in. The session gives each delta a byte budget — the
link's measured bandwidth times τ (what the link carries between two deltas),
less what is still in flight — and ``gate`` decides, for the objects whose
choice needs bytes, which are sent: the largest benefit gained per byte first
(a greedy knapsack over bytes, as F&S's is over seconds). An object left out is
drawn with its best resident ancestor — the finest coarser level the client
already holds — or not at all, which costs less than what was chosen, so the
frame-time budget still holds.

Pure numpy over the scene's representation arrays: no I/O, no clock.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..select.benefit import accuracy
from ..select.camera import screen_size

__all__ = ["Gate", "Gated", "realise_bytes", "resident_fallback", "gain", "gate", "through_gate"]


def realise_bytes(reps: np.ndarray, previous: np.ndarray, rep_first: np.ndarray, rep_bytes: np.ndarray,
                  resident: np.ndarray) -> np.ndarray:
    """(s,) bytes the client still lacks to show ``reps``: every non-resident level between the level drawn
    before (``previous``, −1 if none) and the chosen one, inclusive — a geomorph passes through them."""
    reps = np.asarray(reps, np.int64)
    lacking = np.where(resident, 0, rep_bytes).astype(np.int64)
    prefix = np.concatenate([[0], np.cumsum(lacking)])
    first = np.asarray(rep_first, np.int64)
    prev = np.where(np.asarray(previous, np.int64) >= 0, previous, reps)
    lo = np.minimum(prev, reps)
    hi = np.maximum(prev, reps)
    lo = np.maximum(lo, first)  # never another object's chain
    return prefix[hi + 1] - prefix[lo]


def resident_fallback(reps: np.ndarray, rep_first: np.ndarray, resident: np.ndarray) -> np.ndarray:
    """(s,) the finest resident level of each rep's object coarser than it (its best resident ancestor in the
    chain), or −1 where the client holds none. One running maximum over the whole rep array."""
    reps = np.asarray(reps, np.int64)
    held = np.where(resident, np.arange(resident.size, dtype=np.int64), -1)
    last = np.maximum.accumulate(held) if held.size else held
    below = reps - 1
    cand = np.where(below >= 0, last[np.maximum(below, 0)], -1)
    return np.where(cand >= np.asarray(rep_first, np.int64), cand, -1)


def gain(size: np.ndarray, faces_to: np.ndarray, faces_from: np.ndarray) -> np.ndarray:
    """(s,) F&S benefit gained by showing ``faces_to`` instead of ``faces_from`` (0: nothing) on ``size`` pixels
    covered: pixels × the rise in accuracy (1 − 0.5/faces, capped at the pixels as F&S cap Samples)."""
    cap = np.maximum(size, 1.0)
    acc_to = accuracy(np.minimum(faces_to, cap))
    acc_from = np.where(np.asarray(faces_from) > 0, accuracy(np.minimum(faces_from, cap)), 0.0)
    return size * np.maximum(acc_to - acc_from, 0.0)


@dataclass(frozen=True)
class Gate:
    """The gate's decision for the objects whose choice needs bytes.

    send : (s,) bool — the object's choice is sent (and drawn) now
    order : (s,) int — indices into the inputs, best benefit per byte first
    bytes : total bytes of the sent choices
    """

    send: np.ndarray
    order: np.ndarray
    bytes: int


def gate(gains: np.ndarray, nbytes: np.ndarray, budget: float, at_least_one: bool = True,
         requires: np.ndarray | None = None) -> Gate:
    """Send the increments with the most benefit per byte while their running total fits ``budget``.

    The greedy walk skips an increment too large for what is left and goes on
    with smaller ones (a knapsack fill). ``requires`` (−1: none) names the
    increment each one builds on — an object's full choice on top of its coarse
    stand-in — and is only sent after it. ``at_least_one``: the best goes even
    if it alone exceeds the budget — with nothing in flight, a large
    representation must not wait for ever.
    """
    gains = np.asarray(gains, np.float64)
    nbytes = np.asarray(nbytes, np.int64)
    s = gains.size
    if s == 0:
        return Gate(np.zeros(0, bool), np.zeros(0, np.int64), 0)
    req = np.full(s, -1, np.int64) if requires is None else np.asarray(requires, np.int64)
    value = gains / np.maximum(nbytes, 1)  # benefit per byte, as the solvers' value is benefit per second
    depth = (req >= 0).astype(np.int64)  # a stand-in before what builds on it, at equal value
    order = np.lexsort((nbytes, depth, -value))
    sizes = nbytes[order]
    send = np.zeros(s, bool)
    prefix = order[np.cumsum(sizes) <= budget]
    send[prefix] = True
    left = budget - float(nbytes[send].sum())
    for _ in range(6):  # vectorised fill rounds: what still fits, in value order, once its base is sent
        base_ok = (req < 0) | send[np.maximum(req, 0)]
        open_ = ~send[order] & (sizes <= left) & base_ok[order]
        if not open_.any():
            break
        idx = order[open_]
        take = idx[np.cumsum(nbytes[idx]) <= left]
        if take.size == 0:
            take = idx[:1]
        send[take] = True
        left -= float(nbytes[take].sum())
    # An increment whose base did not go cannot go either.
    send &= (req < 0) | send[np.maximum(req, 0)]
    if at_least_one and not send.any():
        send[order[(req[order] < 0)][0] if (req < 0).any() else order[0]] = True
    return Gate(send, order, int(nbytes[send].sum()))


@dataclass(frozen=True)
class Gated:
    """A selection as the link allows it.

    reps, algorithm : (s',) the representations drawn (and their rendering algorithm, or None)
    rank : (n_objects,) int64 — each object's place in the send order (best value first), or None when
        nothing needed bytes
    stats : the gate's figures for ``last_gate`` (budget, lacking, deferred, fallback, stand_in, bytes)
    deferred, fallbacks : choices left unsent, and those of them drawn with a coarser resident level
    """

    reps: np.ndarray
    algorithm: np.ndarray | None
    rank: np.ndarray | None
    stats: dict
    deferred: int = 0
    fallbacks: int = 0


def through_gate(reps: np.ndarray, algorithm: np.ndarray | None, cam, table, resident: np.ndarray,
                 previous: np.ndarray, budget: float, in_flight: int) -> Gated:
    """The selection as the link allows it.

    reps : (s,) int64 the selection; algorithm : (s,) its rendering algorithm, or None
    cam : the view the benefit is measured in (``camera.View``)
    table : the scene's ``SceneTable``; resident : (m,) bool what the client holds
    previous : (n_objects,) int64 the rep each object drew in the last delta, −1 none
    budget : bytes this delta's new geometry may take; in_flight : bytes still on their way

    Each object whose choice needs bytes offers two increments over its best
    resident ancestor: a coarse stand-in (the next level up from what is held)
    and the full choice, merged into one where the full choice has the higher
    value (F&S's concave hull). The gate sends those of highest value within the
    byte budget; an object whose choice does not go is drawn with what it got,
    or what it held, or not at all — never costlier than chosen.
    """
    lacking = ~resident[reps]
    stats = {"budget": budget, "lacking": int(lacking.sum()), "deferred": 0, "fallback": 0, "stand_in": 0,
             "bytes": 0}
    if not lacking.any():
        return Gated(reps, algorithm, None, stats)
    idx = np.nonzero(lacking)[0]
    r = reps[idx]
    k = r.size
    obj = table.rep_object[r]
    first = table.rep_first_of[r]
    prev = previous[obj]
    fallback = resident_fallback(r, first, resident)
    coarse = np.where(fallback >= 0, fallback + 1, first)  # the next level up from what is held
    nb_full = realise_bytes(r, prev, first, table.rep_bytes, resident)
    nb_coarse = realise_bytes(coarse, prev, first, table.rep_bytes, resident)
    faces = table.rep_faces
    held_faces = np.where(fallback >= 0, faces[np.maximum(fallback, 0)], 0)
    size = screen_size(table.object_lo[obj], table.object_hi[obj], cam.matrix(), cam.width, cam.height)
    g_full = gain(size, faces[r], held_faces)
    g_coarse = gain(size, faces[coarse], held_faces)
    # Two increments where the stand-in is a real step of at least the full choice's value; else the full one.
    two = (coarse < r) & (g_coarse * np.maximum(nb_full, 1) >= (g_full - g_coarse) * np.maximum(nb_coarse, 1))
    n2 = int(two.sum())
    gains = np.concatenate([np.where(two, g_full - g_coarse, g_full), g_coarse[two]])
    sizes = np.concatenate([nb_full, nb_coarse[two]])
    requires = np.full(k + n2, -1, np.int64)
    requires[np.nonzero(two)[0]] = k + np.arange(n2)  # the full choice builds on its stand-in
    decision = gate(gains, sizes, budget, at_least_one=in_flight == 0, requires=requires)
    full_sent = decision.send[:k]
    coarse_sent = np.zeros(k, bool)
    coarse_sent[np.nonzero(two)[0]] = decision.send[k:]
    shown = np.where(full_sent, r, np.where(coarse_sent, coarse, fallback))
    # Send order, per object: by its first increment in the gate's value order.
    pos = np.empty(k + n2, np.int64)
    pos[decision.order] = np.arange(k + n2)
    first_pos = pos[:k].copy()
    first_pos[np.nonzero(two)[0]] = pos[k:]
    rank = np.full(previous.size, k + n2, np.int64)
    rank[obj] = first_pos
    out = reps.copy()
    out[idx] = shown
    keep = out >= 0
    held_back = ~full_sent
    deferred, fallbacks = int(held_back.sum()), int((held_back & (shown >= 0)).sum())
    stats.update(deferred=deferred, fallback=fallbacks, stand_in=int(coarse_sent[held_back].sum()),
                 bytes=decision.bytes)
    return Gated(out[keep], None if algorithm is None else np.asarray(algorithm)[keep], rank, stats,
                 deferred, fallbacks)
