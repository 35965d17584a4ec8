"""``python -m walkstream``: the command line."""

from walkstream.cli import main

main()
