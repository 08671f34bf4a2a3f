"""`python -m cdjax.cli`: the `cdjax` command."""

from cdjax.cli import main

main()
