"""The walkable grid: where a walking camera may stand, and how high the ground is there.

A regular grid over the scene's ground plane (x, y; scenes are z-up). Each
cell holds the ground height (world z, metres) where a person can stand, or
NaN where they cannot (inside a building, on a wall, too steep, outside the
scene). The server builds it once per scene (``server.scene.walkable``) and
sends it in the welcome when a hello asks (``Hello.walkable``); the client
walks on it with collision and the server predicts a walking camera within
it — both read it through this one class.

On the wire it is a msgpack map of the grid's shape, origin and cell size and
the heights quantised to 16 bits over the grid's own height range (65,534
steps, 65,535 = not walkable: 3 cm steps on a 2 km mountain, a fraction of a
millimetre in a flat city — float16 would give metre steps at a mountain's
heights), zstd-compressed: a 1024 × 1024 grid of a city is a few hundred kB.
"""

from __future__ import annotations

from dataclasses import dataclass

import msgpack
import numpy as np
import zstandard

from .errors import ProtocolError

__all__ = ["WalkableGrid", "encode", "decode", "MAX_CELLS"]

#: A grid never has more cells than this (4096 × 4096).
MAX_CELLS = 1 << 24
#: Heights beyond this are refused (float16's range; no ground is higher).
MAX_HEIGHT = 60000.0


@dataclass(frozen=True)
class WalkableGrid:
    """Ground heights on a regular grid.

    origin : (x, y) of the grid's min corner (the outer corner of cell (0, 0)), metres
    cell : edge length of a square cell, metres
    ground : (ny, nx) float32 ground height of each cell, NaN where no one can stand; row j covers
        y ∈ [origin_y + j·cell, origin_y + (j+1)·cell), column i likewise in x
    """

    origin: tuple[float, float]
    cell: float
    ground: np.ndarray

    def __post_init__(self) -> None:
        g = np.asarray(self.ground, np.float32)
        if g.ndim != 2 or g.size == 0 or g.size > MAX_CELLS:
            raise ValueError(f"ground must be a non-empty 2-D array of at most {MAX_CELLS} cells, got {g.shape}")
        if not (np.isfinite(self.cell) and self.cell > 0):
            raise ValueError(f"cell must be a positive finite size, got {self.cell!r}")
        if not all(np.isfinite(v) for v in self.origin) or len(self.origin) != 2:
            raise ValueError(f"origin must be two finite coordinates, got {self.origin!r}")
        finite = g[np.isfinite(g)]
        if finite.size and np.abs(finite).max() > MAX_HEIGHT:
            raise ValueError(f"ground heights must lie within ±{MAX_HEIGHT} m")
        if np.isinf(g).any():
            raise ValueError("ground heights must be finite or NaN (not walkable)")
        object.__setattr__(self, "ground", g)
        object.__setattr__(self, "origin", (float(self.origin[0]), float(self.origin[1])))
        object.__setattr__(self, "cell", float(self.cell))

    @property
    def shape(self) -> tuple[int, int]:
        """(ny, nx)."""
        return self.ground.shape  # type: ignore[return-value]

    @property
    def bounds(self) -> np.ndarray:
        """(2, 2) float64 [[x_min, y_min], [x_max, y_max]] of the whole grid."""
        ny, nx = self.shape
        lo = np.array(self.origin)
        return np.stack([lo, lo + self.cell * np.array([nx, ny])])

    def cells(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cell (row, column) of points ``xy`` (n, 2) or (2,), and a mask of the points inside the grid."""
        p = np.atleast_2d(np.asarray(xy, np.float64))[:, :2]
        ij = np.floor((p - np.array(self.origin)) / self.cell).astype(np.int64)
        ny, nx = self.shape
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < nx) & (ij[:, 1] >= 0) & (ij[:, 1] < ny)
        return np.clip(ij[:, 1], 0, ny - 1), np.clip(ij[:, 0], 0, nx - 1), inside

    def height(self, xy: np.ndarray) -> np.ndarray:
        """Ground height (n,) float64 under points ``xy`` (n, 2+); NaN where not walkable or off the grid."""
        row, col, inside = self.cells(xy)
        return np.where(inside, self.ground[row, col].astype(np.float64), np.nan)

    def walkable(self, xy: np.ndarray) -> np.ndarray:
        """(n,) bool: a person can stand at each point."""
        return np.isfinite(self.height(xy))


#: The quantised value that marks a cell no one can stand on.
_BLOCKED = 65535


def encode(grid: WalkableGrid) -> bytes:
    """The grid as bytes for ``Welcome.walkable``."""
    ny, nx = grid.shape
    g = grid.ground.astype(np.float64)
    ok = np.isfinite(g)
    lo = float(g[ok].min()) if ok.any() else 0.0
    hi = float(g[ok].max()) if ok.any() else 0.0
    step = (hi - lo) / (_BLOCKED - 1) if hi > lo else 1.0
    q = np.full(g.shape, _BLOCKED, "<u2")
    q[ok] = np.round((g[ok] - lo) / step).astype("<u2")
    return msgpack.packb({"shape": [ny, nx], "origin": list(grid.origin), "cell": grid.cell, "low": lo,
                          "step": step, "u16": zstandard.ZstdCompressor(level=9).compress(q.tobytes())},
                         use_bin_type=True)


def decode(data: bytes) -> WalkableGrid:
    """Bytes from ``encode`` → the grid; raises ``ProtocolError("bad_walkable", …)`` naming what is wrong."""
    try:
        m = msgpack.unpackb(data, raw=False, strict_map_key=True)
        ny, nx = (int(v) for v in m["shape"])
        if ny <= 0 or nx <= 0 or ny * nx > MAX_CELLS:
            raise ValueError(f"shape {ny} × {nx} is empty or over {MAX_CELLS} cells")
        low, step = float(m["low"]), float(m["step"])
        if not (np.isfinite(low) and np.isfinite(step) and step > 0):
            raise ValueError(f"height range low={low!r}, step={step!r} is not finite and positive")
        raw = zstandard.ZstdDecompressor().decompress(m["u16"], max_output_size=2 * ny * nx)
        if len(raw) != 2 * ny * nx:
            raise ValueError(f"{len(raw)} bytes of heights for {ny} × {nx} cells")
        q = np.frombuffer(raw, "<u2").reshape(ny, nx)
        ground = np.where(q == _BLOCKED, np.nan, low + q.astype(np.float64) * step).astype(np.float32)
        return WalkableGrid(origin=tuple(float(v) for v in m["origin"]), cell=float(m["cell"]), ground=ground)
    except ProtocolError:
        raise
    except (ValueError, KeyError, TypeError, zstandard.ZstdError, msgpack.UnpackException) as exc:
        raise ProtocolError("bad_walkable", f"walkable grid: {exc}") from None
