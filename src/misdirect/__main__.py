"""``python -m misdirect``: the command line, where the ``misdirect`` script is not on PATH."""

from misdirect.cli import main

main()
