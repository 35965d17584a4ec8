"""proto.geometry: per-vertex colours travel with the geometry, optional, validated."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from proto.errors import ProtocolError
from proto.geometry import decode_geometry, encode_geometry, order_for_gpu


def _mesh(seed: int, n: int = 40, m: int = 60):
    rng = np.random.default_rng(seed)
    return rng.random((n, 3)), rng.integers(0, n, (m, 3)), rng.integers(0, 256, (n, 3)).astype(np.uint8)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000), st.booleans())
def test_colours_follow_their_vertices(seed: int, reorder: bool) -> None:
    """Whatever the reordering, each stored vertex keeps the colour it was given."""
    p, f, c = _mesh(seed)
    g = decode_geometry(encode_geometry(p, f, reorder=reorder, colours=c))
    if reorder:
        _, _, new_of_old = order_for_gpu(p, f)
        used = new_of_old >= 0
        assert g.colours.shape == (int(used.sum()), 3)
        np.testing.assert_array_equal(g.colours[new_of_old[used]], c[used])
    else:
        np.testing.assert_array_equal(g.colours, c)
    assert g.colours.dtype == np.uint8


def test_colourless_payloads_decode_without_colours_and_are_smaller() -> None:
    p, f, c = _mesh(1)
    plain, coloured = encode_geometry(p, f), encode_geometry(p, f, colours=c)
    assert decode_geometry(plain).colours is None
    assert "cb" not in msgpack.unpackb(plain)
    assert len(coloured) > len(plain)  # the byte cost (``rep_bytes`` = payload length) counts the colours


def test_encoder_refuses_colours_of_the_wrong_shape_or_type() -> None:
    p, f, c = _mesh(2)
    with pytest.raises(ValueError, match="colours must be"):
        encode_geometry(p, f, colours=c[:-1])
    with pytest.raises(ValueError, match="colours must be"):
        encode_geometry(p, f, colours=c.astype(np.float32))


def test_decoder_refuses_a_colour_buffer_of_another_size_or_type() -> None:
    p, f, c = _mesh(3)
    payload = msgpack.unpackb(encode_geometry(p, f, reorder=False, colours=c))
    good = payload["cb"]
    payload["cb"] = good[: len(good) // 2]  # truncated
    with pytest.raises(ProtocolError, match="colour buffer"):
        decode_geometry(msgpack.packb(payload, use_bin_type=True))
    payload["cb"] = "red"
    with pytest.raises(ProtocolError, match="'cb'"):
        decode_geometry(msgpack.packb(payload, use_bin_type=True))
    payload["cb"] = b"\x00garbage"
    with pytest.raises(ProtocolError, match="colour buffer"):
        decode_geometry(msgpack.packb(payload, use_bin_type=True))
