"""The host-side sweep: `run_sweep(SweepSpec(...))` trains every arm of any setting in compiled chunks, with
logs, checkpoints, exact resume, evaluation and plots.

    spec = SweepSpec(out="runs/pendulum", config=Config(env="inverted_pendulum", ...),
                     arms=("mbmf", "cd"), grid={"alpha": (0.0, 1.0)}, seeds=3, total_env_steps=100_000)
    run_dir = run_sweep(spec)                 # or run_sweep(resume_spec("runs/pendulum"), resume=True)
    run_sweep(spec, after_chunk=TimeLimit(3600))   # stop (checkpointed, resumable) before an hour is past
    run_sweep(preset_spec("runs/ant", config={"env": "ant"}, seeds=5))  # as `cdjax sweep --env ant --seeds 5`:
                                                  # the ant preset's values under the ones given
    rows = cdjax.io.read_timings(run_dir)     # where its time went: each program's trace, lowering and compile,
                                              # init, restores, evaluations, writes (cdjax.io.timings)

Rooms: `spec` (what is asked, bounds), `plan` (arms, grids, run.json, resume compatibility), `cdjax.budget` (memory;
below the runner, since evaluation compiles with it too, and importable as `cdjax.runner.budget`), `arms` (one arm's
programs and state), `evaluations` (its evaluator, compiled once per sweep), `loop` (run_sweep), `rounds` (the chunk
loop), `console` (progress, clock, Ctrl-C, library messages into cdjax.log).
"""

from cdjax import budget  # noqa: F401  (`from cdjax.runner import budget` works)
from cdjax.runner.arms import Arm, restore_arms
from cdjax.runner.evaluations import EVAL_TAG, evaluate_arms
from cdjax.runner.loop import Interrupted, TimeLimit, prepare, run_sweep
from cdjax.runner.plan import ArmPlan, chunk_size, plan_arms, resume_spec, run_record, spec_of, validate_grid
from cdjax.runner.spec import SweepSpec, preset_spec

__all__ = ["Arm", "ArmPlan", "EVAL_TAG", "Interrupted", "SweepSpec", "TimeLimit", "chunk_size", "evaluate_arms",
           "plan_arms", "prepare", "preset_spec", "restore_arms", "resume_spec", "run_record", "run_sweep", "spec_of", "validate_grid"]
