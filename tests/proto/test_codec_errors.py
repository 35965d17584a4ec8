"""Every frame the codec refuses is refused with a sentence saying what was wrong with it."""

from __future__ import annotations

import msgpack
import pytest
import zstandard

from proto.codec import decode_client
from proto.errors import ProtocolError


@pytest.mark.parametrize("frame, said", [
    (b"\xc1\x00", "not msgpack (starts with bytes c1 00)"),
    (b"", "empty"),
    (b"\x91" * 60_000, "nests maps or arrays too deeply"),
    (zstandard.ZstdCompressor().compress(msgpack.packb({"type": "hello"})), "compressed frames are not accepted"),
    (msgpack.packb({"type": "pong"}) + b"\x00", "bytes follow the first msgpack object"),
    (b"\xa3ab", "incomplete input"),
])
def test_an_undecodable_frame_is_named(frame, said):
    with pytest.raises(ProtocolError) as refused:
        decode_client(frame)
    assert refused.value.code == "bad_msgpack" and said in refused.value.message
