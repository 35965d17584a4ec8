"""Point ("pq16") and instance ("inst") payloads: round trips, order, size, refusal of every defect."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from proto import ProtocolError
from proto.points import decode_instances, decode_points, encode_instances, encode_points, oct_decode, oct_encode
from server.scene.points import point_model
from server.scene.vegetation import broadleaf, conifer


@pytest.fixture(scope="module")
def model():
    return point_model(conifer(2), n_points=4096, seed=1)


@pytest.fixture(scope="module")
def blob(model):
    return encode_points(model)


def test_round_trip_keeps_order_and_precision(model, blob):
    d = decode_points(blob)
    assert len(d) == len(model)
    step = (model.hi - model.lo) / 65535
    assert (np.abs(d.positions - model.positions) <= step / 2 + 1e-4).all()  # same order, within ½ step
    assert np.array_equal(d.colors, model.colors)
    cos = (d.normals * model.normals).sum(axis=1)
    assert cos.min() > np.cos(np.radians(1.5))
    assert np.allclose(d.radius, model.radius, rtol=1e-3)
    assert (np.diff(d.radius) <= 0).all()  # float16 rounding is monotone


def test_explicit_fields_and_box():
    rng = np.random.default_rng(0)
    p = rng.uniform(-1, 1, (100, 3))
    n = rng.normal(size=(100, 3))
    c = rng.integers(0, 256, (100, 3), dtype=np.uint8)
    r = np.linspace(1, 0.1, 100)
    d = decode_points(encode_points(positions=p, normals=n, colors=c, radius=r, box_lo=[-2] * 3, box_hi=[2] * 3))
    assert np.abs(d.positions - p).max() <= 4 / 65535
    assert np.array_equal(d.colors, c)


def test_single_and_flat_points():
    d = decode_points(encode_points(positions=[[1.0, 2.0, 3.0]], normals=[[0, 0, 0]], colors=[[1, 2, 3]], radius=[0.5]))
    assert np.allclose(d.positions, [[1, 2, 3]], atol=1e-5) and np.allclose(d.normals, [[0, 0, 1]])


def test_octahedral_normals_cover_the_sphere():
    v = np.random.default_rng(3).normal(size=(5000, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    axes = np.vstack([np.eye(3), -np.eye(3)])
    v = np.vstack([v, axes])
    back = oct_decode(oct_encode(v))
    assert np.degrees(np.arccos(np.clip((back * v).sum(axis=1), -1, 1))).max() < 1.5


def test_payload_is_at_most_half_of_raw_float32():
    for tm in (conifer(0), broadleaf(1)):
        pm = point_model(tm, n_points=4096, seed=0)
        raw = len(pm) * (12 + 12 + 3 + 4)  # float32 positions, normals, radius; rgb8 colours
        assert len(encode_points(pm)) <= 0.5 * raw


def test_encoder_refuses_bad_input():
    ok = dict(positions=np.zeros((2, 3)), normals=np.ones((2, 3)), colors=np.zeros((2, 3), np.uint8), radius=[1, 1])
    for change in ({"positions": np.full((2, 3), np.nan)}, {"radius": [1, -1]}, {"colors": np.zeros((3, 3))},
                   {"positions": np.zeros((0, 3)), "normals": np.zeros((0, 3)), "colors": np.zeros((0, 3)),
                    "radius": []}):
        with pytest.raises(ValueError):
            encode_points(**{**ok, **change})


def _repack(blob: bytes, **changes) -> bytes:
    payload = msgpack.unpackb(blob, raw=False)
    payload.update(changes)
    for k, v in list(payload.items()):
        if v is _DROP:
            del payload[k]
    return msgpack.packb(payload, use_bin_type=True)


_DROP = object()


@pytest.mark.parametrize("changes", [
    {"enc": "mq16"}, {"n": 0}, {"n": 1 << 30}, {"n": 4097}, {"n": 4095}, {"n": 4096 + 64}, {"lo": [0.0, 0.0, 0.0]}, {"crc": 1}, {"crc": _DROP}, {"n": True}, {"n": 3.0},
    {"lo": [0, 0]}, {"lo": [0, 0, float("nan")]}, {"ext": [1, 0, 1]}, {"ext": [1, -1, 1]},
    {"ext": [1, float("inf"), 1]}, {"pb": b""}, {"pb": "text"}, {"nb": b"\x00" * 7}, {"cb": _DROP},
    {"ext": _DROP},
])
def test_point_payload_defects_are_refused(blob, changes):
    with pytest.raises(ProtocolError) as info:
        decode_points(_repack(blob, **changes))
    assert info.value.code == "bad_geometry"


def test_non_map_and_garbage_are_refused():
    for bad in (msgpack.packb([1, 2]), b"", b"\xc1", msgpack.packb({"enc": "pq16"}), "text"):
        with pytest.raises(ProtocolError):
            decode_points(bad)
        with pytest.raises(ProtocolError):
            decode_instances(bad)


@settings(max_examples=150, deadline=None)
@given(st.data())
def test_corrupted_point_payloads_raise_only_protocol_errors(blob, data):
    cut = data.draw(st.integers(0, len(blob) - 1))
    flips = data.draw(st.lists(st.tuples(st.integers(0, len(blob) - 1), st.integers(1, 255)), max_size=6))
    mutated = bytearray(blob)
    for at, x in flips:
        mutated[at] ^= x
    for candidate in (blob[:cut], bytes(mutated)):
        try:
            d = decode_points(candidate)
        except ProtocolError as exc:
            assert exc.code == "bad_geometry"
        else:  # a flip inside a buffer can still decode: then the result is well formed
            assert np.isfinite(d.positions).all() and np.isfinite(d.radius).all() and (d.radius >= 0).all()


# -- instances ------------------------------------------------------------------------------------


def _instances(k: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    m = np.tile(np.eye(4), (k, 1, 1))
    yaw = rng.uniform(0, 6.3, k)
    s = rng.uniform(0.8, 1.2, k)
    m[:, 0, 0] = m[:, 1, 1] = np.cos(yaw) * s
    m[:, 0, 1], m[:, 1, 0] = -np.sin(yaw) * s, np.sin(yaw) * s
    m[:, 2, 2] = s
    m[:, :3, 3] = rng.uniform(-5e4, 5e4, (k, 3))
    return rng.integers(0, 6, k), m


def test_instances_round_trip():
    ids, m = _instances(64)
    d = decode_instances(encode_instances(ids, m), models=6)
    assert np.array_equal(d.model, ids)
    assert np.allclose(d.matrix, m, rtol=1e-6, atol=5e-3)
    assert (d.matrix[:, 3] == [0, 0, 0, 1]).all()
    big = np.array([70000, 1, 2])
    assert np.array_equal(decode_instances(encode_instances(big, np.tile(np.eye(4), (3, 1, 1)))).model, big)


def test_instance_defects_are_refused():
    ids, m = _instances(8)
    blob = encode_instances(ids, m)
    with pytest.raises(ProtocolError):
        decode_instances(blob, models=int(ids.max()))  # an id ≥ the model count
    bad_m = np.frombuffer(np.full((8, 12), np.nan, np.float32).tobytes(), np.float32).reshape(8, 12)
    import meshoptimizer
    nan_mb = meshoptimizer.encode_vertex_buffer(np.ascontiguousarray(bad_m), 8, 48)
    for changes in ({"enc": "pq16"}, {"k": 0}, {"k": 9}, {"k": 64}, {"crc": "x"}, {"k": -1}, {"k": "8"}, {"ib": b"x"}, {"mb": _DROP},
                    {"mb": nan_mb}):
        with pytest.raises(ProtocolError) as info:
            decode_instances(_repack(blob, **changes))
        assert info.value.code == "bad_geometry"
    from proto.points import _crc
    nan_rows = np.full((8, 12), np.nan, np.float32)
    sneaky = _repack(blob, mb=nan_mb, crc=_crc(np.int64(8), ids.astype(np.uint32).reshape(-1, 1), nan_rows))
    with pytest.raises(ProtocolError, match="not finite"):
        decode_instances(sneaky)
    with pytest.raises(ValueError):
        encode_instances(ids, m[:, :3])
    with pytest.raises(ValueError):
        encode_instances(-ids - 1, m)


@settings(max_examples=150, deadline=None)
@given(st.data())
def test_corrupted_instance_payloads_raise_only_protocol_errors(data):
    ids, m = _instances(64, seed=5)
    blob = encode_instances(ids, m)
    cut = data.draw(st.integers(0, len(blob) - 1))
    flips = data.draw(st.lists(st.tuples(st.integers(0, len(blob) - 1), st.integers(1, 255)), max_size=6))
    mutated = bytearray(blob)
    for at, x in flips:
        mutated[at] ^= x
    for candidate in (blob[:cut], bytes(mutated)):
        try:
            d = decode_instances(candidate, models=6)
        except ProtocolError as exc:
            assert exc.code == "bad_geometry"
        else:
            assert np.isfinite(d.matrix).all() and (d.model < 6).all()
