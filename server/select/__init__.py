"""The algorithms of LOD selection: pure, clock-free, arrays in and arrays out.

Nothing here does I/O or reads a clock, so a solver can be run, tested and
benchmarked without a network or a GPU.
"""
