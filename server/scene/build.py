"""Build the demo scene store: generate, simplify, measure error, encode, write.

Each object is independent (its mesh derives from (seed, index) alone), so
the work — mesh generation, the LOD chain with its geomorph maps, the error of
each level and the encoding — runs in worker processes and only the finished payloads travel
back; the parent writes them in object order through one ``SceneWriter``
transaction. The result does not depend on the number of workers.

Run it::

    python -m server.scene.build demo.db --objects 576 --seed 0
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from proto.geometry import encode_geometry
from proto.morph import encode_morph

from .demo import DemoObject, generate_demo
from .lod import build_chain
from .store import SceneStore, SceneWriter, object_box

__all__ = ["build_demo", "build_object"]

#: Below this many objects a process pool costs more than it saves.
_POOL_MIN_OBJECTS = 48


def build_object(
    obj: DemoObject,
) -> tuple[DemoObject, np.ndarray, np.ndarray, list[float], list[bytes], list[bytes | None]]:
    """One object's store rows: (object, box lo (3,), box hi (3,), errors per level,
    geometry payloads per level, morph payloads per level).

    Levels are coarsest → finest; every level is quantized in one box
    (``object_box``) and stored in the chain's GPU order (``reorder=False``), so
    the morph maps (``proto.morph``, from the simplifier's edge collapses) index
    the stored vertices: entry k maps level k's vertices onto level k − 1's; entry 0 is None.
    """
    positions, faces = obj.mesh()
    chain = build_chain(positions, faces, morph="collapse")
    lo, hi = object_box(chain.levels)
    blobs = [encode_geometry(p, f, lo, hi, reorder=False) for p, f in chain.levels]
    morphs = [None if m is None else encode_morph(m, chain.levels[k - 1][0].shape[0])
              for k, m in enumerate(chain.morph)]
    return obj, lo, hi, chain.errors, blobs, morphs


def _results(objects: list[DemoObject], workers: int) -> Iterator[tuple]:
    if workers <= 1:
        yield from map(build_object, objects)
        return
    # fork is fast and works from any __main__ (a REPL, stdin), but is unsafe
    # once other threads exist, e.g. inside a server; then spawn, which needs
    # an importable __main__ (a script with a ``__name__ == "__main__"`` guard).
    single = threading.active_count() == 1 and "fork" in multiprocessing.get_all_start_methods()
    context = multiprocessing.get_context("fork" if single else "spawn")
    with ProcessPoolExecutor(workers, mp_context=context) as pool:
        yield from pool.map(build_object, objects, chunksize=4)


def build_demo(
    path: str | os.PathLike[str],
    *,
    objects: int = 576,
    seed: int = 0,
    progress: Callable[[int, int], None] | None = None,
    workers: int | None = None,
) -> dict:
    """Generate the demo scene and write it to a new store at ``path`` (atomically).

    objects  : sculptures (ground tiles are added: 16 for the default size)
    progress : called as progress(done, total) after each object is written
    workers  : processes; default one per CPU (at most 8), and none for small scenes

    Returns a summary: path, objects, representations, triangles (full detail),
    triangles_per_level (list, level 0 = coarsest, over objects having that
    level), bytes (file size), geometry_bytes, seconds.
    """
    started = time.perf_counter()
    scene = generate_demo(objects=objects, seed=seed)
    total = len(scene.objects)
    if workers is None:
        workers = 1 if objects < _POOL_MIN_OBJECTS else min(8, os.cpu_count() or 1)
    reps = geometry_bytes = 0
    with SceneWriter(path, name=scene.name, generator="walkstream demo", seed=seed,
                     class_names=scene.class_names) as writer:
        for done, (obj, lo, hi, errors, blobs, morphs) in enumerate(_results(scene.objects, workers), 1):
            writer.add_encoded(obj.name, obj.cls, lo, hi, errors, blobs, morphs=morphs)
            reps += len(blobs)
            geometry_bytes += sum(len(b) for b in blobs)
            if progress is not None:
                progress(done, total)
        writer.set_tour(scene.tour)
        writer.set_start(scene.start)
    with SceneStore.open(path) as store:
        idx = store.index
        full = idx.rep_first + idx.rep_count - 1
        triangles = int(idx.rep_faces[full].sum())
        per_level = np.bincount(idx.rep_level, weights=idx.rep_faces).astype(np.int64).tolist()
    return {
        "path": str(path),
        "objects": total,
        "representations": reps,
        "triangles": triangles,
        "triangles_per_level": per_level,
        "bytes": Path(path).stat().st_size,
        "geometry_bytes": geometry_bytes,
        "seconds": round(time.perf_counter() - started, 2),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Build the walkstream demo scene store.")
    parser.add_argument("path", type=Path)
    parser.add_argument("--objects", type=int, default=576)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=None)
    args = parser.parse_args(argv)

    def report(done: int, total: int) -> None:
        if done == total or done % 50 == 0:
            print(f"\r{done}/{total} objects", end="\n" if done == total else "", file=sys.stderr, flush=True)

    summary = build_demo(args.path, objects=args.objects, seed=args.seed, progress=report, workers=args.workers)
    for key, value in summary.items():
        print(f"{key}: {value}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
