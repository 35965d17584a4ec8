"""walkstream's client: follows a tour, keeps streamed representations, draws and measures them.

Modules: ``app`` (``run_client``, the entry point), ``connection`` (opening
the session, the receiver thread, redialling), ``frame_loop`` (``FrameLoop``:
apply deltas, draw, report), ``records`` (``ClientRun``, ``FrameRecord``,
``FrameTrace``), ``navigation`` (camera tours and controllers), ``cache``
(resident state) and ``schedule`` (morph schedules), ``frame_plan`` (what a
frame draws), ``slots`` and ``shading`` (the renderer's tables and vertex
records), all GL-free; ``renderer``, ``arena``, ``splats`` and ``window``
(moderngl on EGL, fenced frame timing). Import what you need from them
directly; this package imports nothing, so the GL-free modules stay usable
without a GL driver.
"""
