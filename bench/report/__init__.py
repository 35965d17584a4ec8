"""The evaluation's report folder, written from the results dict alone (``bench.evaluate.evaluate``).

What a reader needs to choose a method: Funkhouser & Séquin's Table 1 (their columns — compute mean and
max, frame mean, max and std — plus p95, image error and popping), their Figure 7 (frame time over the
tour, one panel per method on the same axes), the chart of image error against mean frame time for every
method at every budget with its Pareto front, false-colour level images at viewpoints A and C, and the
done-when checks, each with the margin by which it passes or misses. ``index.html`` ties them
together with relative links, so the folder can be zipped, served or opened from disk.

Everything here reads only the results dict (the contract in the evaluation's schema: times in
milliseconds), never a store, a server or a GPU, so the report can be rebuilt from ``results.json``.
"""
