"""The selection's compiled kernels (numba), and the one warm-up that makes them ready.

Modules, one concern each, all pure functions of arrays:

- ``hull``: each object's upper concave hull of its options (the greedy's and the
  incremental solver's first pass), and its start on the hull;
- ``cut``: the greedy's radix cut of every increment at the budget, fill rounds, totals;
- ``coherent``: the incremental solver's coherent step in one pass;
- ``view``: culling, projection and the F&S benefit of a selection's cameras;
- ``fold``: the online cost model's frame reports, folded in one pass (``choose``: its choice of rung);
- ``delta``: a delta's morph marking, and its level ranges expanded into the cache mirror's update;
- ``motion``: the path predictor's robust line fit;
- ``jit``: how they are all compiled.

Each has its vectorised numpy reference beside the code that calls it, and the
solvers and the selection run that reference until the kernels are ready:
``compiled()`` is None until then. Compiling takes seconds (loading from numba's
cache much less), so nothing compiles on import: ``start_warm_up`` — called by the
server's start-up, the benchmarks, the test session and the bootstrap — compiles (or
loads) every kernel in a daemon thread, ``warm_up(timeout)`` also waits for it, and
``use_kernels`` forces one path (tests, benchmarks). Importing this package imports
neither numba nor a kernel module.
"""

from __future__ import annotations

import atexit
import threading
from dataclasses import dataclass
from types import ModuleType

__all__ = ["Compiled", "compiled", "start_warm_up", "warm_up", "use_kernels", "OFF"]

#: Settings (the WALKSTREAM_NUMBA environment variable, as the caller reads it) that keep the kernels off.
OFF = ("0", "false", "no", "off")


@dataclass(frozen=True)
class Compiled:
    """The kernel modules, once every kernel in them is compiled."""

    hull: ModuleType
    cut: ModuleType
    coherent: ModuleType
    view: ModuleType
    fold: ModuleType
    delta: ModuleType
    motion: ModuleType


_mode: bool | None = None  # None: kernels once warm; True: always (waits for the compile); False: never
_ready: Compiled | None = None
_error: BaseException | None = None
_done = threading.Event()
_thread: threading.Thread | None = None
_start_lock = threading.Lock()


def _warm() -> None:
    global _ready, _error
    try:
        from . import coherent, cut, delta, fold, hull, motion, view
        from .jit import compile_module

        for module in (hull, cut, coherent, view, fold, delta, motion):
            compile_module(module)
        _ready = Compiled(hull=hull, cut=cut, coherent=coherent, view=view, fold=fold, delta=delta, motion=motion)
    except Exception as e:  # numba missing or broken: the numpy reference stays in charge
        _error = e
    finally:
        _done.set()


def start_warm_up(setting: str | None = None) -> None:
    """Start compiling (or loading from numba's cache) every kernel in a daemon thread; once per process.

    setting : the WALKSTREAM_NUMBA setting as the caller read it (None: the default, kernels once
              warm). One of ``OFF``: the kernels stay off and the numpy reference runs throughout;
              "wait": every solve waits for the kernels (benchmarks, tests of the compiled path).
    Later calls change nothing.
    """
    global _thread, _mode
    with _start_lock:
        if _thread is not None or _done.is_set():
            return
        if setting in OFF:
            _done.set()
            return
        if setting == "wait":
            _mode = True
        _thread = threading.Thread(target=_warm, name="walkstream-numba-warm-up", daemon=True)
        _thread.start()
        atexit.register(_join_warm_up)


def _join_warm_up() -> None:
    # Let a compile in progress end before the interpreter tears down (LLVM in a dying thread).
    if _thread is not None:
        _thread.join(timeout=30.0)


def warm_up(timeout: float | None = None, setting: str | None = None) -> bool:
    """``start_warm_up(setting)`` and wait until the kernels are ready (at most ``timeout`` s); True if
    they are in use. The caller times it if it wants to know how long that took."""
    start_warm_up(setting)
    _done.wait(timeout)
    return _ready is not None


def use_kernels(flag: bool | None) -> None:
    """Force the compiled kernels (True: waits for the compile), the numpy reference (False),
    or go back to the default (None: kernels as soon as they are warm)."""
    global _mode
    _mode = flag
    if flag and not warm_up():
        raise RuntimeError(f"compiled kernels unavailable: {_error!r}")


def compiled() -> Compiled | None:
    """The kernels if the solvers and the selection should use them for this call, else None (numpy)."""
    if _mode is False:
        return None
    if _mode is True and _ready is None:
        warm_up()
    return _ready
