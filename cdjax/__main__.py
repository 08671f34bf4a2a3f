"""`python -m cdjax ...`: the `cdjax` command (cdjax.cli.main)."""

from cdjax.cli import main

main()
