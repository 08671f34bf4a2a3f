"""python -m cdjax.runner.export_expert OBS_RUN_DIR EXPERT_FILE: the model-free policy with the best
deterministic evaluation return of an observation-space sweep, saved as the pixel setting's expert."""

from __future__ import annotations

import pathlib
import sys
from typing import Sequence

import jax

from cdjax import io
from cdjax.agents.experts import Expert, save_expert
from cdjax.protocol import ConfigError
from cdjax.runner import restore_arms

PROG = "python -m cdjax.runner.export_expert"


def export_from_run(run_dir: str | pathlib.Path, path: str | pathlib.Path, arm: str = "model-free") -> Expert:
    """The policy of `arm`'s run with the best deterministic evaluation return in an observation-space sweep."""
    run_dir = pathlib.Path(run_dir)
    _, arms = restore_arms(run_dir)
    found = next((a for a in arms if a.name == arm), None)
    if found is None:
        raise ConfigError(f"{run_dir} has no arm {arm!r}.")
    labels = list(found.plan.labels)
    evals = [e for e in io.read_jsonl(run_dir / "eval.jsonl") if e["arm"] == arm and e.get("deterministic", True)
             and e.get("eval/return") is not None and e.get("hp") in labels]
    if not evals:
        raise ConfigError(f"{run_dir} has no deterministic evaluation of arm {arm!r}.")
    best = max(evals, key=lambda e: e["eval/return"])
    run = labels.index(best["hp"]) * (found.num_runs // len(labels)) + best["seed"]
    acting = jax.device_get(jax.tree.map(lambda x: x[run], found.trainer.policy(found.state)))
    expert = Expert(found.plan.config, acting["params"]["policy"], acting["norms"], float(best["eval/return"]))
    save_expert(path, expert)
    return expert


def main(argv: Sequence[str] | None = None) -> None:
    """The command (argv None: this process's arguments); bad input ends with one sentence and exit status 2."""
    from cdjax.options import Parser, UsageError
    from cdjax.io import RunDirError

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
