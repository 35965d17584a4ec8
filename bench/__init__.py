"""Evaluation, benchmarks, the demo and the command line: everything that runs the parts together."""
