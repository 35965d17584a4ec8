"""USGS ASCII DEM and .npz height grids: the real files, and malformed ones."""

from __future__ import annotations

import numpy as np
import pytest

from server.scene.data import data_file
from server.scene.importers.dem import load_dem, load_npz
from server.scene.source import SourceError

DEM = data_file("terrain/SainteHelens.dem")


@pytest.fixture(scope="module")
def helens():
    return load_dem(DEM)


def test_st_helens(helens):
    (g,) = helens.grids
    rows, cols = g.heights.shape
    assert cols == 327  # the header's profile count
    assert 440 <= rows <= 470
    assert g.spacing == (30.0, 30.0)
    assert abs(g.origin[0] - 557945) < 200 and abs(g.origin[1] - 5107991) < 200
    z = g.heights[np.isfinite(g.heights)]
    assert 600 < z.min() < 800 and 2450 < z.max() < 2560  # the crater rim after 1980: 2,549 m
    assert z.min() == 682 and z.max() == 2543  # the header's min / max
    assert 0 < np.isnan(g.heights).mean() < 0.1  # the quadrangle is not grid-aligned: corners are empty
    assert g.attributes["utm_zone"] == 10 and helens.crs
    # every column is one profile: a contiguous run of samples
    for c in range(cols):
        ok = np.flatnonzero(np.isfinite(g.heights[:, c]))
        assert ok.size and (np.diff(ok) == 1).all()


def _record(text: str) -> str:
    return text.ljust(1024)[:1024]


def _header(profiles=2, z_units=2) -> str:
    h = list(" " * 1024)
    h[:20] = "SYNTHETIC TEST DEM  "
    put = lambda a, s: h.__setitem__(slice(a, a + len(s)), s)  # noqa: E731
    put(144, f"{1:6d}{1:6d}{1:6d}{10:6d}")
    put(528, f"{2:6d}{z_units:6d}{4:6d}")
    put(738, "   0.100000000000000D+03   0.200000000000000D+03")
    put(786, "   0.000000000000000D+00")
    put(816, "0.300000E+020.300000E+020.100000E+01")
    put(852, f"{1:6d}{profiles:6d}")
    return "".join(h)


def _profile(col, x, y, zs) -> str:
    head = f"{1:6d}{col:6d}{len(zs):6d}{1:6d}" + "".join(f"{v:24.15E}".replace("E", "D") for v in (x, y, 0, 0, 0))
    body = "".join(f"{int(v):6d}" for v in zs)
    first, rest = body[:146 * 6], body[146 * 6:]
    recs = [_record(head + first)] + [_record(rest[k:k + 170 * 6]) for k in range(0, len(rest), 170 * 6)]
    return "".join(recs)


def test_synthetic_dem_placement_and_units(tmp_path):
    zs = np.arange(200) + 100
    zs[5] = -32767
    text = _header(2, z_units=1) + _profile(1, 1000, 2000, zs) + _profile(2, 1030, 2060, [7, 8, 9])
    p = tmp_path / "a.dem"
    p.write_text(text)
    g = load_dem(p).grids[0]
    assert g.heights.shape == (200, 2) and g.origin == (1000.0, 2000.0)
    assert np.isnan(g.heights[5, 0]) and g.heights[199, 0] == pytest.approx(299 * 0.3048)
    assert np.isnan(g.heights[:2, 1]).all() and g.heights[2:5, 1] == pytest.approx(np.array([7, 8, 9]) * 0.3048)
    assert np.isnan(g.heights[5:, 1]).all()


@pytest.mark.parametrize("case, message", [
    ("empty", "empty"),
    ("truncated", "truncated"),
    ("bad token", "record 2"),
    ("bad header", "record 1"),
])
def test_malformed_dem(tmp_path, case, message):
    good = _header(2) + _profile(1, 1000, 2000, [1, 2, 3]) + _profile(2, 1030, 2000, [4, 5, 6])
    text = {"empty": "",
            "truncated": good[:2048],
            "bad token": good[:1024 + 144 + 6] + "   abc" + good[1024 + 144 + 12:],
            "bad header": good[:816] + "0.30000XE+02" + good[828:]}[case]
    p = tmp_path / "bad.dem"
    p.write_text(text)
    with pytest.raises(SourceError, match=message) as e:
        load_dem(p)
    assert "bad.dem" in str(e.value)


def test_real_dem_truncated(tmp_path):
    p = tmp_path / "cut.dem"
    p.write_bytes(DEM.read_bytes()[:1024 * 300])
    with pytest.raises(SourceError, match="truncated.*327 profiles"):
        load_dem(p)


def test_npz_matplotlib():
    cbook = pytest.importorskip("matplotlib.cbook")
    path = cbook.get_sample_data("jacksboro_fault_dem.npz", asfileobj=False)
    (g,) = load_npz(path).grids
    raw = np.load(path)["elevation"]
    assert g.heights.shape == (344, 403)
    assert g.spacing[0] == pytest.approx(1 / 1200) and g.spacing[1] == pytest.approx(1 / 1200)  # 3 arc-seconds
    assert g.origin[0] == pytest.approx(-84.41375) and g.origin[1] == pytest.approx(36.44625)
    assert np.array_equal(g.heights, raw[::-1].astype(float))  # rows turned to run north


def test_npz_spacing_and_malformed(tmp_path):
    p = tmp_path / "g.npz"
    np.savez(p, h=np.ones((3, 4)))
    g = load_npz(p, spacing=5).grids[0]
    assert g.spacing == (5.0, 5.0) and g.origin == (0.0, 0.0)
    assert load_npz(p).grids[0].spacing == (1.0, 1.0)
    np.savez(p, h=np.ones((3, 4)), dx=2.0, dy=4.0)
    assert load_npz(p, spacing=9).grids[0].spacing == (2.0, 4.0)
    for arrays, message in [({"h": np.full((3, 3), np.nan)}, "NaN"),
                            ({"h": np.ones((2, 3, 4))}, "2-D"),
                            ({"h": np.ones((2, 3)), "k": np.ones((2, 2))}, "several")]:
        np.savez(p, **arrays)
        with pytest.raises(SourceError, match=message) as e:
            load_npz(p)
        assert "g.npz" in str(e.value)
    np.savez(p, h=np.ones((2, 3, 4)), k=np.ones((2, 2)))
    with pytest.raises(SourceError, match="2-D"):
        load_npz(p, key="h")
    with pytest.raises(SourceError, match="no array 'z'"):
        load_npz(p, key="z")


def test_line_broken_records_read_as_tokens(tmp_path):
    recs = _header(2) + _profile(1, 1000, 2000, [1, 2, 3]) + _profile(2, 1030, 2030, [4, 5])
    p = tmp_path / "lines.dem"
    p.write_text("\n".join(recs[k:k + 1024].rstrip() for k in range(0, len(recs), 1024)) + "\n")
    g = load_dem(p).grids[0]
    assert g.heights.shape == (3, 2) and list(g.heights[:, 0]) == [1, 2, 3]
    assert np.isnan(g.heights[0, 1]) and list(g.heights[1:, 1]) == [4, 5]
