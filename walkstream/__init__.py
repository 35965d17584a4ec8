"""walkstream: the command line that ties server, client and benchmarks together (``walkstream/cli.py``)."""
