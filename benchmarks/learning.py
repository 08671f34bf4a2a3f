"""Learning benchmark: cdjax's model-free arm against Brax's own PPO at the same Spec and env steps.

    python -m benchmarks.learning --tasks ant --seeds 5 --out DIR            # GPU: both learners, one task
    python -m benchmarks.learning --tasks ant --frameworks cdjax --variants tanh global-std --seeds 3 --out DIR
    python -m benchmarks.learning --tiny --out DIR                            # CPU smoke (point env)
    python -m benchmarks.learning --suite playground --tasks dmc-cheetah-run --frameworks brax --seeds 5 \
        --time-limit 1200 --out DIR        # one unit of the Playground parity (README: the units, their times)
    python -m benchmarks.learning --suite playground --tiny --out DIR         # CPU smoke (Playground's pendulum)
    python -m benchmarks.learning --report DIR [DIR ...] --write benchmarks/LEARNING.md   # no device needed

Both learners see the task's `Spec` (benchmarks.common): the same environments, rollout, minibatches
(sequences of unroll_length steps), epochs, discount, reward scaling, entropy cost, learning rate and
clipping. Every `updates_per_eval` updates, each seed's policy is evaluated deterministically
(tanh of the mean action) on `eval_episodes` fresh episodes; Brax's own evaluator does this for Brax
(`deterministic_eval=True`, `num_eval_envs`), cdjax.evaluate for cdjax, so both are evaluated at the
same env-step counts (physics steps, as Brax counts them). cdjax runs its seeds vmapped in one program;
Brax runs them one after the other (its trainer is not vmappable), with the persistent compilation cache
so that only the first seed compiles.

`--variants` runs cdjax with some of its learner options changed (VARIANTS below: one option back to its
previous value each, and `previous` with all of them): the ablation that says which options matter.

Every row is appended to DIR/rows.jsonl as soon as it is measured (a run cut short keeps what it did);
DIR/meta.json records the device, versions, specs and command, and for cdjax the code (commit, where git can tell)
and the whole Config each variant ran with (what `default` meant then). `--report` turns one or more such
directories into a markdown table (final IQM with 95% stratified-bootstrap intervals per task and
learner, area under the curve, env steps/s), the probability that a cdjax seed ends above a Brax PPO seed (rliable's
P(X > Y), with its interval), and a curve plot. A seed whose run stopped before the last evaluation (a time limit)
is left out and named, while at least half the learner's seeds reached it.

Units that fit a loan: `--time-limit S` stops a run at its first evaluation past S seconds and starts no Brax seed
that the previous one's time says would pass it; a later unit with the same --out skips each (task, learner, seed)
whose rows reach the last evaluation and reruns, from its start, one that stopped short (its rows move to
DIR/rows-stopped.jsonl first). Rows of several units and directories merge in `--report`.

MuJoCo Playground's DM Control tasks (cdjax's names, `dmc-*`; `--suite playground` makes three of them the default)
run at Playground's published Brax PPO configuration, `dm_control_suite_params.brax_ppo_config(task)`, which
`playground_task` maps onto Spec and Task, field by field:
    num_envs, unroll_length, batch_size, num_minibatches, discounting, learning_rate, entropy_cost, reward_scaling,
    episode_length, action_repeat -> the Spec fields of those names (cdjax: Config.num_envs, rollout_len =
    unroll_length x batch_size x num_minibatches / num_envs, segment_len = unroll_length, HParams.gamma, lr_policy
    and lr_value, ent_coef, reward_scale, Config.episode_length, action_repeat); num_updates_per_batch -> num_epochs;
    normalize_observations -> both sides normalise (cdjax always does); clipping_epsilon, max_grad_norm and the
    networks are not in the config, so Playground's train script leaves Brax's defaults: clipping 0.3, no gradient
    clipping (cdjax: max_grad_norm 1e30, which only a diverged run's gradient norm reaches), policy (32,)*4 and value
    (256,)*5 (the Spec defaults); num_timesteps, num_evals and num_resets_per_eval -> Task.evals = num_evals - 1 and
    updates_per_eval = num_resets_per_eval x Brax's training steps per epoch, as Brax's arithmetic rounds them up:
    at 60M steps, 10 evaluations and 10 resets per evaluation Brax runs 9 x 10 updates of 983,040 env steps, 88.5M
    env steps (Brax's budget, given to both sides).
What cannot be matched exactly:
  - num_resets_per_eval: Brax resets every env on the host after each of its num_resets_per_eval epochs per
    evaluation (one update of 480 agent steps here, so its training never reaches a 1,000-step episode's end); cdjax
    resets an env only at its episode's end (to its cached first start, as Playground's auto-reset does). cdjax has
    no reset-everything-between-updates switch.
  - Brax's training/sps counts num_resets_per_eval epochs over one epoch's time (10x too high here): the rows carry
    Brax's training time measured here instead (wall clock between evaluations less the evaluations' own).
  - Evaluation: both sides evaluate 128 episodes (Playground's num_eval_envs) deterministically (tanh of the mean);
    Playground's script evaluates stochastically unless told --deterministic_eval. cdjax's evaluator runs fresh
    episodes of its own (cdjax.evaluate), Brax's its eval env wrapped by wrap_for_brax_training.
  - cdjax's learner is its own (lecun-uniform weights with a policy head x0.1, its loss and clipping per parameter
    group): the comparison is of learners at equal data and schedule, not of identical code.
  - Playground's override for the pendulum (action_repeat 4, 4 epochs) names "PendulumSwingUp", which is no task
    ("PendulumSwingup" is), so it never applies; both sides take the config as Playground returns it.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import dataclasses
import datetime
import json
import math
import os
import pathlib
import shlex
import sys
import time

if __package__ in (None, ""):
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from benchmarks.common import TINY, Parser, Spec, device_info, process_started_at, refuse, unwritable_file  # noqa: E402
from cdjax.envs.playground import NAMES  # noqa: E402
from cdjax.options import non_negative, positive, seconds  # noqa: E402


@dataclasses.dataclass(frozen=True)
class Task:
    """A benchmarked task: its Spec and the evaluation schedule (the budget follows from them)."""

    spec: Spec
    evals: int  # evaluations after the one at step 0
    updates_per_eval: int  # updates (Brax: training steps) between evaluations
    eval_episodes: int = 128  # deterministic episodes per evaluation and seed
    resets_per_eval: int = 0  # Brax's num_resets_per_eval (it must divide updates_per_eval; cdjax has none)

    def __post_init__(self):
        if self.resets_per_eval and self.updates_per_eval % self.resets_per_eval:
            raise ValueError(f"updates_per_eval={self.updates_per_eval} is not a multiple of Brax's "
                             f"num_resets_per_eval={self.resets_per_eval}")

    @property
    def budget(self) -> int:
        return self.evals * self.updates_per_eval * self.spec.env_steps_per_update


SHARED_ENV = "CDJAX_BENCH_SHARED_DEVICE"  # set (benchmarks/lanes.sh): other learner processes share the device
PLAYGROUND = ("dmc-cartpole-swingup", "dmc-cheetah-run", "dmc-humanoid-walk")  # --suite playground's tasks
# --suite playground --tiny: the pendulum (Playground's cheapest task to compile on a CPU) at tiny sizes
PLAYGROUND_TINY = dict(num_envs=4, unroll_length=4, batch_size=4, num_minibatches=2, num_epochs=2, horizon=4,
                       episode_length=12, policy_hidden=(8,), value_hidden=(8,), eval_envs=2, eval_horizon=4)


def playground_task(name: str, tiny: bool = False) -> Task:
    """Task `name` (cdjax's dmc-* name) at MuJoCo Playground's published Brax PPO configuration (the module
    docstring maps its fields); `tiny`: its schedule and Brax's resets at the CPU smoke's sizes."""
    from mujoco_playground.config import dm_control_suite_params

    from cdjax.envs import playground

    playground.check("auto")  # the extra installed (one sentence where not)
    c = dm_control_suite_params.brax_ppo_config(playground.NAMES[name])
    if not c.normalize_observations or "network_factory" in c:
        raise ValueError(f"Playground's config of {name} changed what this harness assumes (observation normalisation "
                         "on, Brax's default networks)")
    spec = Spec(env=name, num_envs=c.num_envs, unroll_length=c.unroll_length, batch_size=c.batch_size,
                num_minibatches=c.num_minibatches, num_epochs=c.num_updates_per_batch, episode_length=c.episode_length,
                action_repeat=c.action_repeat, discounting=c.discounting, reward_scaling=c.reward_scaling,
                entropy_cost=c.entropy_cost, learning_rate=c.learning_rate,
                clipping_epsilon=c.get("clipping_epsilon", 0.3), max_grad_norm=c.get("max_grad_norm"))
    if tiny:
        return Task(dataclasses.replace(spec, **PLAYGROUND_TINY), evals=2, updates_per_eval=2, eval_episodes=2,
                    resets_per_eval=1)  # (Brax: one epoch of 2 updates per evaluation, then its envs reset)
    evals, resets = max(c.num_evals - 1, 1), max(c.num_resets_per_eval, 1)
    per_epoch = math.ceil(c.num_timesteps / (evals * spec.env_steps_per_update * resets))  # Brax's rounding
    return Task(spec, evals=evals, updates_per_eval=per_epoch * resets, eval_episodes=c.get("num_eval_envs", 128),
                resets_per_eval=c.num_resets_per_eval)


# Brax's published PPO settings for these tasks (brax training notebook): ant as in the learner issue's
# measurement (unroll 20 x 4 per env, 32 minibatches x 8 epochs), halfcheetah and reacher as published.
TASKS = {
    "ant": Task(Spec(), evals=8, updates_per_eval=8),
    "halfcheetah": Task(Spec(env="halfcheetah", num_envs=2048, unroll_length=20, batch_size=512, num_minibatches=32,
                             num_epochs=8, discounting=0.95, reward_scaling=1.0, entropy_cost=1e-3),
                        evals=4, updates_per_eval=3),
    "reacher": Task(Spec(env="reacher", num_envs=2048, unroll_length=50, batch_size=256, num_minibatches=32,
                         num_epochs=8, action_repeat=4, discounting=0.95, reward_scaling=5.0, entropy_cost=1e-3,
                         horizon=5),
                    evals=6, updates_per_eval=2),
    # Brax's published humanoid settings, on the ant task's schedule (8 x 8 updates: 21M env steps), as issue 71 timed it
    "humanoid": Task(Spec(env="humanoid", num_envs=2048, unroll_length=10, batch_size=1024, num_minibatches=32,
                          num_epochs=8, discounting=0.97, reward_scaling=0.1, entropy_cost=1e-3),
                     evals=8, updates_per_eval=8),
    # CPU smoke: the pure-JAX point mass (it has Brax's Env interface, so Brax PPO runs on it too), at benchmarks.run's
    # --tiny sizes (one Spec: the tests compile its programs once for both harnesses).
    "point": Task(TINY, evals=2, updates_per_eval=2, eval_episodes=4),
}

# cdjax learner options, each set back to its previous value (before the learner issue): the ablation.
PREVIOUS = {"activation": "tanh", "policy_std": "global", "entropy": "gaussian", "gae_in_loss": False,
            "segment_len": 0, "weight_init": "orthogonal"}
BRAX_HEAD = {"policy_head_scale": 1.0}  # lecun-uniform's own policy head (Brax's; cdjax's default before x0.1)
VARIANTS: dict[str, tuple[dict, dict]] = {  # name -> (Config overrides, HParams overrides)
    "default": ({}, {}),
    "tanh": ({"activation": "tanh"}, {}),
    "global-std": ({"policy_std": "global"}, {}),
    "gaussian-entropy": ({"entropy": "gaussian"}, {}),
    "gae-once": ({"gae_in_loss": False}, {}),
    "env-minibatches": ({"segment_len": 0}, {}),
    "adam-eps-1e-5": ({}, {"adam_eps": 1e-5}),
    "orthogonal-init": ({"weight_init": "orthogonal"}, {}),
    # Brax's choices, tried against the gap on ant (lecun-uniform weights are the default since, and later its policy
    # head x0.1; these variants keep Brax's head, as they were measured: LEARNING.md)
    "lecun-init": ({"weight_init": "lecun", **BRAX_HEAD}, {}),
    "joint-clip": ({"clip_scope": "policy-value"}, {}),
    "lecun-joint-clip": ({"weight_init": "lecun", "clip_scope": "policy-value", **BRAX_HEAD}, {}),
    "lecun-global-std": ({"weight_init": "lecun", "policy_std": "global", **BRAX_HEAD}, {}),
    # the policy head's initial weights 100x (orthogonal's head) and 10x smaller than lecun-uniform's, against
    # half-cheetah's failed seeds; head-0.1 is the default since (LEARNING.md), brax-head the default before
    "lecun-small-head": ({"policy_head_scale": 0.01}, {}),
    "head-0.1": ({"policy_head_scale": 0.1}, {}),
    "brax-head": (BRAX_HEAD, {}),
    "previous": (PREVIOUS, {"adam_eps": 1e-5, "init_log_std": -0.5}),
}


class Rows:
    """rows.jsonl of an output directory, appended one row at a time; a later unit resumes what it holds."""

    def __init__(self, out: pathlib.Path):
        out.mkdir(parents=True, exist_ok=True)
        self.path = out / "rows.jsonl"

    def add(self, **row) -> None:
        row["at"] = time.time()  # when it was measured (Unix time): a process's time to a row, from its launch
        with self.path.open("a") as f:
            f.write(json.dumps(row) + "\n")
        print(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()), flush=True)

    def write_meta(self, module: str, argv, **fields) -> None:
        """DIR/meta.json: the command (`python -m benchmarks.<module> <argv>`), date, device, whether other
        processes shared the device (SHARED_ENV set, as benchmarks/lanes.sh does: then its times are not speeds),
        when this process was launched (the rows' `at` less it: a row's time from the command) and `fields`; a
        unit resuming the directory keeps the earlier units' command, date and device under "earlier"."""
        path = self.path.parent / "meta.json"
        meta = {"command": f"python -m benchmarks.{module} " + shlex.join(argv if argv is not None else sys.argv[1:]),
                "date": str(datetime.date.today()), **device_info(), "shared_device": bool(os.environ.get(SHARED_ENV)),
                "process_started_at": process_started_at(), **fields}
        if path.exists():
            earlier = json.loads(path.read_text())
            meta["earlier"] = earlier.pop("earlier", []) + [{k: earlier.get(k) for k in ("command", "date", "device")}]
        path.write_text(json.dumps(meta, indent=1, default=str))

    def done(self, task: str, framework: str, variant: str, seeds, final_steps: int) -> bool:
        """Whether every one of `seeds` has its row at `final_steps` (an earlier unit ran them: skip them). If not,
        the rows those seeds have (a run stopped short) move to rows-stopped.jsonl, so that the rerun replaces them."""
        from cdjax import io

        rows = io.read_jsonl(self.path, check=None)
        mine = [r.get("task") == task and r.get("framework") == framework and r.get("variant") == variant
                and r.get("seed") in seeds for r in rows]
        if {r["seed"] for r, m in zip(rows, mine) if m and r.get("env_steps") == final_steps} == set(seeds):
            print(f"resume: {framework} {variant} seeds {list(seeds)} on {task} have their rows", flush=True)
            return True
        if any(mine):
            with (self.path.parent / "rows-stopped.jsonl").open("a") as f:
                f.writelines(json.dumps(r) + "\n" for r, m in zip(rows, mine) if m)
            self.path.write_text("".join(json.dumps(r) + "\n" for r, m in zip(rows, mine) if not m))
        return False


def run_sweep(name: str, variant: str, trainer, hp, seeds: int, seed: int, evals: int, updates_per_eval: int,
              eval_episodes: int, rows: Rows, deadline: float = math.inf) -> None:
    """`seeds` vmapped runs of `trainer` (any setting's) with HParams `hp`, their keys from base key `seed` (rows
    say seeds seed*1000 + s, never another base's), each evaluated deterministically on `eval_episodes` fresh
    episodes at step 0 and after every `updates_per_eval` updates, `evals` times; the runs stop at the first
    evaluation past `deadline` (time.perf_counter)."""
    import jax
    import numpy as np

    from cdjax.evaluate import make_evaluator
    from cdjax.runner import budget
    from cdjax.sweep import make_sweep, unpad

    sweep = make_sweep(trainer)
    keys, hps = sweep.grid(seed=seed, num_seeds=seeds, hps=[hp])
    state = sweep.init(keys, hps)
    evaluator = make_evaluator(trainer, episodes=eval_episodes, deterministic=True)
    eval_keys = lambda i: jax.vmap(lambda k: jax.random.fold_in(k, 1000 + i))(keys)  # noqa: E731
    # the evaluator compiles in the background beside the training program (one program for every evaluation)
    pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="evaluator-compile")
    evaluating = pool.submit(evaluator.compiled, (trainer.policy(state), eval_keys(0), hps))
    pool.shutdown(wait=False)  # its one thread ends with that compile
    t0 = time.perf_counter()
    program, _ = budget.compile_fitting(sweep.lower(state, hps, updates_per_eval))  # as a sweep compiles it
    compile_s, train_s, eval_s = time.perf_counter() - t0, 0.0, 0.0
    for i in range(evals + 1):
        if i:
            t0 = time.perf_counter()
            state, metrics = program(state, hps)
            jax.block_until_ready(metrics)
            train_s += time.perf_counter() - t0
        t0 = time.perf_counter()
        evaluating.result()  # raises what its compile met
        returns = np.asarray(unpad(evaluator(trainer.policy(state), eval_keys(i), hps)["return_mean"], seeds))
        eval_s += time.perf_counter() - t0  # the evaluations so far, with the first one's wait for its compile
        for s in range(seeds):
            rows.add(task=name, framework="cdjax", variant=variant, seed=seed * 1000 + s,
                     env_steps=i * updates_per_eval * trainer.config.env_steps_per_update,
                     eval_return=float(returns[s]), train_s=train_s, compile_s=compile_s, eval_s=eval_s)
        if time.perf_counter() > deadline and i < evals:
            print(f"time limit: cdjax {variant} on {name} stopped after evaluation {i} of {evals}", flush=True)
            return


def cdjax_config(task: Task, variant: str):
    """The Config of cdjax's model-free arm on `task` with `variant`'s overrides."""
    return task.spec.config(arm="model-free", num_updates=task.evals * task.updates_per_eval, **VARIANTS[variant][0])


def run_cdjax(name: str, task: Task, variant: str, seeds: int, rows: Rows, seed: int = 0,
              deadline: float = math.inf) -> None:
    """cdjax model-free on `task`, `seeds` vmapped runs from base key `seed` (`run_sweep`)."""
    from cdjax.agents import obs

    if rows.done(name, "cdjax", variant, range(seed * 1000, seed * 1000 + seeds), task.budget):
        return
    run_sweep(name, variant, obs.make_trainer(cdjax_config(task, variant)), task.spec.hparams(**VARIANTS[variant][1]),
              seeds, seed, task.evals, task.updates_per_eval, task.eval_episodes, rows, deadline)


class _TimeUp(Exception):
    """Raised from Brax's progress callback to stop its run at an evaluation past the time limit."""


def run_brax(name: str, task: Task, seed: int, rows: Rows, deadline: float = math.inf) -> None:
    """Brax's PPO trainer on the task's Spec, evaluated by Brax at the same env-step counts; a Playground task through
    Playground's own wrap_for_brax_training. Rows carry Brax's training time (wall clock less its evaluations)."""
    import functools

    import jax
    import numpy as np
    from brax.training import acting
    from brax.training.agents.ppo import networks as ppo_networks
    from brax.training.agents.ppo import train as ppo

    from benchmarks.brax_ppo import install_shim
    from cdjax.envs import make_single_env, playground

    if rows.done(name, "brax", "brax-ppo", [seed], task.budget):
        return
    install_shim()
    spec = task.spec
    if playground.is_playground(spec.env):
        from mujoco_playground import wrapper

        env = {"environment": playground.PlaygroundEnv(spec.env).raw, "wrap_env_fn": wrapper.wrap_for_brax_training}
    else:
        env = {"environment": make_single_env(spec.env)}
    factory = functools.partial(ppo_networks.make_ppo_networks, policy_hidden_layer_sizes=spec.policy_hidden,
                                value_hidden_layer_sizes=spec.value_hidden)
    evaluate, clock = acting.Evaluator.run_evaluation, {"eval": 0.0, "train": 0.0, "mark": None}
    device = jax.local_devices()[0]  # Brax's one (max_devices_per_host=1)

    def timed_evaluation(self, policy_params, *args, **kwargs):  # Brax's evaluation returns host numbers: it ended
        t0 = time.perf_counter()
        # Brax's evaluation program compiles once, not again at the second evaluation, when its arguments are alike at
        # every evaluation: the parameters through the host onto the device as plain arrays, whether they are the
        # replicas placed before training (weakly typed where their value was) or a pmapped epoch's output (typed with
        # its mesh axis), and the evaluation's env state (donated to the next evaluation) committed to the device as
        # the previous evaluation's output is, not left where Brax's first reset put it
        policy_params = jax.device_put(jax.tree.map(np.asarray, policy_params), device)
        self._eval_state_to_donate = jax.device_put(self._eval_state_to_donate, device)
        out = evaluate(self, policy_params, *args, **kwargs)
        clock["eval"] += time.perf_counter() - t0
        return out

    def progress(step, metrics):
        now, evals = time.perf_counter(), clock["eval"]
        if clock["mark"] is not None:
            clock["train"] += now - clock["mark"][0] - (evals - clock["mark"][1])
        clock["mark"] = (now, evals)
        rows.add(task=name, framework="brax", variant="brax-ppo", seed=seed, env_steps=int(step),
                 eval_return=float(metrics["eval/episode_reward"]), train_s=clock["train"], eval_s=evals)
        if now > deadline and step < task.budget:
            raise _TimeUp

    acting.Evaluator.run_evaluation = timed_evaluation
    try:
        ppo.train(num_timesteps=task.budget, num_evals=task.evals + 1, num_eval_envs=task.eval_episodes,
                  num_resets_per_eval=task.resets_per_eval, deterministic_eval=True, seed=seed,
                  network_factory=factory, max_devices_per_host=1, progress_fn=progress, **env, **spec.brax_kwargs())
    except _TimeUp:
        print(f"time limit: brax seed {seed} on {name} stopped at an evaluation", flush=True)
    finally:
        acting.Evaluator.run_evaluation = evaluate


def task_of(name: str, tiny: bool = False) -> Task:
    return TASKS[name] if name in TASKS else playground_task(name, tiny)


def main(argv=None) -> int:
    p = Parser(prog="python -m benchmarks.learning", description=__doc__,
               formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--suite", choices=["brax", "playground"], default="brax",
                   help="the default tasks: Brax's (ant halfcheetah reacher) or Playground's (" + " ".join(PLAYGROUND)
                        + "); with --tiny, the point mass or Playground's pendulum")
    p.add_argument("--tasks", nargs="+", choices=[*TASKS, *sorted(NAMES)], metavar="TASK",
                   help=f"{', '.join(TASKS)} (Brax's published settings) or a Playground task, dmc-* (`cdjax envs`), "
                        "at dm_control_suite_params'")
    p.add_argument("--frameworks", nargs="+", default=["cdjax", "brax"], choices=["cdjax", "brax"])
    p.add_argument("--variants", nargs="+", default=["default"], choices=list(VARIANTS),
                   help="cdjax learner variants (default: the defaults)")
    p.add_argument("--seeds", type=positive, default=5,
                   help="runs per task and learner (cdjax: per variant) (default 5; --tiny: at most 2)")
    p.add_argument("--first-seed", type=non_negative, default=0, metavar="B",
                   help="base seed B, to spread one learner's seeds over processes (default 0): cdjax's runs take "
                        "their keys from base key B, its rows say seeds B*1000 ... B*1000 + seeds - 1 (never those of "
                        "another B); Brax PPO runs seeds B ... B + seeds - 1")
    p.add_argument("--evals", type=positive, help="override every task's number of evaluations")
    p.add_argument("--updates-per-eval", type=positive, help="override every task's updates between evaluations")
    p.add_argument("--tiny", action="store_true", help="CPU smoke: the point task (--suite playground: the pendulum), "
                   "2 seeds")
    p.add_argument("--budget-s", type=seconds, default=float("inf"),
                   help="start no new (task, learner, seed) after this many seconds")
    p.add_argument("--time-limit", type=seconds, default=float("inf"), metavar="S",
                   help="stop a run at its first evaluation past S seconds, start no Brax seed the last one's time "
                        "says would pass it (a later unit with the same --out resumes: module docstring)")
    p.add_argument("--out", help="output directory (rows.jsonl, meta.json)")
    p.add_argument("--cache-dir", default=os.path.expanduser("~/.cache/cdjax/jax"),
                   help="JAX's persistent compilation cache (Brax's seeds after the first reuse its programs)")
    p.add_argument("--report", nargs="+", metavar="DIR", help="make the table and plot from these directories (DIR@brax or DIR@cdjax: only that "
                   "framework's rows of DIR)")
    p.add_argument("--write", help="with --report: write the markdown here (and the plot beside it)")
    p.add_argument("--parity-variants", nargs="+", metavar="VARIANT",
                   help="with --report: the cdjax variants set against Brax PPO in the first table (default: default)")
    args = p.parse_args(argv)
    report_only = [option for option, value in (("--write", args.write), ("--parity-variants", args.parity_variants))
                   if value is not None]
    if report_only and not args.report:  # (the benchmark would run, and ignore them)
        refuse(p.prog, f"{' and '.join(report_only)} go{'es' * (len(report_only) == 1)} with --report DIR (the table of "
                       "a benchmark's --out); without --report this command runs the benchmark")
    run_only = [f"--{name.replace('_', '-')}" for name in ("suite", "tasks", "frameworks", "variants", "seeds",
                                                            "first_seed", "evals", "updates_per_eval", "tiny",
                                                            "budget_s", "time_limit", "out", "cache_dir")
                if getattr(args, name) != p.get_default(name)]
    if args.report and run_only:  # (the report reads what its directories hold, and would ignore them)
        refuse(p.prog, f"{', '.join(run_only)} set{'s' * (len(run_only) == 1)} up a benchmark run, not --report's "
                       "table, which reads what its directories hold: give them without --report")
    if args.report:
        from benchmarks import learning_report

        if args.write and (why := unwritable_file(args.write)):  # said before the rows are read and plotted
            refuse(p.prog, f"--write {args.write}: {why}")
        try:
            text = learning_report.report(args.report, args.write, tuple(args.parity_variants or ["default"]))
        except ValueError as err:  # a source without rows, or a seed given twice: one sentence, not a traceback
            print(f"python -m benchmarks.learning: {err}", file=sys.stderr)
            return 2
        print(text)
        return 0
    playground = args.suite == "playground"
    if args.tiny:
        args.tasks, args.seeds = ["dmc-pendulum-swingup" if playground else "point"], min(args.seeds, 2)
    args.tasks = args.tasks or (list(PLAYGROUND) if playground else ["ant", "halfcheetah", "reacher"])
    from cdjax import io, runtime
    from cdjax.envs import playground
    from cdjax.protocol import ConfigError

    out = pathlib.Path(args.out or f"benchmarks/results/{datetime.date.today()}-learning")
    try:
        io.RunDir(out).check_writable()
        runtime.configure(cache_dir=args.cache_dir, cache_source="--cache-dir")
    except (ConfigError, io.RunDirError) as err:
        refuse(p.prog, str(err))
    rows = Rows(out)
    tasks = {}
    try:
        for name in args.tasks:
            task = task_of(name, args.tiny)
            tasks[name] = dataclasses.replace(task, evals=args.evals or task.evals,
                                              updates_per_eval=args.updates_per_eval or task.updates_per_eval)
    except (ConfigError, ValueError) as err:  # the extra missing, or a schedule Brax cannot run
        refuse(p.prog, str(err))
    meta = {"tasks": {n: {"spec": t.spec.describe(), "evals": t.evals, "updates_per_eval": t.updates_per_eval,
                          "eval_episodes": t.eval_episodes, "budget": t.budget,
                          "resets_per_eval": t.resets_per_eval} for n, t in tasks.items()},
            "variants": {v: [VARIANTS[v][0], VARIANTS[v][1]] for v in args.variants}}
    meta["physics_backend"] = {n: playground.resolve_backend() for n in tasks if playground.is_playground(n)}
    if "cdjax" in args.frameworks:  # what `default` and each variant meant when these rows ran: the whole Config
        from cdjax.runner.plan import code_record

        meta["code"] = code_record()
        meta["configs"] = {n: {v: io.dataclass_to_json(cdjax_config(t, v)) for v in args.variants} for n, t in tasks.items()}
    rows.write_meta("learning", argv, **meta)
    t_start = time.perf_counter()
    deadline, last = t_start + args.time_limit, 0.0  # last: the previous Brax seed's seconds
    for name, task in tasks.items():
        if "cdjax" in args.frameworks:
            for variant in args.variants:
                if time.perf_counter() - t_start > min(args.budget_s, args.time_limit):
                    print(f"budget: skipped cdjax {variant} on {name}", flush=True)
                    continue
                run_cdjax(name, task, variant, args.seeds, rows, seed=args.first_seed, deadline=deadline)
        if "brax" in args.frameworks:
            for seed in range(args.first_seed, args.first_seed + args.seeds):
                t0 = time.perf_counter()
                if t0 - t_start > args.budget_s or t0 + last > deadline:
                    print(f"budget: skipped brax seed {seed} on {name}", flush=True)
                    continue
                run_brax(name, task, seed, rows, deadline)
                last = time.perf_counter() - t0
    print(f"rows in {rows.path}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
