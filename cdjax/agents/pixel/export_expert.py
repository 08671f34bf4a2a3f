"""python -m cdjax.agents.pixel.export_expert OBS_RUN_DIR EXPERT_FILE: the model-free policy with the best
deterministic evaluation return of an observation-space sweep, saved as the pixel setting's expert."""

from __future__ import annotations

import sys

from cdjax.agents.pixel.expert import export_from_run


def main(argv: list[str]) -> None:
    if len(argv) != 2:
        sys.exit("usage: python -m cdjax.agents.pixel.export_expert OBS_RUN_DIR EXPERT_FILE")
    done = export_from_run(argv[0], argv[1])
    print(f"Expert of {done.config.env} (evaluation return {done.eval_return:.1f}) written to {argv[1]}.")


if __name__ == "__main__":
    main(sys.argv[1:])
