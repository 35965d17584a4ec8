"""proto.geometry / proto.texture: UVs and a base-colour texture travel with the geometry, optional, validated."""

from __future__ import annotations

import io

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image, ImageFile

from proto.errors import ProtocolError
from proto.geometry import decode_geometry, encode_geometry, order_for_gpu
from proto.texture import MAX_TEXTURE_SIDE, decode_texture, encode_texture


def _mesh(seed: int, n: int = 30, m: int = 40):
    rng = np.random.default_rng(seed)
    return rng.random((n, 3)), rng.integers(0, n, (m, 3))


def _png(width: int, height: int, value: int = 0) -> bytes:
    out = io.BytesIO()
    Image.new("RGB", (width, height), (value, value, value)).save(out, format="PNG")
    return out.getvalue()


def _payload(seed: int = 0) -> dict:
    p, f = _mesh(seed)
    uv = np.random.default_rng(seed).random((p.shape[0], 2))
    tex = np.zeros((8, 16, 3), np.uint8)
    return msgpack.unpackb(encode_geometry(p, f, reorder=False, uv=uv, texture=tex))


def _decode(payload: dict):
    return decode_geometry(msgpack.packb(payload, use_bin_type=True))


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000), st.booleans(), st.integers(1, 40), st.integers(1, 40),
       st.floats(-8.0, 8.0), st.floats(1e-3, 16.0))
def test_uvs_and_texture_round_trip(seed: int, reorder: bool, width: int, height: int, shift: float,
                                    span: float) -> None:
    """Each stored vertex keeps its UV (to 16 bits of its box, wherever the box lies) and the texture
    comes back pixel for pixel."""
    p, f = _mesh(seed)
    rng = np.random.default_rng(seed)
    uv = shift + span * rng.random((p.shape[0], 2))
    tex = rng.integers(0, 256, (height, width, 3)).astype(np.uint8)
    g = decode_geometry(encode_geometry(p, f, reorder=reorder, uv=uv, texture=tex))
    want = uv
    if reorder:
        _, _, new_of_old = order_for_gpu(p, f)
        used = new_of_old >= 0
        want = np.empty((int(used.sum()), 2))
        want[new_of_old[used]] = uv[used]
    assert g.uv.dtype == np.float32 and g.uv.shape == want.shape
    np.testing.assert_allclose(g.uv, want, atol=span / 65535 + 1e-5 * (abs(shift) + span))
    np.testing.assert_array_equal(g.texture, tex)
    assert g.texture.dtype == np.uint8


def test_untextured_payloads_decode_without_uvs_and_the_texture_is_in_the_bytes() -> None:
    p, f = _mesh(1)
    uv = np.random.default_rng(1).random((p.shape[0], 2))
    tex = np.random.default_rng(2).integers(0, 256, (32, 32, 3)).astype(np.uint8)
    plain, textured = encode_geometry(p, f), encode_geometry(p, f, uv=uv, texture=tex)
    g = decode_geometry(plain)
    assert g.uv is None and g.texture is None
    assert not {"tb", "tx"} & set(msgpack.unpackb(plain))
    # What the byte gate and the cache count (the payload's length) includes the PNG.
    assert len(textured) > len(plain) + len(encode_texture(tex))


def test_encoder_refuses_uvs_without_a_texture_and_bad_shapes() -> None:
    p, f = _mesh(2)
    uv = np.zeros((p.shape[0], 2))
    with pytest.raises(ValueError, match="both or neither"):
        encode_geometry(p, f, uv=uv)
    with pytest.raises(ValueError, match="uv must be"):
        encode_geometry(p, f, uv=uv[:-1], texture=np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(ValueError, match="texture must be"):
        encode_geometry(p, f, uv=uv, texture=np.zeros((8, 8), np.uint8))


def test_a_truncated_png_is_refused() -> None:
    payload = _payload()
    png = _png(64, 64)
    payload["tx"], payload["tw"], payload["th"] = png[: len(png) // 2], 64, 64
    with pytest.raises(ProtocolError, match="does not decode") as err:
        _decode(payload)
    assert err.value.code == "bad_geometry"


def test_bytes_that_are_not_a_png_are_refused() -> None:
    payload = _payload()
    payload["tx"] = b"GIF89a not a png at all"
    with pytest.raises(ProtocolError, match="not a PNG"):
        _decode(payload)


def test_declared_sides_over_the_cap_are_refused() -> None:
    payload = _payload()
    payload["tw"] = MAX_TEXTURE_SIDE + 1
    with pytest.raises(ProtocolError, match="outside 1..4096"):
        _decode(payload)
    payload["tw"], payload["th"] = 16, 0
    with pytest.raises(ProtocolError, match="outside 1..4096"):
        _decode(payload)


def test_declared_and_decoded_sizes_must_match_and_nothing_larger_is_decoded(monkeypatch) -> None:
    """A PNG whose header is larger than declared is refused from its header: its pixels are never decoded."""
    big = _png(2048, 2048)
    loads = []
    real = ImageFile.ImageFile.load
    monkeypatch.setattr(ImageFile.ImageFile, "load", lambda self: loads.append(self.size) or real(self))
    with pytest.raises(ProtocolError, match="declared 16×16 but its PNG is 2048×2048"):
        decode_texture(big, 16, 16)
    assert loads == []
    payload = _payload()
    payload["tx"], payload["tw"], payload["th"] = _png(8, 8), 16, 8
    with pytest.raises(ProtocolError, match="declared 16×8 but its PNG is 8×8"):
        _decode(payload)


def test_half_a_texture_is_refused() -> None:
    payload = _payload()
    del payload["tx"]
    with pytest.raises(ProtocolError, match="'tb' without 'tx'"):
        _decode(payload)
    payload = _payload()
    del payload["tb"]
    with pytest.raises(ProtocolError, match="'tx' without 'tb'"):
        _decode(payload)


def test_a_bad_uv_buffer_or_box_is_refused() -> None:
    payload = _payload()
    payload["tb"] = payload["tb"][: len(payload["tb"]) // 2]
    with pytest.raises(ProtocolError, match="UV buffer"):
        _decode(payload)
    payload = _payload()
    payload["text"] = [1.0, 0.0]
    with pytest.raises(ProtocolError, match="UV box extent"):
        _decode(payload)
    payload["text"] = [1.0]
    with pytest.raises(ProtocolError, match="'text' must be two numbers"):
        _decode(payload)
