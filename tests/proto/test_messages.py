"""The wire contract: round trips, and refusal of every kind of malformed frame."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from proto import PROTOCOL_VERSION, ProtocolError
from proto.codec import MAX_CLIENT_FRAME, decode_client, decode_server, encode
from proto.geometry import decode_geometry, encode_geometry
from proto.messages import Camera, Delta, Error, FrameReport, Hello, Pose, RepresentationAdd, TourKey, Welcome

POSE = {"eye": [1.0, 2.0, 3.0], "forward": [0.0, 1.0, 0.0], "up": [0.0, 0.0, 1.0]}


def test_client_messages_round_trip():
    for msg in [
        Hello(protocol=PROTOCOL_VERSION, scene="demo", viewport=[640, 360], fov_y=55.0, target_frame_time=0.04),
        Camera(t=1.25, **POSE),
        FrameReport(frame=7, t=1.3, time=0.049, triangles=1000, vertices=600, draws=12, selection=3),
    ]:
        assert decode_client(encode(msg)) == msg


def test_server_messages_round_trip():
    blob = encode_geometry(*_mesh())
    for msg in [
        Welcome(session="abc", protocol=1, scene="demo", bounds=[[0, 0, 0], [1, 1, 1]], start=Pose(**POSE), tau=0.5,
                solver="greedy", tour=[TourKey(t=0.0, **POSE), TourKey(t=2.0, **POSE)]),
        Delta(seq=1, t0=0.0, t1=0.5, add=[RepresentationAdd(rep=3, object=1, level=0, geometry=blob)], drop=[1, 2],
              selection=[3], budget=0.05, predicted_cost=0.04, cost_coeff=2e-7),
        Error(code="invalid", message="x"),
    ]:
        assert decode_server(encode(msg)) == msg


def _refused(data: bytes, code: str) -> ProtocolError:
    with pytest.raises(ProtocolError) as info:
        decode_client(data)
    assert info.value.code == code, info.value
    return info.value


def test_truncated_msgpack_is_refused():
    data = encode(Camera(t=1.0, **POSE))
    for cut in (1, len(data) // 2, len(data) - 1):
        _refused(data[:cut], "bad_msgpack")
    _refused(b"\xc1", "bad_msgpack")  # a byte msgpack never uses


def test_trailing_garbage_is_refused():
    _refused(encode(Camera(t=1.0, **POSE)) + b"\x00", "bad_msgpack")


def test_unknown_type_and_missing_type():
    err = _refused(msgpack.packb({"type": "teleport"}), "unknown_type")
    assert "teleport" in err.message and "camera" in err.message
    _refused(msgpack.packb({"t": 1.0}), "invalid")
    _refused(msgpack.packb([1, 2, 3]), "invalid")
    _refused(msgpack.packb({"type": 5}), "invalid")


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_numbers_are_refused(bad):
    err = _refused(msgpack.packb({"type": "camera", "t": 1.0, **{**POSE, "eye": [0.0, bad, 0.0]}}), "invalid")
    assert "camera.eye.1" in err.message
    _refused(msgpack.packb({"type": "frame_report", "frame": 1, "t": 1.0, "time": bad, "triangles": 1,
                            "vertices": 1, "draws": 1}), "invalid")


def test_wrong_types_are_refused():
    err = _refused(msgpack.packb({"type": "camera", "t": "1.0", **POSE}), "invalid")
    assert "camera.t" in err.message
    _refused(msgpack.packb({"type": "frame_report", "frame": 1.5, "t": 1.0, "time": 0.05, "triangles": 1,
                            "vertices": 1, "draws": 1}), "invalid")
    _refused(msgpack.packb({"type": "camera", "t": 1.0, **{**POSE, "eye": [0.0, 1.0]}}), "invalid")
    _refused(msgpack.packb({"type": "camera", "t": 1.0, "extra": 1, **POSE}), "invalid")
    _refused(msgpack.packb({"type": "frame_report", "frame": True, "t": 1.0, "time": 0.05, "triangles": 1,
                            "vertices": 1, "draws": 1}), "invalid")
    err = _refused(msgpack.packb({"type": "frame_report", "frame": 1, "t": 1.0, "time": 0.05, "triangles": 1,
                                  "vertices": 1, "draws": 1, "governor_spare": "yes"}), "invalid")
    assert "governor_spare" in err.message


def test_ranges_are_enforced():
    _refused(msgpack.packb({"type": "hello", "protocol": 1, "scene": "demo", "viewport": [4, 4]}), "invalid")
    _refused(msgpack.packb({"type": "hello", "protocol": 1, "scene": "../etc", "viewport": [64, 64]}), "invalid")
    _refused(msgpack.packb({"type": "hello", "protocol": 1, "scene": "d", "viewport": [64, 64],
                            "target_frame_time": 0.0}), "invalid")
    _refused(msgpack.packb({"type": "camera", "t": 1.0, **{**POSE, "eye": [1e12, 0.0, 0.0]}}), "invalid")
    _refused(msgpack.packb({"type": "frame_report", "frame": 1, "t": 1.0, "time": -0.01, "triangles": 1,
                            "vertices": 1, "draws": 1}), "invalid")


def test_degenerate_poses_are_refused():
    err = _refused(msgpack.packb({"type": "camera", "t": 1.0, **{**POSE, "forward": [0.0, 0.0, 0.0]}}), "invalid")
    assert "forward" in err.message
    err = _refused(msgpack.packb({"type": "camera", "t": 1.0, **{**POSE, "up": [0.0, 3.0, 0.0]}}), "invalid")
    assert "parallel" in err.message


def test_oversize_frames_are_refused_before_decoding():
    err = _refused(b"\x00" * (MAX_CLIENT_FRAME + 1), "too_large")
    assert str(MAX_CLIENT_FRAME) in err.message
    # A msgpack header announcing a huge array must not allocate it.
    _refused(b"\xdd\xff\xff\xff\xff", "bad_msgpack")


def test_text_is_refused():
    _refused("hello", "not_binary")  # type: ignore[arg-type]


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=512))
def test_random_bytes_never_crash_the_decoder(data):
    try:
        decode_client(data)
    except ProtocolError:
        pass


def _mesh():
    s = trimesh.creation.icosphere(subdivisions=3)
    return s.vertices, s.faces


def test_geometry_round_trip_within_quantization():
    v, f = _mesh()
    g = decode_geometry(encode_geometry(v, f))
    assert g.faces == len(f) and g.vertices == len(v)
    # Same triangles, up to the reordering for the vertex cache.
    tri_in = np.sort(np.round(v[f].reshape(-1, 9), 3), axis=0)
    tri_out = np.sort(np.round(g.positions[g.indices].reshape(-1, 9), 3), axis=0)
    step = 2.0 / 65535
    assert np.abs(np.sort(tri_in.ravel()) - np.sort(tri_out.ravel())).max() <= step + 1e-3


def test_geometry_payload_defects_are_refused():
    v, f = _mesh()
    payload = msgpack.unpackb(encode_geometry(v, f))
    for change, needle in [({"enc": "xyz"}, "encoding"), ({"nv": 0}, "vertex count"), ({"nf": -1}, "face count"),
                           ({"lo": [0.0, math.nan, 0.0]}, "finite"), ({"ext": [1.0, 0.0, 1.0]}, "extent"),
                           ({"vb": b"\x00" * 10}, "decode"), ({"nv": 3}, "")]:
        with pytest.raises(ProtocolError) as info:
            decode_geometry(msgpack.packb({**payload, **change}))
        assert info.value.code == "bad_geometry" and needle in info.value.message
    with pytest.raises(ProtocolError):
        decode_geometry(b"\x93")


def test_welcome_sun_is_optional_and_never_a_zero_vector():
    from pydantic import ValidationError

    from proto.messages import DEFAULT_SUN

    base = dict(session="abc", protocol=1, scene="demo", bounds=[[0, 0, 0], [1, 1, 1]], start=Pose(**POSE),
                tau=0.5, solver="greedy")
    assert Welcome(**base).sun is None
    assert Welcome(**base, sun=list(DEFAULT_SUN)).sun == list(DEFAULT_SUN)
    assert abs(sum(x * x for x in DEFAULT_SUN) - 1.0) < 1e-5
    with pytest.raises(ValidationError, match="sun"):
        Welcome(**base, sun=[0.0, 0.0, 0.0])
    with pytest.raises(ValidationError):
        Welcome(**base, sun=[1.0, float("nan"), 0.0])
