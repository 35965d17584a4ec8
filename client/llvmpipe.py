"""Mesa's llvmpipe, the software renderer the client draws with where there is no GPU, on a single core.

llvmpipe sizes its pool of rasterizer threads from the cores the process may
use, and with one core it keeps none: it rasterizes in the thread that draws.
That mode is much dearer than one rasterizer thread on the same core — the same
frames spend several times the system time — and one core is what a client
gets when it is pinned (the evaluation pins server and client apart, a
container may be given one core). So where a process may run on one core only,
the client asks for one rasterizer thread, unless the user chose a number.
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from typing import Iterator, MutableMapping

__all__ = ["VARIABLE", "raster_threads"]

#: The environment variable llvmpipe reads its rasterizer thread count from when it makes a screen.
VARIABLE = "LP_NUM_THREADS"


@contextmanager
def raster_threads(environ: MutableMapping[str, str] = os.environ, cores=None) -> Iterator[str | None]:
    """Around the making of a GL context: ``LP_NUM_THREADS`` is 1 where this thread may run on one core and the
    variable is unset, and the environment is as it was afterwards — the pin is the calling thread's, often for
    a while only (the evaluation lifts it after its runs), and the processes this one starts later must not
    inherit it. ``cores``: the cores the thread may use (default: its affinity). Yields the value in force
    (None: llvmpipe's own choice)."""
    if VARIABLE in environ:
        yield environ[VARIABLE]
        return
    if cores is None:
        cores = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else ()
    if len(cores) != 1:
        yield None
        return
    environ[VARIABLE] = "1"
    try:
        yield "1"
    finally:
        environ.pop(VARIABLE, None)
