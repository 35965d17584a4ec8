"""The walkable grid on the wire: heights come back within half a quantisation step, blocked cells stay blocked,
and a damaged grid is refused with what is wrong."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from proto.errors import ProtocolError
from proto.walkable import WalkableGrid, decode, encode


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 40), st.integers(1, 40), st.floats(-500, 3000), st.floats(0.0, 2500.0), st.integers(0, 2**31))
def test_heights_survive_the_wire_within_half_a_step_and_blocked_cells_stay_blocked(ny, nx, low, span, seed):
    rng = np.random.default_rng(seed)
    ground = (low + span * rng.random((ny, nx))).astype(np.float32)
    ground[rng.random((ny, nx)) < 0.3] = np.nan
    grid = WalkableGrid((10.0, -5.0), 0.5, ground)
    back = decode(encode(grid))
    assert back.shape == grid.shape and back.origin == grid.origin and back.cell == grid.cell
    assert np.array_equal(np.isnan(back.ground), np.isnan(ground))
    ok = np.isfinite(ground)
    if ok.any():
        step = (ground[ok].max() - ground[ok].min()) / 65534
        tol = step / 2 + 1e-6 * max(1.0, float(np.abs(ground[ok]).max()))  # float32 rounding on top
        assert np.abs(back.ground[ok] - ground[ok]).max() <= tol


def test_a_mountain_keeps_centimetres_where_float16_would_lose_metres():
    ground = np.linspace(680.0, 2540.0, 400, dtype=np.float32).reshape(20, 20)
    back = decode(encode(WalkableGrid((0.0, 0.0), 10.0, ground)))
    assert np.abs(back.ground - ground).max() < 0.02


@pytest.mark.parametrize("damage, says", [
    (lambda m: m.pop("u16"), "u16"),
    (lambda m: m.update(shape=[5000, 5000]), "over"),
    (lambda m: m.update(step=float("nan")), "step"),
    (lambda m: m.update(u16=m["u16"][:-3]), "walkable grid"),
])
def test_a_damaged_grid_is_refused_naming_what_is_wrong(damage, says):
    m = msgpack.unpackb(encode(WalkableGrid((0.0, 0.0), 1.0, np.zeros((4, 4), np.float32))), raw=False)
    damage(m)
    with pytest.raises(ProtocolError, match=says) as err:
        decode(msgpack.packb(m, use_bin_type=True))
    assert err.value.code == "bad_walkable"
