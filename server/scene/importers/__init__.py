"""Importers: files → SourceScene. ``load_source`` picks one by the file's suffix.

Importers are imported lazily inside the dispatcher, so a missing optional one
(or its dependency) only matters for the files that need it.
"""

from __future__ import annotations

from pathlib import Path

from ..source import SourceError, SourceScene

__all__ = ["SUPPORTED_SUFFIXES", "load_source", "load_cityjson", "load_mesh_file"]

# suffix → (module, function, what it is)
_IMPORTERS: dict[str, tuple[str, str, str]] = {
    ".city.json": ("cityjson", "load_cityjson", "CityJSON"),
    ".json": ("cityjson", "load_cityjson", "CityJSON"),
    ".gltf": ("meshes", "load_mesh_file", "glTF"),
    ".glb": ("meshes", "load_mesh_file", "glTF binary"),
    ".obj": ("meshes", "load_mesh_file", "Wavefront OBJ"),
    ".ply": ("meshes", "load_mesh_file", "PLY"),
    ".dem": ("dem", "load_dem", "USGS ASCII DEM"),
    ".npz": ("dem", "load_npz", "height grid (numpy .npz)"),
    ".gml": ("citygml", "load_citygml", "CityGML"),
}
SUPPORTED_SUFFIXES = tuple(_IMPORTERS)


def load_source(path: str | Path) -> SourceScene:
    """Import ``path`` with the importer its suffix names; ``SourceError`` for unknown kinds."""
    path = Path(path)
    name = path.name.lower()
    suffix = next((s for s in _IMPORTERS if name.endswith(s)), None)
    if suffix is None:
        kinds = ", ".join(f"{s} ({what})" for s, (_, _, what) in _IMPORTERS.items())
        raise SourceError(f"{path}: unsupported file type {path.suffix or '(no suffix)'!r}; supported: {kinds}")
    module, function, what = _IMPORTERS[suffix]
    from importlib import import_module

    try:
        loader = getattr(import_module(f"{__name__}.{module}"), function)
    except (ImportError, AttributeError) as exc:
        raise SourceError(f"{path}: the {what} importer is not available ({exc})") from None
    return loader(path)


def __getattr__(name: str):
    """``from server.scene.importers import load_cityjson`` without importing every importer up front."""
    lazy = {"load_cityjson": "cityjson", "load_mesh_file": "meshes", "load_dem": "dem", "load_npz": "dem",
            "load_citygml": "citygml"}
    if name in lazy:
        from importlib import import_module

        return getattr(import_module(f"{__name__}.{lazy[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
