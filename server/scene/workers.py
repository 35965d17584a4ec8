"""Worker processes for scene builds: one rule for when and how a build stage uses a pool.

The objects of a build (and the HLOD nodes of one depth) are independent, so a
stage maps one function over its jobs in worker processes and takes the
results back in job order: the result does not depend on the number of workers.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
from concurrent.futures import ProcessPoolExecutor
from typing import Callable, Iterable, Iterator

__all__ = ["POOL_MIN_JOBS", "default_workers", "process_pool", "pool_map"]

#: Below this many jobs a process pool costs more than it saves.
POOL_MIN_JOBS = 48


def default_workers() -> int:
    """Processes a build uses unless told otherwise: one per CPU, at most 8."""
    return min(8, os.cpu_count() or 1)


def process_pool(workers: int) -> ProcessPoolExecutor:
    """A pool of ``workers`` processes started the way that is safe in this process.

    fork is fast and works from any ``__main__`` (a REPL, stdin), but is unsafe
    once other threads exist, e.g. inside a server; then spawn, which needs an
    importable ``__main__`` (a script with a ``__name__ == "__main__"`` guard).
    """
    single = threading.active_count() == 1 and "fork" in multiprocessing.get_all_start_methods()
    context = multiprocessing.get_context("fork" if single else "spawn")
    return ProcessPoolExecutor(workers, mp_context=context)


def pool_map(fn: Callable, jobs: Iterable, workers: int, chunksize: int = 1) -> Iterator:
    """``fn`` over ``jobs``, results in job order; in this process when ``workers`` ≤ 1."""
    if workers <= 1:
        yield from map(fn, jobs)
        return
    with process_pool(workers) as pool:
        yield from pool.map(fn, jobs, chunksize=chunksize)
