"""The server's copy of what one client's cache holds, kept within the client's budget.

Every delta adds representations to the client's cache and drops others; the
mirror applies the same changes on the server side, so the next selection knows
what need not be sent again. It keeps the held count, bytes and order-free
digest (``proto.manifest``) incrementally, and a record of each delta's
outcome until its ack arrives. An ack names what the client refused (those
leave the mirror, and the records of the deltas sent since) and, from a client
that reports its cache, the held count, bytes and digest after that delta: a
mismatch means the two sides diverged beyond repair by bookkeeping, and the
next delta resyncs (drops everything ever sent and restarts the mirror).

When what a delta needs exceeds the budget it is sent in priority order as far
as the budget allows; least recently selected representations are evicted to
make room. The client never receives more than it can keep.
"""

from __future__ import annotations

import logging
import zlib
from dataclasses import dataclass

import numpy as np

from proto.manifest import digest
from proto.messages import Ack

from ..select import kernels
from .table import SceneTable

__all__ = ["CacheMirror", "expand"]

log = logging.getLogger("walkstream.session")


@dataclass
class _Sent:
    """The mirror right after one delta (what its ack must report), and what that delta added and dropped."""

    held: int
    bytes: int
    digest: int
    add: np.ndarray
    drop: np.ndarray

    def remove(self, reps: np.ndarray, rep_bytes: np.ndarray, terms: np.ndarray) -> None:
        """Take refused reps out of this record (they were counted as held)."""
        self.held -= int(reps.size)
        self.bytes -= int(rep_bytes[reps].sum())
        self.digest ^= int(np.bitwise_xor.reduce(terms[reps]))


class CacheMirror:
    """What one client holds of one scene, as the server follows it.

    resident : (m,) bool — held now; sent : (m,) bool — ever sent this session (what a resync drops)
    last_used : (m,) int64 — the seq of the last delta that selected or needed each rep (eviction order)
    held : [count, bytes, digest] of ``resident``, kept incrementally
    budget : the most bytes the client's cache holds
    name : the session's id, for the log
    """

    #: The counters a snapshot holds (among the session's fields), by their snapshot names.
    COUNTERS = {"evicted": "evicted", "over_budget": "over_budget", "refused": "refused",
                "mirror_checks": "checks", "mirror_mismatch": "mismatch", "resyncs": "resyncs"}

    def __init__(self, table: SceneTable | None, budget: int, name: str = "") -> None:
        m = 0 if table is None else table.n_reps
        self.table = table
        self.budget = int(budget)
        self.name = name
        self.resident = np.zeros(m, dtype=bool)
        self.sent = np.zeros(m, dtype=bool)
        self.last_used = np.full(m, -1, dtype=np.int64)
        self.held = [0, 0, 0]
        self.models_sent = False  # the scene's tree models went with the first tree group
        self.resync = False  # the next delta drops everything and restarts the mirror
        self._records: dict[int, _Sent] = {}  # seq → the mirror right after that delta, until acked
        self._epoch = 0  # acks of seqs before this predate the last resync
        self._acked = 0  # the last delta acked
        self.evicted = 0  # reps dropped to keep within the budget
        self.over_budget = 0  # needed reps left unsent for want of budget, summed over deltas
        self.refused = 0  # reps the client refused (acks' ``rejected``)
        self.checks = 0  # acks whose held/held_bytes/digest were compared with the mirror
        self.mismatch = 0  # ... and did not match (each triggers a resync)
        self.resyncs = 0  # deltas that dropped everything and restarted the mirror empty
        self._planned = 0  # plans so far (what ``to_state``'s packed arrays were packed after)
        self._packed: tuple | None = None

    # ------------------------------------------------------------------ the client's word

    def adopt(self, held: np.ndarray) -> None:
        """Take what the client says it holds (a hello's ``held``) as the mirror: nothing of it is sent again."""
        resident = np.zeros(self.resident.size, bool)
        resident[held] = True
        self.resident, self.sent, self.resync = resident, resident.copy(), False
        self._planned += 1
        self.models_sent = bool(self.table.rep_trees[held].any()) or self.models_sent
        self.recount()

    def restart(self, seq: int) -> None:
        """A resumed session restarts its pipeline at ``seq``: acks of the deltas before are stale."""
        self._acked, self._epoch = seq, seq + 1

    def recount(self) -> None:
        ids = np.flatnonzero(self.resident)
        self.held = [int(ids.size), int(self.table.rep_bytes[ids].sum()), digest(ids)]

    # ------------------------------------------------------------------ deltas

    def plan(self, selected: np.ndarray, needed: np.ndarray, seq: int, ranges=None) -> tuple[np.ndarray, np.ndarray]:
        """Bring the mirror to what delta ``seq`` needs, within the budget; returns (reps to add, reps to drop).

        selected : reps the selection draws (meshes, drawn tree groups) — first in line when not all fits
        needed : every rep the schedule draws from its window on (ramp intermediates, morph sources, …)
        ranges : (key, lo, hi) — more of those, as each object key's level range (``expand``)

        Once the kernels are ready the expansion and the whole update are one compiled pass
        (``kernels.delta.plan``); the numpy steps below are its reference.

        When what is needed alone exceeds the budget, it is sent in priority
        order (the selection before the rest, coarse before fine, small before
        large so the most objects show) as far as the budget allows and the rest
        counted in ``over_budget``.
        """
        rep_bytes, rep_level = self.table.rep_bytes, self.table.rep_level
        selected, needed = np.asarray(selected, np.int64), np.asarray(needed, np.int64)
        self._planned += 1
        ready = kernels.compiled()
        if ready is not None:
            return self._plan_compiled(ready.delta.plan, selected, needed, seq, ranges)
        if ranges is not None:
            needed = np.concatenate([expand(*ranges), needed])
        want = np.union1d(needed, selected).astype(np.int64)
        later = ~np.isin(want, selected)
        want = want[np.lexsort((rep_bytes[want], rep_level[want], later))]
        keep = want
        sizes = rep_bytes[want]
        if int(sizes.sum()) > self.budget:
            keep = want[: int(np.searchsorted(np.cumsum(sizes), self.budget, side="right"))]
        if self.resync:  # the client's holdings are unknown: forget them, send afresh what is kept
            self._mark(np.nonzero(self.resident)[0], False)
        new = keep[~self.resident[keep]]
        self._mark(new, True)
        self.sent[new] = True
        self.last_used[want] = seq
        drop = self._evict(keep)
        if self.resync:
            # Everything the client may hold but what this delta re-sends (an add and a drop of one rep
            # in one delta would leave it dropped).
            drop = np.nonzero(self.sent & ~self.resident)[0]
            self.resync, self._epoch = False, seq
            self.resyncs += 1
        self.over_budget += int((~self.resident[want]).sum())
        self._records[seq] = _Sent(*self.held, add=new, drop=drop)
        if len(self._records) > 256:  # a client that stopped acking must not grow this without bound
            self._records.pop(min(self._records))
        return new, drop

    def _plan_compiled(self, kernel, selected, needed, seq, ranges) -> tuple[np.ndarray, np.ndarray]:
        key, lo, hi = ranges if ranges is not None else (np.zeros(0, np.int64), np.zeros(0), np.zeros(0))
        t = self.table
        new, drop, d_count, d_bytes, d_digest, evicted, over = kernel(
            selected, np.asarray(key, np.int64), np.asarray(lo, np.float64), np.asarray(hi, np.float64), needed,
            t.rep_bytes, t.rep_level, t.rep_mix, self.budget, self.resident, self.sent, self.last_used, seq,
            self.resync, self.held[1])
        self.held[0] += int(d_count)
        self.held[1] += int(d_bytes)
        self.held[2] ^= int(d_digest)
        self.evicted += int(evicted)
        if self.resync:
            self.resync, self._epoch = False, seq
            self.resyncs += 1
        self.over_budget += int(over)
        self._records[seq] = _Sent(*self.held, add=new, drop=drop)
        if len(self._records) > 256:
            self._records.pop(min(self._records))
        return new, drop

    def _evict(self, keep: np.ndarray) -> np.ndarray:
        """Drop least recently selected representations (never ``keep``) until the mirror fits the budget."""
        total = self.held[1]
        if total <= self.budget:
            return np.zeros(0, np.int64)
        held = self.resident.copy()
        held[keep] = False
        candidates = np.nonzero(held)[0]
        candidates = candidates[np.argsort(self.last_used[candidates], kind="stable")]
        freed = np.cumsum(self.table.rep_bytes[candidates])
        n = min(int(np.searchsorted(freed, total - self.budget)) + 1, candidates.size)
        drop = candidates[:n]
        self._mark(drop, False)
        self.evicted += int(drop.size)
        return drop

    def _mark(self, reps: np.ndarray, held: bool) -> None:
        """Set reps (each currently the opposite) held or not, updating count, bytes and digest."""
        if reps.size == 0:
            return
        sign = 1 if held else -1
        self.resident[reps] = held
        self.held[0] += sign * int(reps.size)
        self.held[1] += sign * int(self.table.rep_bytes[reps].sum())
        self.held[2] ^= int(np.bitwise_xor.reduce(self.table.rep_mix[reps]))

    # ------------------------------------------------------------------ acks

    def on_ack(self, ack: Ack, seq: int) -> None:
        """Follow the client's refusals in the ack of a delta (``seq``: the last one sent), then check the mirror
        against what the client says it holds.

        A refused add stays out of the mirror — now, and in the records of the
        deltas sent since (unless one of them dropped it), so later acks compare
        exactly. A mismatch makes the next delta resync.
        """
        if not self._acked < ack.seq <= seq:
            return  # never sent, or a repeat (acks come in order): nothing to follow
        self._acked = ack.seq
        record = self._records.pop(ack.seq, None)
        if record is None:
            # From before the last resync: nothing to follow. A record lost to pruning (a client that left
            # hundreds of deltas unacked), though, may hide refusals: resync rather than trust the mirror.
            if ack.rejected and ack.seq >= self._epoch and not self.resync:
                log.warning("session %s: refusals in an ack of delta %d the mirror no longer tracks; resyncing",
                            self.name, ack.seq)
                self._begin_resync(seq)
            return
        for s in [s for s in self._records if s < ack.seq]:
            del self._records[s]  # acks come in order: those will not come
        rep_bytes, terms = self.table.rep_bytes, self.table.rep_mix
        rejected = np.unique(np.asarray(ack.rejected, np.int64))
        alive = rejected[np.isin(rejected, record.add)]  # only this delta's adds can have been refused
        if alive.size:
            self.refused += int(alive.size)
            record.remove(alive, rep_bytes, terms)
            for s in sorted(self._records):
                alive = alive[~np.isin(alive, self._records[s].drop)]  # a later drop ended it anyway
                if not alive.size:
                    break
                self._records[s].remove(alive, rep_bytes, terms)
            self._mark(alive, False)
        if ack.held < 0:
            return  # a client that does not report what it holds: nothing to check
        self.checks += 1
        if (ack.held, ack.held_bytes, ack.digest) != (record.held, record.bytes, record.digest):
            self.mismatch += 1
            log.warning("session %s: after delta %d the client holds %d reps, %d bytes (digest %016x); the mirror "
                        "says %d, %d (%016x); resyncing", self.name, ack.seq, ack.held, ack.held_bytes, ack.digest,
                        record.held, record.bytes, record.digest)
            self._begin_resync(seq)

    def _begin_resync(self, seq: int) -> None:
        """Make the next delta drop everything ever sent and restart the mirror; acks until then are stale."""
        self.resync = True
        self._records.clear()
        self._epoch = seq + 1

    # ------------------------------------------------------------------ snapshot

    def to_state(self) -> dict:
        """The mirror as plain data: bitsets, the last use of each held rep, totals and flags.

        A session saves far more often than its mirror changes (acks, every quarter second): the packed arrays
        are kept until it does. Every change of the held set moves the totals' digest; the sent set and the
        last uses move only with a delta's plan."""
        key = (tuple(self.held), self._planned)
        if self._packed is None or self._packed[0] != key:
            resident = self.resident
            self._packed = (key, np.packbits(resident).tobytes(), np.packbits(self.sent).tobytes(),
                            zlib.compress(self.last_used[resident].astype("<i4").tobytes(), 1))  # runs of equal seqs
        _, resident_bits, sent_bits, used = self._packed
        return {
            "resident": resident_bits,
            "sent": sent_bits,
            "used": used,
            "held": [int(x) for x in self.held],
            "models_sent": bool(self.models_sent),
            "resync": bool(self.resync),
        }

    def counters(self) -> dict:
        """The mirror's counters by their snapshot names (the session's fields hold them)."""
        return {key: int(getattr(self, attr)) for key, attr in self.COUNTERS.items()}

    @classmethod
    def from_state(cls, state, counters, table: SceneTable, budget: int, name: str = "") -> "CacheMirror":
        """A mirror of ``table``'s scene from ``to_state``'s data and ``counters``' (the snapshot's fields),
        checked: bitsets of the scene's size, totals that add up; ValueError if not."""
        if not isinstance(state, dict):
            raise ValueError("the snapshot has no mirror")
        m = table.n_reps

        def bits(key: str) -> np.ndarray:
            b = state.get(key)
            if not isinstance(b, bytes) or len(b) != (m + 7) // 8:
                raise ValueError(f"mirror.{key}: expected a bitset of {m} representations")
            flags = np.unpackbits(np.frombuffer(b, np.uint8))
            if flags[m:].any():
                raise ValueError(f"mirror.{key}: bits beyond the scene's representations")
            return flags[:m].astype(bool)

        resident, sent = bits("resident"), bits("sent")
        ids = np.flatnonzero(resident)
        try:
            inflate = zlib.decompressobj()
            used = inflate.decompress(state.get("used"), 4 * ids.size + 1)
        except (TypeError, zlib.error):
            used = b""
        if len(used) != 4 * ids.size or not inflate.eof:
            raise ValueError("mirror.used: expected one last use per held representation")
        held = state.get("held")
        if held != [int(ids.size), int(table.rep_bytes[ids].sum()), digest(ids)]:
            raise ValueError("mirror.held: the count, bytes and digest do not match the bitset")
        flags = (state.get("models_sent"), state.get("resync"))
        if not all(isinstance(f, bool) for f in flags):
            raise ValueError("mirror: models_sent and resync are booleans")
        if not isinstance(counters, dict):
            raise ValueError("session: expected a map")
        mirror = cls(table, budget, name)
        for key, attr in cls.COUNTERS.items():
            value = counters.get(key)
            if isinstance(value, bool) or not isinstance(value, int):
                raise ValueError(f"session.{key}: expected a number")
            setattr(mirror, attr, value)
        mirror.resident, mirror.sent = resident, sent
        mirror.last_used[resident] = np.frombuffer(used, "<i4").astype(np.int64)
        mirror.models_sent, mirror.resync = flags
        mirror.recount()
        return mirror


def expand(key: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Representation ids key + l for every whole level l in [floor(lo), ceil(hi)], per row."""
    if key.size == 0:
        return np.zeros(0, np.int64)
    first = np.floor(lo + 1e-9).astype(np.int64)
    count = np.ceil(hi - 1e-9).astype(np.int64) - first + 1
    count = np.maximum(count, 1)
    base = np.repeat(key + first, count)
    step = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
    return np.unique(base + step)
