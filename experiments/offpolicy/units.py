"""The off-policy experiment's GPU units: `python -m experiments.offpolicy list`, `... run UNIT --out DIR`.

  TASK-base     model-free and model, 10 seeds each (the preset TASK: 128 envs, 8 gradient steps per env step)
  TASK-k3       paper-cd and self-pred at horizon 3, alpha 0.1 and 1 (20 runs per arm, vmapped)
  TASK-k5       paper-cd and self-pred at horizon 5, alpha 0.1 and 1
  TASK-obs      model-free with the actor and critic on the observation alone (`--inputs obs`, no encoder), 10
                seeds: the reference without a latent (why: PLAN.md)

Each is `cdjax sweep --setting offpolicy --preset TASK --arms ... --seeds 10 --steps STEPS --diagnostics true`
stopped by --time-limit (a unit that stops short is run again with `--resume` by the same command: the sweep
resumes from its last checkpoint), then `cdjax plot`. `steps` (default 1,000,000 env steps per run) and `sweep`
(more sweep options) are parameters (`--param steps=...`).
"""

from __future__ import annotations

import signal

from experiments.launch import Context, Step, Unit, python
from experiments.offpolicy import ALPHAS, SEEDS, STEPS, TASKS

LIMIT_S, END_S = 1260, 1440
PARTS = {"base": (("model-free", "model"), None), "k3": (("paper-cd", "self-pred"), 3),
         "k5": (("paper-cd", "self-pred"), 5), "obs": (("model-free",), None)}
INPUTS = {"obs": "obs"}  # the parts whose actor and critic read other inputs than the preset's (Config.inputs)
THIN = {"points": 1000, "tail": 100}  # collect: the last 10% of a run's points kept whole (its final return)


def sweep_args(task: str, part: str, steps: str, out: str) -> list[str]:
    """The `cdjax sweep` arguments of unit TASK-PART (without --time-limit and --resume)."""
    arms, horizon = PARTS[part]
    args = ["--setting", "offpolicy", "--preset", task, "--arms", *arms, "--seeds", str(SEEDS), "--steps", steps,
            "--diagnostics", "true", "--no-progress", "--out", out]
    if horizon is not None:
        args += ["--horizon", str(horizon), "--alpha", *(f"{a:g}" for a in ALPHAS)]
    if part in INPUTS:
        args += ["--inputs", INPUTS[part]]
    return args


def _steps(task: str, part: str):
    def steps(ctx: Context) -> list[Step]:
        run = str(ctx.out / "run")
        resume = ["--resume"] if (ctx.out / "run" / "run.json").exists() else []
        args = sweep_args(task, part, ctx.params["steps"], run)
        if resume:  # a resumed sweep takes its arguments from run.json: only the budget and the time limit
            args = ["--out", run, "--steps", ctx.params["steps"], "--no-progress"]
        return [Step(python("cdjax.cli", "sweep", *args, "--time-limit", str(ctx.limit), *resume,
                            *ctx.params["sweep"].split()), timeout=ctx.limit + 120),
                Step(python("cdjax.cli", "plot", run), timeout=60, signal=signal.SIGTERM, kill_after=10)]
    return steps


def _units() -> dict[str, Unit]:
    units = []
    for task in TASKS:
        for part, (arms, horizon) in PARTS.items():
            what = " and ".join(arms) + (f" at horizon {horizon}, alpha {' and '.join(f'{a:g}' for a in ALPHAS)}"
                                          if horizon else "") + (f" on inputs {INPUTS[part]}" if part in INPUTS else "")
            units.append(Unit(f"{task}-{part}", f"{task}: {what}, {SEEDS} seeds, `steps` env steps per run", 24,
                              _steps(task, part), {"steps": str(STEPS), "sweep": ""}))
    return {u.name: u for u in units}


UNITS = _units()
