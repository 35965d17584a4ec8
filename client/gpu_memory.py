"""GPU memory in use, where the driver tells it.

OpenGL has no core query for memory. NVIDIA's drivers and Mesa's radeonsi (AMD) answer
``GL_NVX_gpu_memory_info``: the dedicated memory's total and what is still available, in KiB; what
the kiosk reports is their difference (the board's memory in use — on a kiosk, its own). Mesa's
software renderers (llvmpipe, here) and most others answer nothing, and the heartbeat then says null
rather than a guess. ``GL_ATI_meminfo`` gives only the free memory, not the total, so it is not used.

moderngl has no call for an arbitrary ``glGetIntegerv``; ``gl_integer`` makes it through libglvnd's
``libOpenGL``, which sends it to the context current on the calling thread (the renderer's).
"""

from __future__ import annotations

import ctypes
import ctypes.util
from typing import Callable

__all__ = ["gpu_memory", "gl_integer", "NVX_EXTENSION"]

NVX_EXTENSION = "GL_NVX_gpu_memory_info"
_TOTAL_KIB = 0x9048  # GL_GPU_MEMORY_INFO_TOTAL_AVAILABLE_MEMORY_NVX
_AVAILABLE_KIB = 0x9049  # GL_GPU_MEMORY_INFO_CURRENT_AVAILABLE_VIDMEM_NVX

_lib: ctypes.CDLL | None = None


def gl_integer(name: int) -> int:
    """``glGetIntegerv(name)`` in the context current on this thread."""
    global _lib
    if _lib is None:
        path = ctypes.util.find_library("OpenGL") or ctypes.util.find_library("GL")
        if path is None:
            raise OSError("no libOpenGL or libGL to query the driver with")
        _lib = ctypes.CDLL(path)
        _lib.glGetIntegerv.argtypes = [ctypes.c_uint, ctypes.POINTER(ctypes.c_int)]
        _lib.glGetIntegerv.restype = None
    value = ctypes.c_int(0)
    _lib.glGetIntegerv(name, ctypes.byref(value))
    return int(value.value)


def gpu_memory(extensions, get_integer: Callable[[int], int] = gl_integer) -> int | None:
    """Bytes of GPU memory in use, or None where the driver does not tell (``extensions``: the context's,
    e.g. ``moderngl.Context.extensions``). Must run on the thread whose context is current."""
    if NVX_EXTENSION not in extensions:
        return None
    try:
        total, available = get_integer(_TOTAL_KIB), get_integer(_AVAILABLE_KIB)
    except OSError:
        return None
    if total <= 0 or not 0 <= available <= total:  # a driver that answers nonsense tells nothing
        return None
    return (total - available) * 1024
