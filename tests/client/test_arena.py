"""Arena allocator on a real EGL context: first fit, coalescing, growth and compaction keep every block's bytes."""

from __future__ import annotations

import moderngl
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from client.arena import Arena, Relocation

ES = 8  # bytes per element in these tests: two uint32 words


@pytest.fixture(scope="module")
def ctx() -> moderngl.Context:
    c = moderngl.create_standalone_context(require=330, backend="egl")
    yield c
    c.release()


def _fill(tag: int, n: int) -> np.ndarray:
    """n elements whose words encode (tag, position): a moved or overwritten block cannot match by accident."""
    words = np.empty((n, 2), np.uint32)
    words[:, 0] = tag
    words[:, 1] = np.arange(n, dtype=np.uint32)
    return words


def _read(arena: Arena, offset: int) -> np.ndarray:
    return np.frombuffer(arena.read(offset), np.uint32).reshape(-1, 2)


def _check(arena: Arena, contents: dict[int, np.ndarray] | None = None) -> None:
    """Invariants: live blocks and holes tile [0, top) without overlap; holes sorted, merged, below top."""
    off, size = arena.blocks()
    hoff, hlen = arena.free_list()
    assert (size > 0).all() and (hlen > 0).all()
    assert arena.used == int(size.sum()) and arena.holes == int(hlen.sum())
    assert arena.top <= arena.capacity and arena.buffer.size == arena.capacity * ES
    spans = sorted([(o, s, "b") for o, s in zip(off.tolist(), size.tolist())]
                   + [(o, s, "h") for o, s in zip(hoff.tolist(), hlen.tolist())])
    at = 0
    for o, s, kind in spans:
        assert o == at, f"gap or overlap at {at}: next span starts at {o}"
        at = o + s
    assert at == arena.top
    assert (np.diff(hoff) > 0).all()
    assert not (hoff[1:] == hoff[:-1] + hlen[:-1]).any(), "adjacent holes were not coalesced"
    if hoff.size:
        assert hoff[-1] + hlen[-1] < arena.top, "a hole touches the tail"
        kinds = [k for _, _, k in spans]
        assert all(not (a == b == "h") for a, b in zip(kinds, kinds[1:]))
    if contents is not None:
        assert sorted(contents) == off.tolist()
        for o, data in contents.items():
            np.testing.assert_array_equal(_read(arena, o), data)


def test_first_fit_and_coalescing(ctx: moderngl.Context) -> None:
    a = Arena(ctx, ES, 64, compact_min=10**9)
    blocks = [a.alloc(n) for n in (4, 8, 4, 8, 4)]
    assert blocks == [0, 4, 12, 16, 24] and a.top == 28 and a.used == 28
    a.free(4)
    a.free(16)
    _check(a)
    assert a.free_list()[0].tolist() == [4, 16] and a.holes == 16
    assert a.alloc(6) == 4  # first fit: the first hole large enough
    assert a.free_list()[0].tolist() == [10, 16] and a.free_list()[1].tolist() == [2, 8]
    assert a.alloc(3) == 16  # the 2-element hole at 10 is too small
    a.free(12)  # merges with the hole on its left (10..12); 16..19 is live
    _check(a)
    assert a.free_list()[0].tolist() == [10, 19] and a.free_list()[1].tolist() == [6, 5]
    a.free(16)  # merges with the holes on both sides
    _check(a)
    assert a.free_list()[0].tolist() == [10] and a.free_list()[1].tolist() == [14]
    a.free(24)  # the top block: the tail grows back over it and the hole below
    assert a.top == 10 and a.free_list()[0].size == 0
    a.free(0)
    a.free(4)
    assert a.top == 0 and a.used == 0 and len(a) == 0
    _check(a)
    a.release()


def test_errors(ctx: moderngl.Context) -> None:
    a = Arena(ctx, ES, 16)
    with pytest.raises(ValueError):
        a.alloc(0)
    with pytest.raises(KeyError):
        a.free(3)
    off = a.alloc(4)
    with pytest.raises(KeyError):
        a.free(off + 1)
    with pytest.raises(ValueError):
        a.write(off, _fill(1, 5))  # more than the block
    with pytest.raises(ValueError):
        a.write(off, b"\0" * 3)  # not whole elements
    with pytest.raises(KeyError):
        a.write(off + 4, _fill(1, 1))
    a.write(off, _fill(1, 2))  # a prefix of the block is fine
    np.testing.assert_array_equal(np.frombuffer(a.read(off, 2), np.uint32).reshape(-1, 2), _fill(1, 2))
    with pytest.raises(ValueError):
        Arena(ctx, 0, 16)
    a.release()


def test_growth_copies_on_the_gpu_and_notifies(ctx: moderngl.Context) -> None:
    a = Arena(ctx, ES, 8)
    events: list[Relocation | None] = []
    a.listeners.append(lambda arena, moved: events.append(moved))
    contents = {}
    for tag in range(1, 4):
        off = a.alloc(3 if tag < 3 else 5)
        contents[off] = _fill(tag, a.size_of(off))
        a.write(off, contents[off])
    assert a.grows >= 1 and a.capacity >= 11 and events and all(e is None for e in events)
    old = a.buffer
    big = a.alloc(100)  # grows by doubling until it fits
    assert a.capacity >= a.top and a.buffer is not old and isinstance(old.mglo, moderngl.mgl.InvalidObject)
    contents[big] = _fill(9, 100)
    a.write(big, contents[big])
    _check(a, contents)
    a.release()


def test_reserve_grows_once_for_a_batch_and_keeps_contents(ctx: moderngl.Context) -> None:
    a = Arena(ctx, ES, 8)
    first = a.alloc(4)
    contents = {first: _fill(1, 4)}
    a.write(first, contents[first])
    a.reserve(0)
    a.reserve(4)  # fits in what is free: nothing moves
    assert a.grows == 0
    a.reserve(60)
    assert a.grows == 1 and a.capacity >= 64
    for tag, n in enumerate((10, 20, 30), start=2):  # the batch the reserve was for
        off = a.alloc(n)
        contents[off] = _fill(tag, n)
        a.write(off, contents[off])
    assert a.grows == 1
    _check(a, contents)
    a.release()


def test_compact_moves_blocks_down_and_returns_the_mapping(ctx: moderngl.Context) -> None:
    a = Arena(ctx, ES, 64, compact_min=10**9)
    moves: list[Relocation | None] = []
    a.listeners.append(lambda arena, moved: moves.append(moved))
    contents = {}
    offs = [a.alloc(n) for n in (5, 3, 7, 2, 6, 4)]
    for tag, off in enumerate(offs):
        contents[off] = _fill(tag, a.size_of(off))
        a.write(off, contents[off])
    for off in (offs[0], offs[2], offs[3]):
        a.free(off)
        del contents[off]
    _check(a, contents)
    moved = a.compact()
    assert moves[-1] is moved and a.compactions == 1
    assert moved.old.tolist() == [offs[1], offs[4], offs[5]] and moved.new.tolist() == [0, 3, 9]
    assert moved.as_dict() == {offs[1]: 0, offs[4]: 3, offs[5]: 9}
    np.testing.assert_array_equal(moved.map(np.array([offs[5], offs[1]])), [9, 0])
    with pytest.raises(KeyError):
        moved.map(np.array([offs[0]]))  # freed: not relocated
    contents = {int(moved.map(np.array([o]))[0]): d for o, d in contents.items()}
    assert a.holes == 0 and a.top == a.used == 13
    _check(a, contents)
    a.release()


def test_fragmentation_triggers_compaction_before_growth(ctx: moderngl.Context) -> None:
    a = Arena(ctx, ES, 100, compact_ratio=0.5, compact_min=10)
    offs = [a.alloc(10) for _ in range(10)]
    contents = {o: _fill(i, 10) for i, o in enumerate(offs)}
    for o, d in contents.items():
        a.write(o, d)
    for o in offs[1:8:2]:  # four holes of 10, each alone: no merging
        a.free(o)
        del contents[o]
    assert a.holes == 40 and a.used == 60 and a.fragmented  # 40 > 0.5 · 60 and ≥ 10
    moved = []
    a.listeners.append(lambda arena, m: moved.append(m))
    off = a.alloc(30)  # no hole fits 30 and the tail is full: compaction makes room without growing
    assert a.grows == 0 and a.compactions == 1 and off == 60 and moved and moved[0] is not None
    contents = {int(moved[0].map(np.array([o]))[0]): d for o, d in contents.items()}
    contents[off] = _fill(99, 30)
    a.write(off, contents[off])
    _check(a, contents)
    # maybe_compact does nothing below the thresholds
    assert a.maybe_compact() is None
    a.release()


def test_read_outside_is_refused(ctx: moderngl.Context) -> None:
    a = Arena(ctx, ES, 4)
    with pytest.raises(ValueError):
        a.read(2, 3)
    a.release()


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.tuples(st.sampled_from(["alloc", "alloc", "free", "compact"]), st.integers(1, 40),
                          st.integers(0, 10**6)), min_size=1, max_size=60),
       st.integers(1, 64), st.sampled_from([0.25, 0.5, 2.0]))
def test_random_sequences_keep_invariants_and_data(ctx: moderngl.Context, ops, capacity: int, ratio: float) -> None:
    a = Arena(ctx, ES, capacity, compact_ratio=ratio, compact_min=8)
    contents: dict[int, np.ndarray] = {}

    def follow(arena: Arena, moved: Relocation | None) -> None:
        if moved is not None:
            moved_contents = {int(moved.map(np.array([o]))[0]): d for o, d in contents.items()}
            contents.clear()
            contents.update(moved_contents)

    a.listeners.append(follow)
    tag = 0
    for op, n, pick in ops:
        if op == "alloc":
            tag += 1
            off = a.alloc(n)
            assert off not in contents
            contents[off] = _fill(tag, n)
            a.write(off, contents[off])
        elif op == "free" and contents:
            off = sorted(contents)[pick % len(contents)]
            a.free(off)
            del contents[off]
            a.maybe_compact()
        elif op == "compact":
            a.compact()
            assert a.holes == 0
        _check(a)
    _check(a, contents)
    a.release()
