"""Scenarios where methods fail: six hostile paths and conditions, a PASS or FAIL line each.

A frame-time budget is easy to hold on a smooth tour. These scenarios go where
the methods of Funkhouser & Séquin, Zach and Zach-Mantler-Karner are known to
struggle, with the real server (a child process) and the real headless client:

- ``spin``: sudden complexity — at viewpoint C, a sparse view (up at the ceiling or
  sky), then a full turn in 1 s down into the dense view (F&S's spin at C).
- ``turn``: an abrupt turn — walk straight, then turn 150° in 0.15 s: the path
  predictor (fitted on a straight walk) was wrong for the view that appears.
- ``oscillation``: forward and back with a period near 2τ — every prediction
  points the wrong way, up-morphs are overridden by down-morphs (morph conflicts).
- ``drift``: cost drift — busy-loop processes take the CPU from the renderer
  mid-run; the fitted cost model has to follow and coarsen the selection.
- ``below_coarsest``: a target smaller than the coarsest-everything frame costs.
- ``network``: 40 ± 10 ms latency each way and 1 % loss (``bench.netem.DelayProxy``).

Every path is built from the store (its tour, viewpoints and bounds, ``anchor_of``),
so the scenarios run on any scene ``walkstream build`` makes. Each function's
docstring states its criterion and the margin; the figures are computed from the
run's frames and trace (``ClientRun``). One server serves every scenario of a
``run_scenarios`` call (each run is a fresh session with a fresh cost model).
"""
