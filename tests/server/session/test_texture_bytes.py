"""A texture travels inside its representation's payload, so every byte count sees it: the session's table (what
the byte gate and the cache mirror read), the gate's bytes to realise a choice, and the client's cache budget."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
import trimesh

from client.cache import ResidentCache
from proto.geometry import decode_geometry, encode_geometry
from proto.messages import Delta, RepresentationAdd
from server.scene.catalog import build_path
from server.scene.store import SceneStore
from server.session.gate import realise_bytes
from server.session.table import SceneTable
from tests.server.scene.test_textures import checker, curved_wall


def _untextured(blob: bytes) -> bytes:
    """The same geometry, colours and box without its UVs and texture."""
    fields = msgpack.unpackb(blob)
    g = decode_geometry(blob)
    lo = np.asarray(fields["lo"])
    return encode_geometry(g.positions, g.indices, lo, lo + np.asarray(fields["ext"]), reorder=False,
                           colours=g.colours)


@pytest.fixture(scope="module")
def wall(tmp_path_factory):
    folder = tmp_path_factory.mktemp("texture_bytes")
    trimesh.Scene(curved_wall(checker(512, 8))).export(folder / "wall.glb")
    build_path(folder / "wall.glb", folder / "wall.db", workers=1)
    with SceneStore.open(folder / "wall.db") as store:
        table = SceneTable.of(store.index)
        first, count = int(store.index.rep_first[0]), int(store.index.rep_count[0])
        blobs = [store.geometry(r) for r in range(first, first + count)]
        yield table, first, blobs


def test_the_gate_counts_a_textured_chains_pngs(wall) -> None:
    table, first, blobs = wall
    reps = np.arange(first, first + len(blobs))
    np.testing.assert_array_equal(table.rep_bytes[reps], [len(b) for b in blobs])
    finest = np.array([reps[-1]])
    nothing = np.zeros(table.rep_bytes.size, bool)
    lacking = int(realise_bytes(finest, np.array([-1]), np.array([first]), table.rep_bytes, nothing)[0])
    assert lacking == len(blobs[-1])  # nothing drawn before: the finest level alone
    from_coarsest = int(realise_bytes(finest, np.array([first]), np.array([first]), table.rep_bytes, nothing)[0])
    pngs = sum(len(msgpack.unpackb(b)["tx"]) for b in blobs)
    assert from_coarsest == sum(len(b) for b in blobs) >= sum(len(_untextured(b)) for b in blobs) + pngs


def test_the_client_cache_budget_counts_the_texture(wall) -> None:
    """A budget the untextured payload would fit refuses the textured one; held bytes include the PNG."""
    _, _, blobs = wall
    textured, plain = blobs[-1], _untextured(blobs[-1])
    png = len(msgpack.unpackb(textured)["tx"])
    add = [RepresentationAdd(rep=1, object=0, level=0, geometry=textured)]
    tight = ResidentCache(budget_bytes=len(plain) + png // 2)
    changes = tight.apply(Delta(seq=0, t0=0, t1=0.5, add=add, selection=[1]))
    assert changes.rejected == [1] and tight.refused_full == 1 and tight.held_bytes == 0
    roomy = ResidentCache(budget_bytes=len(textured))
    changes = roomy.apply(Delta(seq=0, t0=0, t1=0.5, add=add, selection=[1]))
    assert changes.rejected == [] and roomy.held_bytes == len(textured) >= len(plain) + png
    (rep, geometry), = changes.uploads
    assert rep == 1 and geometry.texture is not None and geometry.uv is not None
