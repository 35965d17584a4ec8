"""What a client holds, in a few numbers both sides can compute: count, bytes and an order-free digest.

The server keeps a mirror of every client's cache so it never sends what the
client has and never counts on what it does not. After each delta the client
acks ``held``, ``held_bytes`` and ``digest``; the server compares them with its
mirror as of that delta. The digest is the XOR of a 64-bit mix of each
representation id, so it is independent of order, and adding or removing one
id is one XOR — the server updates it incrementally, never rehashing a set.
"""

from __future__ import annotations

import zlib

import numpy as np

from .errors import ProtocolError

__all__ = ["mix", "digest", "pack_held", "unpack_held"]

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


def pack_held(reps: np.ndarray) -> bytes:
    """The held set as a zlib'd little-endian bitset over ids 0..max: a city's cache in a few kilobytes."""
    reps = np.asarray(reps, np.int64)
    if reps.size == 0:
        return zlib.compress(b"", 9)
    if reps.min() < 0:
        raise ValueError("representation ids are ≥ 0")
    bits = np.zeros(int(reps.max()) + 1, bool)
    bits[reps] = True
    return zlib.compress(np.packbits(bits, bitorder="little").tobytes(), 9)


def unpack_held(blob: bytes, n_reps: int) -> np.ndarray:
    """(k,) int64 sorted ids from ``pack_held``; refuses (``bad_held``) a bad stream, a bomb, or an id ≥ n_reps."""
    limit = (int(n_reps) + 7) // 8
    inflate = zlib.decompressobj()
    try:
        raw = inflate.decompress(bytes(blob), limit + 1)
    except zlib.error as exc:
        raise ProtocolError("bad_held", f"the held manifest does not inflate: {exc}") from None
    if len(raw) > limit or inflate.unconsumed_tail or not inflate.eof:
        raise ProtocolError("bad_held", f"the held manifest is truncated or longer than {n_reps} representations")
    ids = np.nonzero(np.unpackbits(np.frombuffer(raw, np.uint8), bitorder="little"))[0].astype(np.int64)
    if ids.size and ids[-1] >= n_reps:
        raise ProtocolError("bad_held", f"the held manifest names representation {int(ids[-1])}; the scene has {n_reps}")
    return ids
