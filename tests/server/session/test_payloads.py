"""Payloads read and packed once per scene: every session sent a representation gets the same add, and a
delta packed around the shared bytes is byte for byte the delta packed from scratch."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from bench.loadtest.scripted import run_scripted
from proto.codec import decode_server, encode
from proto.messages import Delta, ModelAdd, RepresentationAdd
from server.scene.store import SceneStore
from server.session import Session, SessionConfig
from server.session.payloads import Payloads, packed


@pytest.fixture()
def city(denhaag_store):
    store = SceneStore.open(denhaag_store)
    yield store
    store.close()


def test_sessions_share_each_add_and_the_store_is_read_once(city):
    scenes = {city.index.name: city}
    cache = Payloads.of(city)
    assert Payloads.of(city) is cache
    run = run_scripted(scenes, 4, 3.0, make_session=lambda i: Session(scenes, f"s{i}", SessionConfig()),
                       stagger=0.0)
    # Four clients over a city see much the same representations: each is read and built once, then shared.
    assert run.deltas >= 4 and cache.hits > 2 * cache.misses > 0 and cache.reads < run.deltas
    firsts = [decode_server(f[1] if decode_server(f[0]).type == "ping" else f[0]) for f in run.frames]
    assert all(isinstance(d, Delta) and d.add for d in firsts)
    reps = [a.rep for a in firsts[0].add]
    assert [a.rep for a in cache.adds(reps, True)] == reps
    again = cache.adds(reps, True)
    assert all(a is b for a, b in zip(cache.adds(reps, True), again))
    for add in again:
        stored = city.geometries([add.rep])[0]
        assert add.geometry == stored and add.object == int(city.index.rep_object[add.rep])
        assert add.morph == (city.morphs([add.rep])[0] if city.index.rep_morph[add.rep] else None)
    assert all(a.morph is None for a in cache.adds(reps, False))


def test_a_delta_packed_around_shared_bytes_is_the_delta_packed_from_scratch(city):
    cache = Payloads.of(city)
    trees = np.flatnonzero(city.index.object_kind[city.index.rep_object] == 3)
    reps = [0, 5, 17, *trees[:2].tolist()]
    adds = cache.adds(reps, True) + [RepresentationAdd(rep=9, object=1, level=0, geometry=b"not cached")]
    models = cache.models()
    assert models and all(isinstance(m, ModelAdd) for m in models)
    delta = Delta(seq=3, t0=1.0, t1=1.5, start=0.5, add=adds, models=models, selection=[0, 5], drop=[2])
    assert packed(adds[0]) == msgpack.packb(adds[0].model_dump(), use_bin_type=True)
    assert packed(adds[-1]) is None and packed(RepresentationAdd(**adds[0].model_dump())) is None
    for compress in (False, True):
        assert encode(delta, compress, packed=packed) == encode(delta, compress)
    small = Delta(seq=1, t0=0.0, t1=0.5, add=adds[:1])
    assert encode(small, packed=packed) == encode(small)
    assert decode_server(encode(delta, packed=packed)) == delta


def test_the_cache_keeps_to_its_bound_and_forgets_what_it_evicts(city):
    cache = Payloads(city, max_bytes=4096)
    first = cache.adds(range(40), False)
    assert cache.bytes <= 4096 or len(cache._adds) == 1
    assert packed(first[0]) is None  # evicted: its bytes are no longer claimed for that object
    last = cache.adds([39], False)[0]
    assert last is first[-1] and packed(last) is not None
    cache.close()
    assert packed(last) is None and cache.bytes == 0


def test_a_deltas_byte_count_from_the_stored_sizes_is_its_adds_lengths(city):
    """The pipeline counts a delta's bytes from the store's recorded sizes and the cache's morph-map sizes
    (arrays, not a pass over the adds): they must be the adds' own lengths, trees and meshes alike."""
    from server.session.table import SceneTable

    cache = Payloads(city)
    table = SceneTable.of(city.index)
    trees = np.flatnonzero(city.index.object_kind[city.index.rep_object] == 3)
    reps = np.unique(np.r_[np.arange(0, city.index.rep_object.size, 7), trees[:5]])
    assert city.index.rep_morph[reps].any()
    for morph in (True, False):
        adds = cache.adds(reps.tolist(), morph)
        assert int(table.rep_bytes[reps].sum()) == sum(len(a.geometry) for a in adds)
        maps = sum(len(a.morph) for a in adds if a.morph)
        assert (int(cache.morph_bytes[reps].sum()) if morph else 0) == maps
        assert maps > 0 or not morph
