"""python -m cdjax.agents.pixel.export_expert OBS_RUN_DIR EXPERT_FILE: the model-free policy with the best
deterministic evaluation return of an observation-space sweep, saved as the pixel setting's expert."""

from __future__ import annotations

import pathlib
import sys
from typing import Sequence

from cdjax.agents.pixel.expert import export_from_run

PROG = "python -m cdjax.agents.pixel.export_expert"


def main(argv: Sequence[str] | None = None) -> None:
    """The command (argv None: this process's arguments); bad input ends with one sentence and exit status 2."""
    from cdjax.cli import Parser, UsageError
    from cdjax.io import RunDirError
    from cdjax.protocol import ConfigError

    p = Parser(prog=PROG, description=__doc__)
    p.add_argument("run_dir", metavar="OBS_RUN_DIR", help="the --out of an observation-space sweep with a model-free arm")
    p.add_argument("expert_file", metavar="EXPERT_FILE", help="where the expert is written (its directory is made)")
    try:
        args = p.parse_args(sys.argv[1:] if argv is None else list(argv))
        if pathlib.Path(args.expert_file).is_dir():  # said before the run is restored
            raise UsageError(f"EXPERT_FILE {args.expert_file} is a directory; name a file.")
        done = export_from_run(args.run_dir, args.expert_file)
    except (UsageError, ConfigError, RunDirError) as err:
        print(f"{PROG}: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    print(f"Expert of {done.config.env} (evaluation return {done.eval_return:.1f}) written to {args.expert_file}.")


if __name__ == "__main__":
    main()
