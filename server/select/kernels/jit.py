"""How every kernel is compiled: ``jit`` (numba's ``njit`` with the options they share) and
``compile_module`` (a module's warm-up calls, in memory when numba's cache is unusable).

``cache=True`` keeps the machine code next to the module, or in the user's cache
directory when the package is read-only; when numba finds no usable cache at all the
kernels compile in memory, and every process then compiles them once. A module's
``compile_all()`` calls each of its kernels once with the argument types its callers
pass, so that the first real call neither compiles nor loads anything.
"""

from __future__ import annotations

import sys
from types import ModuleType

import numba

__all__ = ["jit", "compile_module"]


def jit(**options):
    """``numba.njit(cache=True, nogil=True, error_model="numpy", ...)``, without the cache when numba finds
    nowhere to keep it. nogil: the server solves sessions on a thread pool."""

    def wrap(fn):
        try:
            return numba.njit(cache=True, nogil=True, error_model="numpy", **options)(fn)
        except RuntimeError:  # "cannot cache function ...: no locator available" (read-only everywhere)
            return numba.njit(cache=False, nogil=True, error_model="numpy", **options)(fn)

    return wrap


def compile_module(module: ModuleType) -> None:
    """Run ``module.compile_all()``; if the cache numba chose cannot be read or written (a path under a
    file, say), drop the cache of the package's kernels (the module's and those it calls from its siblings)
    and compile them in memory instead."""
    try:
        module.compile_all()
    except OSError:
        from numba.core.caching import NullCache

        package = module.__name__.rpartition(".")[0] + "."
        siblings = [m for name, m in list(sys.modules.items()) if name.startswith(package) and m is not None]
        for fn in [f for m in siblings for f in list(vars(m).values())]:
            if isinstance(fn, numba.core.registry.CPUDispatcher):
                fn._cache = NullCache()
        module.compile_all()
