"""The scene stores the benchmarks and evaluations share: cached named stores and scene resolution.

A named scene is built once into ``DEFAULT_CACHE`` under a name that carries the store's
``SCHEMA_VERSION``, the builds' ``BUILD_VERSION`` (``server.scene.catalog``) and the
generator's ``VERSION``, where a generator has one (``cache_key``), so a change to any of
them builds anew instead of reading a stale store; old files are left where they are.
A progress bar on stderr follows a build. ``resolve_scene`` turns what a user typed (a store, a named scene or a
source file) into a store.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Callable

from server.cli import progress_bar

__all__ = ["DEFAULT_CACHE", "cache_key", "demo_store", "build_demo", "cached_denhaag", "cached_auditorium", "scene_version",
           "resolve_scene"]

Progress = Callable[[str, int, int], None]

DEFAULT_CACHE = Path.home() / ".cache" / "walkstream"
SOURCE_SUFFIXES = (".city.json", ".json", ".gltf", ".glb", ".obj", ".ply", ".dem", ".npz", ".gml")


def cache_key(stem: str) -> str:
    """The cached store's file name for ``stem`` ("denhaag-s0", a user file's name and digest):
    ``{stem}-v{SCHEMA_VERSION}-b{BUILD_VERSION}.db``, the one place every key is made."""
    from server.scene.catalog import BUILD_VERSION
    from server.scene.store import SCHEMA_VERSION

    return f"{stem}-v{SCHEMA_VERSION}-b{BUILD_VERSION}.db"


def demo_store(objects: int, seed: int) -> Path:
    """Where the demo scene of ``objects`` objects and ``seed`` is cached."""
    return DEFAULT_CACHE / cache_key(f"demo-n{objects}-s{seed}")


def build_demo(path: Path, objects: int, seed: int, quiet: bool = False) -> dict:
    """Build the demo scene into ``path`` behind a progress bar; the build's summary."""
    from server.scene.catalog import build_named

    path.parent.mkdir(parents=True, exist_ok=True)
    bar, tick = progress_bar("building demo", quiet)
    with bar:
        return build_named("demo", path, seed=seed, size=objects, progress=tick)


def cached_denhaag(size: int | None = None, seed: int = 0, quiet: bool = False) -> Path:
    """The Den Haag store the benchmarks use, under ``DEFAULT_CACHE``; built (progress bar on stderr) if missing."""
    from server.scene.catalog import build_named

    tag = "" if size is None else f"-n{size}"
    path = DEFAULT_CACHE / cache_key(f"denhaag{tag}-s{seed}")
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        bar, tick = progress_bar("building denhaag", quiet)
        with bar:
            build_named("denhaag", path, seed=seed, size=size, progress=tick)
    return path


def cached_auditorium(quiet: bool) -> Path:
    """The auditorium store the benchmarks share, under ``DEFAULT_CACHE``; built (progress bar) if missing."""
    from server.scene.catalog import build_named

    store = DEFAULT_CACHE / cache_key(f"auditorium-s0{scene_version('auditorium')}")
    if not store.exists():
        store.parent.mkdir(parents=True, exist_ok=True)
        bar, tick = progress_bar("building auditorium", quiet)
        with bar:
            build_named("auditorium", store, seed=0, progress=tick)
    return store


def scene_version(name: str) -> str:
    """A named scene's generator version as a cache-key suffix ("-g2"), or "" for a scene without one."""
    import importlib

    try:
        module = importlib.import_module(f"server.scene.generate.{name}")
    except ImportError:
        return ""
    version = getattr(module, "VERSION", None)
    return f"-g{version}" if version is not None else ""


def resolve_scene(arg: str | Path, *, seed: int = 0, cache_dir: str | Path | None = None,
                  progress: Progress | None = None) -> tuple[Path, str]:
    """(store path, scene name) for what a user typed: a store, a named scene or a source file.

    A ``.db`` file is opened for its name. A named scene (demo, auditorium, denhaag, sthelens, megacity) is
    built once into ``cache_dir/{name}-s{seed}[-g{generator VERSION}]-v{SCHEMA_VERSION}-b{BUILD_VERSION}.db``.
    A user's CityJSON, glTF/GLB, OBJ, PLY, USGS DEM, .npz or CityGML file is built once (with generated
    tours) into ``cache_dir/{stem}-{sha256[:16]}-v{SCHEMA_VERSION}-b{BUILD_VERSION}.db``, keyed by its
    content, so an edited file builds anew (``cache_key``). ``cache_dir`` defaults to ~/.cache/walkstream. ValueError says what was wrong with anything else.
    """
    from server.scene.catalog import SCENES, build_named, build_path, is_named
    from server.scene.source import SourceError
    from server.scene.store import SceneStore, StoreError

    cache = Path(cache_dir) if cache_dir is not None else DEFAULT_CACHE
    text = str(arg)
    path = Path(text).expanduser()
    names = ", ".join(["demo", *SCENES])

    def name_of(p: Path) -> str:
        try:
            with SceneStore.open(p) as s:
                return s.index.name
        except StoreError as exc:
            raise ValueError(f"{p} is not a usable scene store: {exc}") from None

    if path.suffix.lower() == ".db":
        if not path.is_file():
            raise ValueError(f"no such scene store: {path}")
        return path, name_of(path)
    if is_named(text) and not path.exists():
        target = cache / cache_key(f"{text}-s{seed}{scene_version(text)}")
        if not target.exists():
            target.parent.mkdir(parents=True, exist_ok=True)
            build_named(text, target, seed=seed, progress=progress)
        return target, name_of(target)
    if path.is_file() and path.name.lower().endswith(SOURCE_SUFFIXES):
        suffix = next(x for x in SOURCE_SUFFIXES if path.name.lower().endswith(x))
        digest = _file_digest(path, suffix)
        stem = path.name.split(".")[0] or "scene"
        target = cache / cache_key(f"{stem}-{digest[:16]}")
        if not target.exists():
            target.parent.mkdir(parents=True, exist_ok=True)
            try:
                build_path(path, target, progress=progress)
            except (SourceError, StoreError) as exc:
                raise ValueError(f"cannot build a scene from {path}: {exc}") from None
        return target, name_of(target)
    if path.is_file():
        raise ValueError(f"{path}: not a scene store (.db) nor a source walkstream can import "
                         f"({', '.join(SOURCE_SUFFIXES)})")
    raise ValueError(f"{text!r} is neither a scene store (.db), a named scene ({names}) nor an existing "
                     f"source file (CityJSON, glTF/GLB, OBJ, PLY, USGS DEM, .npz, CityGML)")


def _file_digest(path: Path, suffix: str) -> str:
    """sha256 of the importer's suffix and the file's bytes: the same bytes read as another kind differ."""
    h = hashlib.sha256(suffix.encode())
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()
