"""Height grids from USGS ASCII DEMs and ``.npz`` arrays.

**USGS ASCII DEM** (the 1990s "native" format, e.g. Mount St. Helens): a file of
1024-byte logical records. Record 1 is the type A header; then one type B
record group per profile (a south→north column of elevations starting at its
own (x, y), because the quadrangle is not aligned with the UTM grid, so
profiles have different lengths and start rows); optionally a type C
accuracy record. Fields are fixed-width Fortran output (``I6``, ``D24.15``,
``E12.6``) and neighbouring fields may touch ("10.300000E+020.300000E+02"), so
the header is cut at the spec's byte positions rather than split on blanks.
Elevations are integers scaled by the z resolution and offset by the
profile's local datum; -32767 (and anything ≤ -32767) marks a void.

Files that carry line breaks (some exporters end every record, or every
line, with a newline) are read as a token stream instead; the fixed-width
path is taken whenever the file is a whole number of 1024-byte records.

**npz**: one 2-D array (matplotlib's ``jacksboro_fault_dem.npz`` stores
``elevation`` plus ``dx``/``dy``/``xmin``/``ymin``/...). Rows are turned so
that they run along +y, as HeightGrid wants.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from server.scene.source import HeightGrid, SourceError, SourceScene

__all__ = ["load_dem", "load_npz", "FEET"]

FEET = 0.3048  #: metres per (international) foot
_RECORD = 1024
_VOID = -32767
# type A: (name, start byte (0-based), end byte, kind); DEM spec, Data Elements 1–16.
_A_FIELDS = [
    ("level", 144, 150, int), ("pattern", 150, 156, int), ("ref_system", 156, 162, int),
    ("zone", 162, 168, int), ("xy_units", 528, 534, int), ("z_units", 534, 540, int),
    ("sides", 540, 546, int), ("zmin", 738, 762, float), ("zmax", 762, 786, float),
    ("angle", 786, 810, float), ("dx", 816, 828, float), ("dy", 828, 840, float),
    ("dz", 840, 852, float), ("rows", 852, 858, int), ("profiles", 858, 864, int),
]
_DATUMS = {1: "NAD27", 2: "WGS72", 3: "WGS84", 4: "NAD83", 5: "Old Hawaii", 6: "Puerto Rico"}
_EPSG_UTM = {"NAD27": 26700, "NAD83": 26900, "WGS84": 32600}
_FIRST_B = 146  # elevations in the first record of a profile ((1024 - 144) // 6)
_NEXT_B = 170  # elevations in each continuation record (1024 // 6)


def _num(text: str, kind, path, where: str):
    """A Fortran number (``D`` exponents allowed); SourceError naming the file and record otherwise."""
    t = text.strip().replace("D", "E").replace("d", "e")
    try:
        return kind(float(t)) if kind is int else float(t)
    except ValueError:
        raise SourceError(f"{path}: {where}: not a number: {text.strip()!r}") from None


def _header(rec: str, path) -> dict:
    if len(rec.strip()) == 0:
        raise SourceError(f"{path}: record 1 (type A header) is blank")
    h = {"name": rec[:144].strip()}
    for name, a, b, kind in _A_FIELDS:
        field = rec[a:b]
        if not field.strip():
            if name in ("rows", "level", "pattern", "angle"):
                continue
            raise SourceError(f"{path}: record 1 (type A header): field {name!r} (bytes {a + 1}–{b}) is blank")
        h[name] = _num(field, kind, path, f"record 1 (type A header), field {name!r} (bytes {a + 1}–{b})")
    datum = rec[890:896].strip() if len(rec) >= 896 else ""
    if datum.isdigit():
        h["datum"] = _DATUMS.get(int(datum))
    if h["profiles"] <= 0:
        raise SourceError(f"{path}: record 1 (type A header): number of profiles is {h['profiles']}")
    if min(h["dx"], h["dy"]) <= 0 or h["dz"] <= 0:
        raise SourceError(f"{path}: record 1 (type A header): spatial resolution "
                          f"({h['dx']}, {h['dy']}, {h['dz']}) must be positive")
    return h


def _profiles_fixed(text: str, n_prof: int, path):
    """Type B groups from 1024-byte records: (x, y, datum, int elevations) per profile."""
    n_rec = len(text) // _RECORD
    out = []
    r = 1  # next record (0-based); record numbers in messages are 1-based
    for p in range(n_prof):
        if r >= n_rec:
            raise SourceError(f"{path}: truncated: the header announces {n_prof} profiles, "
                              f"the file ends after {p} (record {r})")
        rec = text[r * _RECORD:(r + 1) * _RECORD]
        where = f"record {r + 1} (profile {p + 1})"
        m = _num(rec[12:18], int, path, where + ", field m")
        n = _num(rec[18:24], int, path, where + ", field n")
        x = _num(rec[24:48], float, path, where + ", field x")
        y = _num(rec[48:72], float, path, where + ", field y")
        datum = _num(rec[72:96], float, path, where + ", local datum")
        count = m * n
        if count <= 0:
            raise SourceError(f"{path}: {where}: profile has {m}×{n} elevations")
        extra = max(0, count - _FIRST_B)
        n_recs = 1 + (extra + _NEXT_B - 1) // _NEXT_B
        if r + n_recs > n_rec:
            raise SourceError(f"{path}: truncated in {where} of the {n_prof} profiles the header announces: "
                              f"{count} elevations need {n_recs} records, the file has {n_rec - r} left")
        body = rec[144:144 + 6 * _FIRST_B] + "".join(
            text[k * _RECORD:k * _RECORD + 6 * _NEXT_B] for k in range(r + 1, r + n_recs))
        cells = np.frombuffer(body[:6 * count].encode("latin-1"), dtype="S6")
        try:
            z = cells.astype(np.int64)
        except ValueError:
            bad = next(i for i, c in enumerate(cells) if not c.strip().lstrip(b"-+").isdigit())
            rec_no = r + 1 + (0 if bad < _FIRST_B else 1 + (bad - _FIRST_B) // _NEXT_B)
            raise SourceError(f"{path}: record {rec_no} (profile {p + 1}), elevation {bad + 1}: "
                              f"not an integer: {cells[bad].decode('latin-1').strip()!r}") from None
        out.append((x, y, datum, z))
        r += n_recs
    return out


_TOKEN = re.compile(r"\S+")


def _profiles_tokens(text: str, start: int, n_prof: int, path):
    """Type B groups from a blank-separated stream (files with line breaks)."""
    lines = text[start:].splitlines()
    toks = [(i + 2, t) for i, line in enumerate(lines) for t in _TOKEN.findall(line)]
    out, k = [], 0
    for p in range(n_prof):
        if k + 9 > len(toks):
            raise SourceError(f"{path}: truncated: the header announces {n_prof} profiles, "
                              f"the file ends after {p}")
        where = lambda j: f"line {toks[j][0]} (profile {p + 1})"  # noqa: E731
        m, n = (_num(toks[k + j][1], int, path, where(k + j)) for j in (2, 3))
        x, y, datum = (_num(toks[k + j][1], float, path, where(k + j)) for j in (4, 5, 6))
        k += 9
        if m * n <= 0 or k + m * n > len(toks):
            raise SourceError(f"{path}: truncated in profile {p + 1}: {m * n} elevations announced")
        z = np.array([_num(t, int, path, f"line {ln} (profile {p + 1})") for ln, t in toks[k:k + m * n]])
        out.append((x, y, datum, z))
        k += m * n
    return out


def load_dem(path) -> SourceScene:
    """A USGS ASCII DEM as a SourceScene with one HeightGrid (metres up; x, y in the source's units).

    Profiles are placed into one grid by their start (x, y): col = (x − x0)/dx,
    row = (y − y0)/dy with (x0, y0) the smallest start; samples no profile
    covers, and voids, are NaN.
    """
    path = Path(path)
    raw = path.read_bytes()
    if not raw.strip():
        raise SourceError(f"{path}: empty file")
    text = raw.decode("latin-1")
    fixed = "\n" not in text[:_RECORD] and len(text) >= _RECORD
    if fixed:
        if len(text) % _RECORD:
            text = text + " " * (_RECORD - len(text) % _RECORD)
        head = text[:_RECORD]
    else:  # record 1 ends at the first line break; pad it to the fixed layout
        end = text.index("\n") if "\n" in text else len(text)
        head = text[:end].ljust(_RECORD)
    h = _header(head, path)
    n_prof = h["profiles"]
    profs = (_profiles_fixed(text, n_prof, path) if fixed
             else _profiles_tokens(text, text.index("\n") + 1 if "\n" in text else len(text), n_prof, path))

    dx, dy, dz = h["dx"], h["dy"], h["dz"]
    xs = np.array([p[0] for p in profs])
    ys = np.array([p[1] for p in profs])
    x0, y0 = float(xs.min()), float(ys.min())
    cols = np.rint((xs - x0) / dx).astype(np.int64)
    rows0 = np.rint((ys - y0) / dy).astype(np.int64)
    lengths = np.array([p[3].size for p in profs])
    for i in np.flatnonzero((np.abs((xs - x0) / dx - cols) > 0.01) | (np.abs((ys - y0) / dy - rows0) > 0.01)):
        raise SourceError(f"{path}: profile {i + 1} starts at ({xs[i]}, {ys[i]}), "
                          f"off the {dx}×{dy} lattice through ({x0}, {y0})")
    if len(set(cols.tolist())) != len(cols):
        raise SourceError(f"{path}: two profiles start in the same column")
    heights = np.full((int((rows0 + lengths).max()), int(cols.max()) + 1), np.nan)
    unit = FEET if h["z_units"] == 1 else 1.0
    for (x, y, datum, z), c, r0 in zip(profs, cols, rows0):
        v = (datum + z * dz) * unit
        v[z <= _VOID] = np.nan
        heights[r0:r0 + z.size, c] = v

    attrs = {"source": "USGS ASCII DEM", "title": h["name"], "z_units": "feet" if h["z_units"] == 1 else "metres",
             "xy_units": {0: "radians", 1: "feet", 2: "metres", 3: "arc-seconds"}.get(h["xy_units"], "unknown"),
             "resolution": (dx, dy, dz)}
    crs = None
    if h["ref_system"] == 1:
        attrs.update(crs_system="UTM", utm_zone=h["zone"])
        datum = h.get("datum")
        attrs["horizontal_datum"] = datum or "unspecified (NAD27 for files before 1992)"
        crs = f"EPSG:{_EPSG_UTM[datum] + h['zone']}" if datum in _EPSG_UTM else f"UTM zone {h['zone']}"
    elif h["ref_system"] == 0:
        attrs["crs_system"] = "geographic"
    elif h["ref_system"] == 2:
        attrs.update(crs_system="state plane", spcs_zone=h["zone"])
    if crs:
        attrs["crs"] = crs
    grid = HeightGrid(name=path.stem, heights=heights, origin=(x0, y0), spacing=(dx, dy), attributes=attrs)
    return SourceScene(grids=[grid], crs=crs, sources=[str(path)])


def load_npz(path, *, key: str | None = None, spacing=None) -> SourceScene:
    """A height grid stored as a 2-D array in a ``.npz`` file.

    The array is ``key``, else the only 2-D array, else one named
    elevation/heights/z/dem. Spacing comes from the file (``dx``/``dy`` or
    ``spacing``) when present, else from ``spacing`` (a number or (dx, dy)),
    else 1. When the file's ``ymin`` exceeds its ``ymax`` (matplotlib's
    sample stores the first row's y as ``ymin``), rows run south and are flipped.
    """
    path = Path(path)
    if path.stat().st_size == 0:
        raise SourceError(f"{path}: empty file")
    try:
        data = np.load(path, allow_pickle=False)
        arrays = {k: data[k] for k in data.files}
    except Exception as e:  # zipfile / format errors
        raise SourceError(f"{path}: not a readable .npz file ({e})") from None
    if key is None:
        two_d = [k for k, v in arrays.items() if v.ndim == 2]
        named = [k for k in ("elevation", "heights", "height", "z", "dem", "data") if k in arrays]
        if len(two_d) == 1:
            key = two_d[0]
        elif named:
            key = named[0]
        elif not two_d:
            raise SourceError(f"{path}: no 2-D array among {sorted(arrays)}")
        else:
            raise SourceError(f"{path}: several 2-D arrays {two_d}; pass key=")
    if key not in arrays:
        raise SourceError(f"{path}: no array {key!r} (has {sorted(arrays)})")
    z = arrays[key]
    if z.ndim != 2:
        raise SourceError(f"{path}: array {key!r} has shape {z.shape}, a height grid must be 2-D")
    if not np.issubdtype(z.dtype, np.number) or z.size == 0:
        raise SourceError(f"{path}: array {key!r} ({z.dtype}, shape {z.shape}) is not a non-empty numeric grid")
    heights = z.astype(np.float64)
    if np.isinf(heights).any():
        r, c = np.argwhere(np.isinf(heights))[0]
        raise SourceError(f"{path}: array {key!r}: infinite height at row {r}, col {c}")
    if np.isnan(heights).all():
        raise SourceError(f"{path}: array {key!r}: every height is NaN")

    def scalar(name):
        v = arrays.get(name)
        return float(v) if v is not None and v.size == 1 and np.isfinite(v) else None

    dx, dy = scalar("dx"), scalar("dy")
    if dx is None and "spacing" in arrays and np.size(arrays["spacing"]) in (1, 2):
        dx, dy = (float(s) for s in np.broadcast_to(arrays["spacing"].astype(float), (2,)))
    if dx is None and spacing is not None:
        dx, dy = (float(s) for s in np.broadcast_to(np.asarray(spacing, float), (2,)))
    dx = 1.0 if dx is None else dx
    dy = dx if dy is None else dy
    if not (dx > 0 and dy > 0 and math.isfinite(dx) and math.isfinite(dy)):
        raise SourceError(f"{path}: spacing ({dx}, {dy}) must be positive")
    xmin, ymin, ymax = scalar("xmin"), scalar("ymin"), scalar("ymax")
    attrs = {"source": "npz", "key": key}
    if ymin is not None and ymax is not None and ymin > ymax:
        heights = heights[::-1]
        ymin = ymax
        attrs["rows_flipped"] = True
    origin = (xmin if xmin is not None else 0.0, ymin if ymin is not None else 0.0)
    if xmin is not None and abs(origin[0]) <= 180 and abs(origin[1]) <= 90 and dx < 1:
        attrs["crs_system"] = "geographic (degrees, presumably)"
    grid = HeightGrid(name=path.stem, heights=heights, origin=origin, spacing=(dx, dy), attributes=attrs)
    return SourceScene(grids=[grid], sources=[str(path)])
