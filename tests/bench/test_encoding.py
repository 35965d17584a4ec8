"""Geometry on the wire: at most 40 % of raw float32 on the real scenes, and the codec's zstd envelope."""

from __future__ import annotations

import json
import subprocess
import sys

import msgpack
import pytest
import zstandard

from bench.encoding import GOAL, measure, wire
from proto.codec import COMPRESS_ABOVE, ZSTD_MAGIC, decode_server, encode
from proto.errors import ProtocolError
from proto.messages import Delta, Error, Ping, RepresentationAdd


@pytest.mark.parametrize("which", ["denhaag_store", "auditorium_store"])
def test_what_deltas_carry_is_at_most_forty_percent_of_raw_float32(which, request):
    path = request.getfixturevalue(which)
    w = wire(path, keys=12)
    assert w["raw"] > 100_000  # the deltas really carried geometry
    assert w["ratio"] <= GOAL, w
    assert w["frames"] < w["uncompressed"]  # zstd over the frame earned its place
    m = measure(path)
    assert m["kinds"]["mesh"]["count"] > 100 and 0 < m["ratio"] < 1  # the stored payloads beat raw already


def test_large_server_frames_go_out_compressed_and_decode_back():
    blob = bytes(range(256)) * 64  # compressible
    d = Delta(seq=1, t0=0.0, t1=0.5, start=0.0, reset=True,
              add=[RepresentationAdd(rep=i, object=i, level=0, geometry=blob) for i in range(4)])
    frame = encode(d)
    assert frame[:4] == ZSTD_MAGIC and len(frame) < len(encode(d, compress=False)) / 4
    assert decode_server(frame) == d
    small = encode(Ping(id=1, sent=0.0))
    assert len(small) < COMPRESS_ABOVE and small[:4] != ZSTD_MAGIC and decode_server(small) == Ping(id=1, sent=0.0)


def test_a_compressed_frame_that_lies_or_is_garbage_is_refused():
    zc = zstandard.ZstdCompressor(write_content_size=True)
    with pytest.raises(ProtocolError) as e:
        decode_server(ZSTD_MAGIC + b"\x00" * 32)
    assert e.value.code in ("bad_msgpack", "too_large")
    # A bomb: a small frame that declares (and holds) more than a server frame may be.
    bomb = zstandard.ZstdCompressor(level=1).compress(b"\x00" * (300 * 1024 * 1024))
    with pytest.raises(ProtocolError) as e:
        decode_server(bomb)
    assert e.value.code == "too_large"
    # Valid zstd of something that is not a message.
    with pytest.raises(ProtocolError) as e:
        decode_server(zc.compress(msgpack.packb([1, 2, 3])))
    assert e.value.code == "invalid"
    # The server never accepts compressed frames from a client: they are not msgpack maps.
    from proto.codec import decode_client

    with pytest.raises(ProtocolError):
        decode_client(zc.compress(encode(Error(code="invalid", message="x" * 4000), compress=False)))


def test_bench_encoding_json(denhaag_store):
    out = subprocess.run([sys.executable, "-m", "walkstream", "bench", "encoding", "--store", str(denhaag_store),
                          "--keys", "6", "--json"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    doc = json.loads(out.stdout.strip().splitlines()[-1])
    assert doc["goal"] == GOAL and doc["wire"][0]["scene"] == "denhaag" and doc["worst_ratio"] <= GOAL
    assert "on the wire" in out.stderr
