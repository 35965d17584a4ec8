"""A synthetic city for tests of tours: blocks of box buildings between streets on gently sloping ground."""

from __future__ import annotations

import numpy as np
import trimesh

from proto.walkable import WalkableGrid
from server.scene.source import Mesh, SourceObject, SourceScene
from server.scene.streets import dense_blocks, street_loop


class City:
    """A synthetic city: blocks of box buildings between streets, on ground that slopes a little.

    lo, hi : (n, 3) the buildings' boxes; grid: the walkable grid (a cell a box touches is blocked)
    """

    def __init__(self, seed: int, cell: float = 0.5) -> None:
        rng = np.random.default_rng(seed)
        nbx, nby = (int(v) for v in rng.integers(3, 6, 2))
        street = float(rng.uniform(8.0, 14.0))
        widths, depths = rng.uniform(15.0, 35.0, nbx), rng.uniform(15.0, 35.0, nby)
        x0 = street + np.concatenate([[0.0], np.cumsum(widths + street)[:-1]])
        y0 = street + np.concatenate([[0.0], np.cumsum(depths + street)[:-1]])
        bx, by = np.meshgrid(np.arange(nbx), np.arange(nby), indexing="ij")
        bx, by = bx.reshape(-1), by.reshape(-1)
        keep = rng.random(bx.size) < 0.85  # some blocks are squares
        keep[0] = True
        bx, by = bx[keep], by[keep]
        self.slope = rng.uniform(-0.04, 0.04, 2)
        self.base = float(rng.uniform(-5.0, 20.0))
        lo2 = np.column_stack([x0[bx], y0[by]])
        hi2 = lo2 + np.column_stack([widths[bx], depths[by]])
        z0 = self.ground(lo2) - 0.5
        self.lo = np.column_stack([lo2, z0])
        self.hi = np.column_stack([hi2, z0 + rng.uniform(6.0, 45.0, len(lo2))])
        ext = np.array([x0[-1] + widths[-1] + street, y0[-1] + depths[-1] + street])
        nx, ny = (int(v) for v in np.ceil(ext / cell))
        ys, xs = np.mgrid[0:ny, 0:nx]
        centres = (np.stack([xs, ys], axis=-1) + 0.5) * cell
        ground = self.ground(centres.reshape(-1, 2)).reshape(ny, nx)
        blocked = np.zeros((ny, nx), bool)
        for a, b in zip(lo2, hi2):  # every cell the box touches
            c0, r0 = np.floor(a / cell).astype(int)
            c1, r1 = np.ceil(b / cell).astype(int)
            blocked[r0:r1, c0:c1] = True
        self.grid = WalkableGrid((0.0, 0.0), cell, np.where(blocked, np.nan, ground).astype(np.float32))

    def ground(self, xy: np.ndarray) -> np.ndarray:
        return self.base + np.asarray(xy, np.float64) @ self.slope

    def inside(self, xy: np.ndarray) -> np.ndarray:
        """(n,) bool: points inside some building's footprint."""
        p = np.asarray(xy)[:, None, :2]
        return ((p > self.lo[None, :, :2]) & (p < self.hi[None, :, :2])).all(axis=2).any(axis=1)

    def roof_under(self, xy: np.ndarray) -> np.ndarray:
        """(n,) the highest roof whose footprint holds each point (−inf where none does)."""
        p = np.asarray(xy)[:, None, :2]
        over = ((p >= self.lo[None, :, :2]) & (p <= self.hi[None, :, :2])).all(axis=2)
        return np.where(over, self.hi[None, :, 2], -np.inf).max(axis=1)

    def loop(self, budget: float, min_length: float):
        blocks = dense_blocks(self.grid, self.lo[:, :2], self.hi[:, :2])
        return street_loop(self.grid, blocks, budget, min_length)


def box(lo, hi) -> Mesh:
    m = trimesh.creation.box(np.subtract(hi, lo))
    m.apply_translation((np.asarray(lo) + np.asarray(hi)) / 2)
    return Mesh(np.asarray(m.vertices), np.asarray(m.faces))


def city_source(seed: int = 5) -> tuple[SourceScene, City]:
    city = City(seed)
    x1, y1 = city.grid.bounds[1]
    ground = Mesh(np.array([[0, 0, 0], [x1, 0, 0], [x1, y1, 0], [0, y1, 0]], float), np.array([[0, 1, 2], [0, 2, 3]]))
    objects = [SourceObject("ground", "ground", [ground])]
    objects += [SourceObject(f"b{i}", "building", [box(a, b)]) for i, (a, b) in enumerate(zip(city.lo, city.hi))]
    return SourceScene(objects=objects), city
