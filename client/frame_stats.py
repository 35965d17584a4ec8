"""What a drawn frame reports (``FrameStats``, per algorithm ``FrameTerms``) and what may draw inside it (``Layer``).

Plain records, no GL: ``client.renderer`` fills them, the frame loop, the
calibration and the benchmarks read them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

__all__ = ["FrameStats", "FrameTerms", "Layer"]


@dataclass(frozen=True)
class FrameTerms:
    """A frame's work per rendering algorithm (index into ``ALGORITHMS``), as ``proto.messages.AlgorithmTerms``.

    Each field is a list of 3 ints; ``pixels`` are samples that passed the depth test.
    """

    triangles: list[int]
    vertices: list[int]
    pixels: list[int]
    draws: list[int]


@dataclass(frozen=True)
class FrameStats:
    """One drawn frame: fenced wall time (s) and what was drawn.

    A morphing representation counts its own (the finer level's) triangles and
    vertices; ``morphs`` is how many of the ``draws`` were morphing (weight < 1).
    ``pixels``: samples that passed the depth test in the mesh draws (occlusion
    query; overdraw counts). ``gpu_time``: the timer query's GL_TIME_ELAPSED
    over the fenced frame (s), or None when not plausible (``Renderer.gpu_time_plausible``).
    ``cpu_time``: seconds ``draw`` spent on the CPU before the final wait on the
    GPU (preparation and submission; on llvmpipe submission includes the vertex
    processing its draw module does in the calling thread). ``prepare_time``:
    the part of it that is the renderer's own work (looking up the reps,
    building the multi-draw commands and per-draw rows, uploading them), which
    is what grows with the number of drawn representations. ``culled``: reps
    asked for but outside the view frustum, not drawn (nor counted in the
    other figures: the cost model is fitted to what was drawn). ``splats``: what
    the layers drew. ``terms``: the same work split by rendering algorithm. ``seen``: which of the reps
    asked for were drawn.
    """

    time: float
    triangles: int
    vertices: int
    draws: int
    morphs: int = 0
    pixels: int = 0
    gpu_time: float | None = None
    cpu_time: float = 0.0
    splats: int = 0
    terms: FrameTerms | None = None
    prepare_time: float = 0.0
    culled: int = 0
    seen: np.ndarray | None = None  # (s,) bool over the reps asked for: the ones drawn (resident, in view)


class Layer(Protocol):
    """Something drawn inside the fence after the meshes (the point-splat layer).

    ``render`` gets the row-major camera-relative ``view_projection`` (see the
    module docstring), the eye (3,) float64, the viewport (width, height) and the
    vertical fov in degrees; it draws into the bound framebuffer (depth test on)
    and returns how many splats it drew. It must not begin a GL_TIME_ELAPSED
    query (the frame's is active).
    """

    def render(self, view_projection: np.ndarray, eye: np.ndarray, viewport: tuple[int, int],
               fov_y: float) -> int: ...
