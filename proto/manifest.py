"""What a client holds, in a few numbers both sides can compute: count, bytes and an order-free digest.

The server keeps a mirror of every client's cache so it never sends what the
client has and never counts on what it does not. After each delta the client
acks ``held``, ``held_bytes`` and ``digest``; the server compares them with its
mirror as of that delta. The digest is the XOR of a 64-bit mix of each
representation id, so it is independent of order, and adding or removing one
id is one XOR — the server updates it incrementally, never rehashing a set.
"""

from __future__ import annotations

import numpy as np

__all__ = ["mix", "digest"]

_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)


def mix(reps: np.ndarray) -> np.ndarray:
    """(n,) uint64 — splitmix64's finaliser of each id (well spread, so XORs rarely cancel)."""
    z = np.asarray(reps, np.int64).astype(np.uint64) + np.uint64(0x9E3779B97F4A7C15)
    with np.errstate(over="ignore"):
        z = (z ^ (z >> np.uint64(30))) * _M1
        z = (z ^ (z >> np.uint64(27))) * _M2
    return z ^ (z >> np.uint64(31))


def digest(reps: np.ndarray) -> int:
    """The digest of a set of representation ids (duplicates are the caller's error: they cancel)."""
    m = mix(reps)
    return int(np.bitwise_xor.reduce(m)) if m.size else 0
