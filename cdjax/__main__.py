"""`python -m cdjax`: the `cdjax` command."""

from cdjax.cli import main

main()
