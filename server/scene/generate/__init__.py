"""Procedural benchmark scenes: the papers' test scenes, rebuilt as ``SourceScene`` sources with tours.

``auditorium`` — Funkhouser & Séquin 1993: hundreds of detailed chairs in a hall, viewpoints A, B, C.
``megacity``   — Zach 2002 at scale: ≥ 40k facade-detailed buildings over a street grid (≥ 20M triangles).

Each returns ``(SourceScene, tour, viewpoints)``: tour keys are {"t", "eye",
"forward", "up"} dicts (``proto.messages.TourKey`` fields, z up) on a loop whose
last key repeats the first pose, and viewpoints maps names to tour times.
"""

from server.scene.generate.auditorium import auditorium
from server.scene.generate.megacity import megacity

__all__ = ["auditorium", "megacity"]
