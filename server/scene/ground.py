"""The ground under a scene that brings none: a height grid under its footprints, built as terrain.

A city model without terrain (a CityJSON or CityGML file of buildings, a glTF
of a few houses) floats in the sky. The builder lays a ground under it
(``BuildOptions.ground``): a ``HeightGrid`` over the objects' plan extent,
padded on every side, that goes through the same terrain quadtree as a DEM
(``server.scene.terrain``: patches with skirts, crack-free at any cut, coarse
patches far away). Flat where the city is flat, so its error is 0 and one coarse
patch draws it.

Its height follows the objects' bases, never above them: at each sample, the
bases (each object's lowest point) linearly interpolated between the objects'
centres (the nearest base outside their hull), then lowered to the lowest base
of every object whose plan box covers the sample (its steps blurred into ramps
outside the boxes), less ``SINK`` so that the
buildings' own ground surfaces do not fight it in the depth buffer. On flat
data that is the lowest ground height under the footprints; on a slope
(Berlin's blocks stand 4 m apart in height) no building stands on stilts.

Only a city gets one — a scene with buildings (``BUILDING_CLASSES``: a CityJSON or
CityGML city, an IFC house, a glTF whose nodes are named ``house_…``); a glTF of a
chair stays a chair in space. A scene that has terrain — a height grid, or an object
of a terrain class (``TERRAIN_CLASSES``: a TIN relief, a generated city's ground
tiles) — gets none.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.interpolate import griddata

from .source import HeightGrid, SourceScene

__all__ = ["GROUND_NAME", "TERRAIN_CLASSES", "BUILDING_CLASSES", "SINK", "needs_ground", "ground_grid"]

#: The generated ground's grid name (its patches are ``ground/patch_<j>``) and class (``server.scene.palette``).
GROUND_NAME = "ground"
#: Object classes that are the scene's ground already.
TERRAIN_CLASSES = ("terrain", "tinrelief", "ground", "relieffeature", "landuse")
#: Object classes that make a scene a city, which stands on a ground.
BUILDING_CLASSES = ("building", "buildingpart", "building_part", "house", "bridge", "bridgepart", "tunnel")
#: How far below the objects' bases the ground lies (metres).
SINK = 0.05


def needs_ground(source: SourceScene) -> bool:
    """Whether the scene is a city (it has buildings) with neither a height grid nor an object of a terrain class."""
    if source.grids or not any(o.cls.lower() in BUILDING_CLASSES for o in source.objects):
        return False
    return not any(o.cls.lower() in TERRAIN_CLASSES for o in source.objects)


def ground_grid(source: SourceScene, *, pad: float = 0.5, min_pad: float = 50.0, cells: int = 128) -> HeightGrid:
    """The ground's height grid under ``source``'s objects (module docstring), in source coordinates.

    pad     : padding on every side, as a share of the plan extent's larger side
    min_pad : the least padding (metres), so a single house gets a garden
    cells   : grid cells along the larger side (a multiple of the terrain patch keeps the quadtree full)
    Raises ValueError when the scene has no mesh vertices.
    """
    boxes = [(m.positions.min(axis=0), m.positions.max(axis=0)) for o in source.objects
             for m in o.levels[-1:] if m.n_vertices]
    if not boxes:
        raise ValueError("the scene holds no mesh to lay a ground under")
    lo = np.array([b[0] for b in boxes])
    hi = np.array([b[1] for b in boxes])
    base = lo[:, 2]
    extent = float(np.max(hi[:, :2].max(axis=0) - lo[:, :2].min(axis=0)))
    margin = max(min_pad, pad * extent)
    x0, y0 = lo[:, :2].min(axis=0) - margin
    x1, y1 = hi[:, :2].max(axis=0) + margin
    step = max(x1 - x0, y1 - y0) / cells
    nx, ny = int(np.ceil((x1 - x0) / step)) + 1, int(np.ceil((y1 - y0) / step)) + 1
    gx, gy = np.meshgrid(x0 + step * np.arange(nx), y0 + step * np.arange(ny))
    centres = (lo[:, :2] + hi[:, :2]) / 2
    heights = np.full(gx.shape, float(base.min()))
    if len(boxes) >= 3 and np.ptp(base) > 0:
        try:
            linear = griddata(centres, base, (gx, gy), method="linear")
        except Exception:  # collinear or coincident centres: Qhull cannot triangulate them
            linear = np.full(gx.shape, np.nan)
        nearest = griddata(centres, base, (gx, gy), method="nearest")
        heights = np.where(np.isfinite(linear), linear, nearest)
    # Never above an object's base where its plan box (grown by a cell) covers the ground.
    c0 = np.clip(np.floor((lo[:, 0] - x0) / step).astype(np.int64) - 1, 0, nx - 1)
    c1 = np.clip(np.ceil((hi[:, 0] - x0) / step).astype(np.int64) + 1, 0, nx - 1)
    r0 = np.clip(np.floor((lo[:, 1] - y0) / step).astype(np.int64) - 1, 0, ny - 1)
    r1 = np.clip(np.ceil((hi[:, 1] - y0) / step).astype(np.int64) + 1, 0, ny - 1)
    for k in range(base.size):
        block = heights[r0[k]:r1[k] + 1, c0[k]:c1[k] + 1]
        np.minimum(block, base[k], out=block)
    # The lowering leaves steps at the boxes' edges; a blur kept below them turns each into a ramp outside.
    heights = np.minimum(ndimage.gaussian_filter(heights, 2.0, mode="nearest"), heights)
    return HeightGrid(GROUND_NAME, heights - SINK, (float(x0), float(y0)), (float(step), float(step)),
                      {"class": "ground", "generated": True})
