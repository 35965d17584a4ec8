"""Point-cloud files → ``PointCloud``: XYZ text, PLY points, LAS/LAZ (scanned trees).

What each format brings:

- **XYZ** (``.xyz``, ``.txt``): one point a line, ``x y z`` or ``x y z r g b``
  (colours 0–255), numbers separated by blanks; every line must have the same
  count, 3 or 6 — any other count is refused rather than guessed at (a seventh
  column may be intensity, a scalar field or a normal, depending on the tool).
  Blank lines and lines starting with ``#`` are skipped.
- **PLY** (``.ply``): the ``vertex`` element's ``x y z`` and, when present,
  ``red green blue`` and ``nx ny nz``; faces and other elements are ignored.
  ASCII bodies are read here (so an error names its line); binary bodies by
  trimesh's PLY reader, after the header has been checked against the file's
  length.
- **LAS/LAZ** (``.las``, ``.laz``, by laspy; LAZ needs its ``lazrs`` backend):
  scaled coordinates, 16-bit RGB when the point format has it; points classed
  as ground (2) or noise (7, 18) are left out, since a tree cut from a survey
  often keeps a ring of ground around its trunk.

Every failure is a ``SourceError`` naming the file and, for text, the line
(1-based, as an editor shows it); for binary files, the point and byte offset.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..source import PointCloud, SourceError

__all__ = ["POINT_CLOUD_SUFFIXES", "read_point_cloud", "read_xyz", "read_ply", "read_las"]

#: Classes of the ASPRS LAS specification a tree model leaves out: ground, low noise, high noise.
LAS_DROPPED_CLASSES = (2, 7, 18)
XYZ_COLUMNS = (3, 6)


def read_point_cloud(path: str | Path) -> PointCloud:
    """Read a point-cloud file by its suffix (``POINT_CLOUD_SUFFIXES``)."""
    path = Path(path)
    reader = POINT_CLOUD_SUFFIXES.get(path.suffix.lower())
    if reader is None:
        raise SourceError(f"{path}: not a point-cloud file (supported: {', '.join(POINT_CLOUD_SUFFIXES)})")
    if not path.is_file():
        raise SourceError(f"{path}: no such file")
    cloud = reader(path)
    if len(cloud) == 0:
        raise SourceError(f"{path}: no points")
    return cloud


# -- text --------------------------------------------------------------------------------------


def _decode(path: Path, raw: bytes, offset: int = 0) -> str:
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1 + offset
        raise SourceError(f"{path}: line {line}: not text (byte {exc.start + 1} is not UTF-8)") from None


def _table(path: Path, lines: list[str], first: int, columns: tuple[int, ...]) -> np.ndarray:
    """The numbers of ``lines`` as an (n, c) float64 table, c one of ``columns``, all finite.

    first : the file's line number of ``lines[0]``. Blank and ``#`` lines are skipped.
    """
    rows = [(first + i, line.split()) for i, line in enumerate(lines)]
    rows = [(no, tokens) for no, tokens in rows if tokens and not tokens[0].startswith("#")]
    if not rows:
        return np.zeros((0, columns[0]))
    counts = np.fromiter((len(tokens) for _, tokens in rows), np.int64, len(rows))
    want = int(counts[0]) if counts[0] in columns else columns[0]
    bad = np.flatnonzero(counts != want)
    if bad.size:
        no, tokens = rows[int(bad[0])]
        allowed = " or ".join(map(str, columns)) if counts[0] not in columns else str(want)
        raise SourceError(f"{path}: line {no}: {len(tokens)} columns, expected {allowed}")
    try:
        values = np.array([t for _, tokens in rows for t in tokens], np.float64).reshape(-1, want)
    except ValueError:
        for no, tokens in rows:  # error path only: find the line
            for t in tokens:
                try:
                    float(t)
                except ValueError:
                    raise SourceError(f"{path}: line {no}: {t!r} is not a number") from None
        raise
    finite = np.isfinite(values).all(axis=1)
    if not finite.all():
        no, tokens = rows[int(np.argmin(finite))]
        raise SourceError(f"{path}: line {no}: {' '.join(tokens)!r} is not finite (NaN or infinity)")
    return values


def _colours(path: Path, values: np.ndarray, line_of, top: float = 255.0) -> np.ndarray:
    """(n, 3) uint8 from colour columns in 0..top; the first one outside is named by ``line_of(i)``."""
    ok = ((values >= 0) & (values <= top)).all(axis=1)
    if not ok.all():
        i = int(np.argmin(ok))
        raise SourceError(f"{path}: {line_of(i)}: colour {values[i].tolist()} outside 0..{top:g}")
    return np.rint(values * (255.0 / top)).astype(np.uint8)


def read_xyz(path: str | Path) -> PointCloud:
    """``x y z`` or ``x y z r g b`` per line (see the module docstring)."""
    path = Path(path)
    lines = _decode(path, path.read_bytes()).splitlines()
    table = _table(path, lines, 1, XYZ_COLUMNS)
    if table.shape[0] == 0:
        raise SourceError(f"{path}: no points (empty file)")
    colors = None
    if table.shape[1] == 6:
        numbered = [i + 1 for i, line in enumerate(lines) if line.split() and not line.split()[0].startswith("#")]
        colors = _colours(path, table[:, 3:], lambda i: f"line {numbered[i]}")
    return PointCloud(table[:, :3], colors)


# -- PLY ---------------------------------------------------------------------------------------

_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def _ply_header(path: Path, raw: bytes) -> tuple[str, list[tuple[str, int, list[tuple[str, str]]]], int, int]:
    """(format, elements [(name, count, [(property, type or 'list')])], header bytes, header lines)."""
    end = raw.find(b"end_header")
    stop = raw.find(b"\n", end) if end >= 0 else -1
    if not raw.startswith(b"ply"):
        raise SourceError(f"{path}: line 1: not a PLY file (it must start with 'ply')")
    if end < 0 or stop < 0:
        raise SourceError(f"{path}: the PLY header has no end_header line (truncated header?)")
    lines = _decode(path, raw[:stop]).splitlines()
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    for no, line in enumerate(lines, 1):
        words = line.split()
        if not words or words[0] in ("ply", "comment", "obj_info", "end_header"):
            continue
        if words[0] == "format" and len(words) == 3:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements and len(words) == 3 and words[1] in _PLY_TYPES:
            elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
        elif words[0] == "property" and elements and len(words) == 5 and words[1] == "list":
            elements[-1][2].append((words[4], "list"))
        else:
            raise SourceError(f"{path}: line {no}: {line.strip()!r} is not a PLY header line")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise SourceError(f"{path}: the PLY header names no known format (ascii, binary_little_endian, "
                          f"binary_big_endian)")
    return fmt, elements, stop + 1, len(lines)


def read_ply(path: str | Path) -> PointCloud:
    """The ``vertex`` element of a PLY file as points (see the module docstring)."""
    path = Path(path)
    raw = path.read_bytes()
    if not raw:
        raise SourceError(f"{path}: no points (empty file)")
    fmt, elements, body, header_lines = _ply_header(path, raw)
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise SourceError(f"{path}: the PLY header declares no vertex element")
    at = names.index("vertex")
    _, count, props = elements[at]
    columns = [p for p, _ in props]
    if not {"x", "y", "z"} <= set(columns):
        raise SourceError(f"{path}: the PLY vertex element has no x, y and z properties")
    if count == 0:
        raise SourceError(f"{path}: no points (the header declares 0 vertices)")
    if fmt == "ascii":
        if any(t == "list" for _, t in props):
            raise SourceError(f"{path}: ASCII PLY vertices with list properties are not supported")
        lines = _decode(path, raw[body:], header_lines).splitlines()
        skip = sum(e[1] for e in elements[:at])
        block = lines[skip : skip + count]
        if len(block) < count:
            raise SourceError(f"{path}: line {header_lines + len(lines)}: truncated: the header declares {count} "
                              f"vertices, the file ends after {max(len(block), 0)}")
        table = _table(path, block, header_lines + skip + 1, (len(columns),))
        data = {c: table[:, k] for k, c in enumerate(columns)}
        first_line = header_lines + skip + 1
        line_of = lambda i: f"line {first_line + i}"
    else:
        data = _ply_binary(path, raw, fmt, elements, at, body)
        line_of = lambda i: f"vertex {i + 1}"
    xyz = np.column_stack([np.asarray(data[c], np.float64) for c in "xyz"])
    finite = np.isfinite(xyz).all(axis=1)
    if not finite.all():
        raise SourceError(f"{path}: {line_of(int(np.argmin(finite)))}: a coordinate is not finite (NaN or infinity)")
    colors = normals = None
    if {"red", "green", "blue"} <= set(columns):
        rgb = np.column_stack([np.asarray(data[c], np.float64) for c in ("red", "green", "blue")])
        top = 65535.0 if dict(props)["red"] in ("u2", "i2") else (1.0 if dict(props)["red"] in ("f4", "f8") else 255.0)
        colors = _colours(path, rgb, line_of, top)
    if {"nx", "ny", "nz"} <= set(columns):
        n = np.column_stack([np.asarray(data[c], np.float64) for c in ("nx", "ny", "nz")])
        length = np.linalg.norm(n, axis=1)
        if np.isfinite(length).all() and (length > 0).all():
            normals = n / length[:, None]
    return PointCloud(xyz, colors, normals)


def _ply_binary(path: Path, raw: bytes, fmt: str, elements: list, at: int, body: int) -> dict:
    """The vertex columns of a binary PLY, read by trimesh once the file's length is known to suffice."""
    import io

    import trimesh

    fixed = all(t != "list" for e in elements[: at + 1] for _, t in e[2])
    if fixed:
        order = "<" if fmt == "binary_little_endian" else ">"
        stride = [sum(np.dtype(order + t).itemsize for _, t in e[2]) for e in elements]
        start = body + sum(c * s for (_, c, _), s in zip(elements[:at], stride[:at]))
        count, size = elements[at][1], stride[at]
        have = (len(raw) - start) // size if size else 0
        if have < count:
            raise SourceError(f"{path}: truncated: the header declares {count} vertices of {size} bytes, the file "
                              f"ends in vertex {have + 1} (byte {len(raw)})")
    try:
        result = trimesh.exchange.ply.load_ply(io.BytesIO(raw))
    except Exception as exc:  # trimesh raises several unrelated types for a damaged body
        raise SourceError(f"{path}: truncated or damaged binary PLY ({exc})") from None
    vertex = (result.get("metadata") or {}).get("_ply_raw", {}).get("vertex")
    if vertex is None:
        raise SourceError(f"{path}: trimesh found no vertex data")
    data = vertex["data"]
    return {name: data[name] for name in data.dtype.names} if hasattr(data, "dtype") else dict(data)


# -- LAS / LAZ ---------------------------------------------------------------------------------


def read_las(path: str | Path) -> PointCloud:
    """Points of a LAS or LAZ file, without ground and noise (see the module docstring)."""
    import laspy

    path = Path(path)
    size = path.stat().st_size
    if size == 0:
        raise SourceError(f"{path}: no points (empty file)")
    try:
        with laspy.open(path) as reader:
            header = reader.header
            count = int(header.point_count)
            if count == 0:
                raise SourceError(f"{path}: no points (the header declares 0)")
            if not header.are_points_compressed:
                stride = header.point_format.size
                need = header.offset_to_point_data + count * stride
                if size < need:
                    whole = max(size - header.offset_to_point_data, 0) // stride
                    raise SourceError(f"{path}: truncated: the header declares {count} points of {stride} bytes, "
                                      f"the file ends in point {whole + 1} (byte {size})")
            las = reader.read()
    except SourceError:
        raise
    except Exception as exc:  # laspy and lazrs raise several unrelated types for a damaged file
        raise SourceError(f"{path}: not a readable LAS/LAZ file ({type(exc).__name__}: {exc})") from None
    xyz = np.column_stack([np.asarray(las.x, np.float64), np.asarray(las.y, np.float64),
                           np.asarray(las.z, np.float64)])
    finite = np.isfinite(xyz).all(axis=1)
    if not finite.all():
        raise SourceError(f"{path}: point {int(np.argmin(finite)) + 1}: a coordinate is not finite")
    dims = set(las.point_format.dimension_names)
    keep = ~np.isin(np.asarray(las.classification), LAS_DROPPED_CLASSES)
    if not keep.any():
        raise SourceError(f"{path}: every point is classed as ground or noise (classes {LAS_DROPPED_CLASSES})")
    colors = None
    if {"red", "green", "blue"} <= dims:
        rgb = np.column_stack([np.asarray(las[c], np.uint16) for c in ("red", "green", "blue")])
        # The spec asks for 16-bit colour; some writers store 8-bit values in those fields.
        if rgb.any():  # a format with colour fields whose writer left them all zero has no colour
            colors = (rgb >> 8 if rgb.max() > 255 else rgb).astype(np.uint8)[keep]
    return PointCloud(xyz[keep], colors)


POINT_CLOUD_SUFFIXES = {".xyz": read_xyz, ".txt": read_xyz, ".ply": read_ply, ".las": read_las, ".laz": read_las}
