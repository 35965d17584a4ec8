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

__all__ = ["VARIABLE", "raster_threads"]

#: The environment variable llvmpipe reads its rasterizer thread count from when it makes a screen.
VARIABLE = "LP_NUM_THREADS"


def raster_threads(environ=os.environ, cores=None) -> str | None:
    """Set ``LP_NUM_THREADS`` to 1 where this process may run on one core and it is unset; call it before the
    first GL context is made. ``cores``: the cores the process may use (default: its affinity). Returns the
    value in force (None: llvmpipe's own choice)."""
    if VARIABLE in environ:
        return environ[VARIABLE]
    if cores is None:
        if not hasattr(os, "sched_getaffinity"):
            return None
        cores = os.sched_getaffinity(0)
    if len(cores) == 1:
        environ[VARIABLE] = "1"
        return "1"
    return None
