"""Brax's SAC against cdjax's off-policy setting in one process, at equal env steps and update-to-data ratio.

    python -m benchmarks.brax_sac --tasks ant --seeds 5 --out DIR           # GPU: both learners
    python -m benchmarks.brax_sac --speed --tasks ant --out DIR             # env and gradient steps/s, 1 and 10 seeds
    python -m benchmarks.brax_sac --tiny --out DIR                          # CPU smoke (point env)

Both learners see the task's `SacTask`: the environments, parallel envs, batch size, gradient steps per batched env
step (Brax's grad_updates_per_step, cdjax's updates_per_step), replay size, learning start (Brax's min_replay_size,
cdjax's learning_starts), learning rate, discount, reward scaling, tau, the networks' widths and observation
normalisation. What stays each learner's own: cdjax's critics have LayerNorm and n-step returns (its defaults,
`--cdjax-plain` for 1-step returns without LayerNorm and without the latent encoder: Brax's SAC), and Brax fills its
first min_replay_size steps with its initial policy where cdjax takes uniform random actions. Each seed's policy is
evaluated deterministically (tanh of the mean) on `eval_episodes` fresh episodes at the same env-step counts;
cdjax runs its seeds vmapped in one program, Brax one after the other.

Rows go to DIR/rows.jsonl in benchmarks.learning's row format (framework cdjax or brax, variant offpolicy-<arm> or
brax-sac; the speed case's rows say case=speed), so `python -m benchmarks.learning --report DIR ...` makes their
table, intervals, verdicts and curves. Brax evaluates at its own epoch ends, which count its prefill steps, so its
env-step counts differ slightly from cdjax's (the report compares final returns within 1% of env steps).

Brax 0.14.2's SAC calls `jax.device_put_replicated`, which newer JAX releases no longer have: `replicate_on_one`
stands in for it on one device (the tree with a leading axis of 1, put on that device).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import pathlib
import sys
import time

if __package__ in (None, ""):
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from benchmarks.common import Parser, refuse  # noqa: E402
from cdjax.options import non_negative, positive  # noqa: E402


@dataclasses.dataclass(frozen=True)
class SacTask:
    env: str
    num_envs: int = 128
    batch_size: int = 512
    updates_per_step: int = 8  # gradient steps per batched env step (both learners)
    max_replay: int = 1_048_576  # transitions
    min_replay: int = 8192  # env steps before learning
    learning_rate: float = 3e-4
    discounting: float = 0.99
    reward_scaling: float = 1.0
    tau: float = 0.005
    hidden: tuple[int, ...] = (256, 256)
    episode_length: int = 1000
    evals: int = 10  # evaluations after the one at step 0
    steps_per_eval: int = 100_000  # env steps between evaluations
    eval_episodes: int = 128

    @property
    def budget(self) -> int:
        return self.evals * self.steps_per_eval


TASKS = {name: SacTask(env=name) for name in ("ant", "humanoid", "halfcheetah", "hopper")}
TASKS["point"] = SacTask(env="point", num_envs=8, batch_size=32, updates_per_step=1, max_replay=2048, min_replay=128,
                         hidden=(16,), episode_length=20, evals=2, steps_per_eval=256, eval_episodes=4)


def replicate_on_one(tree, devices):
    """jax.device_put_replicated(tree, devices) for one device: every leaf with a leading axis of 1, on it."""
    import jax
    import jax.numpy as jnp

    if len(devices) != 1:
        raise ValueError(f"this stand-in for jax.device_put_replicated serves one device, got {len(devices)}")
    return jax.device_put(jax.tree.map(lambda x: jnp.asarray(x)[None], tree), devices[0])


def install_replicated():
    """Give JAX `device_put_replicated` (the stand-in) where it lacks it; whether it was installed."""
    import jax

    if hasattr(jax, "device_put_replicated"):
        return False
    jax.device_put_replicated = replicate_on_one
    return True


def parse_sets(items) -> dict:
    """["FIELD=VALUE", ...] -> {field: value} of the off-policy Config or HParams, each value of its field's type
    (bool: true/false; tuple: comma-separated ints); an unknown field or a bad value refused by SystemExit."""
    from cdjax.agents.offpolicy import Config, HParams

    defaults = {**dataclasses.asdict(Config()), **dataclasses.asdict(HParams())}
    out = {}
    for item in items or ():
        name, sep, text = item.partition("=")
        if not sep or name not in defaults:
            raise SystemExit(f"--cdjax-set {item!r}: give FIELD=VALUE with FIELD one of the off-policy Config or "
                             f"HParams fields ({', '.join(sorted(defaults))}).")
        default = defaults[name]
        try:
            if isinstance(default, bool):
                if text.lower() not in ("true", "false"):
                    raise ValueError(text)
                out[name] = text.lower() == "true"
            elif isinstance(default, tuple):
                out[name] = tuple(int(w) for w in text.split(",") if w)
            else:
                out[name] = type(default)(text)
        except ValueError:
            raise SystemExit(f"--cdjax-set {item!r}: {text!r} is no {type(default).__name__}.") from None
    return out


def variant_name(arm: str, plain: bool = False, sets: dict | None = None) -> str:
    """The rows' variant: offpolicy-<arm>, -plain for --cdjax-plain, +field=value for each --cdjax-set."""
    return f"offpolicy-{arm}" + ("-plain" if plain else "") + "".join(
        f"+{k}={','.join(map(str, v)) if isinstance(v, tuple) else v}" for k, v in sorted((sets or {}).items()))


def cdjax_config(task: SacTask, arm: str = "model-free", plain: bool = False, num_updates: int = 1,
                 sets: dict | None = None):
    """The off-policy setting's Config matching `task` (one batched env step per update), with the Config fields
    of `sets` (parse_sets) put over it."""
    from cdjax.agents.offpolicy import Config

    steps = -(-task.max_replay // task.num_envs)
    extra = dict(inputs="obs", n_step=1, layer_norm=False) if plain else {}
    fields = {f.name for f in dataclasses.fields(Config)}
    extra.update({k: v for k, v in (sets or {}).items() if k in fields})
    return Config(**{**dict(env=task.env, arm=arm, num_envs=task.num_envs, steps_per_update=1,
                            updates_per_step=task.updates_per_step, buffer_steps=steps, batch_size=task.batch_size,
                            learning_starts=task.min_replay, actor_hidden=task.hidden, critic_hidden=task.hidden,
                            episode_length=task.episode_length, num_updates=num_updates), **extra})


def cdjax_hparams(task: SacTask, sets: dict | None = None):
    """The HParams matching `task`, with the HParams fields of `sets` put over them."""
    from cdjax.agents.offpolicy import HParams

    lr = task.learning_rate
    fields = {f.name for f in dataclasses.fields(HParams)}
    given = dict(lr_actor=lr, lr_critic=lr, lr_alpha=lr, lr_model=lr, gamma=task.discounting, tau=task.tau,
                 reward_scale=task.reward_scaling)
    return HParams(**{**given, **{k: v for k, v in (sets or {}).items() if k in fields}})


def run_cdjax(name: str, task: SacTask, seeds: int, rows, arm: str = "model-free", plain: bool = False,
              seed: int = 0, sets: dict | None = None) -> None:
    """cdjax's off-policy arm, `seeds` vmapped runs, evaluated every steps_per_eval env steps (rounded up to whole
    updates) by benchmarks.learning's loop."""
    from benchmarks.learning import run_sweep
    from cdjax.agents import offpolicy

    config = cdjax_config(task, arm, plain, sets=sets)
    run_sweep(name, variant_name(arm, plain, sets), offpolicy.make_trainer(config), cdjax_hparams(task, sets),
              seeds, seed, task.evals, -(-task.steps_per_eval // config.env_steps_per_update), task.eval_episodes,
              rows)


def brax_kwargs(task: SacTask) -> dict:
    return dict(num_timesteps=task.budget, episode_length=task.episode_length, num_envs=task.num_envs,
                batch_size=task.batch_size, grad_updates_per_step=task.updates_per_step,
                max_replay_size=task.max_replay, min_replay_size=task.min_replay, learning_rate=task.learning_rate,
                discounting=task.discounting, reward_scaling=task.reward_scaling, tau=task.tau,
                normalize_observations=True, num_evals=task.evals + 1, num_eval_envs=task.eval_episodes,
                deterministic_eval=True, max_devices_per_host=1)


def brax_env(name: str) -> dict:
    """{"environment": the task, and wrap_env_fn where it is no brax Env subclass (the point mass: Brax's interface,
    not its class, which Brax SAC checks for)}."""
    from brax import envs as brax_envs

    from cdjax.envs import make_single_env

    env = make_single_env(name)
    return {"environment": env} if isinstance(env, brax_envs.Env) else {
        "environment": env, "wrap_env_fn": brax_envs.training.wrap}


def run_brax(name: str, task: SacTask, seed: int, rows) -> None:
    """Brax's SAC trainer on the task, evaluated by Brax at its evaluation steps."""
    import functools

    install_replicated()
    from brax.training.agents.sac import networks as sac_networks
    from brax.training.agents.sac import train as sac

    factory = functools.partial(sac_networks.make_sac_networks, hidden_layer_sizes=task.hidden)
    t_start = time.perf_counter()

    def progress(step, metrics):
        rows.add(task=name, framework="brax", variant="brax-sac", seed=seed, env_steps=int(step),
                 eval_return=float(metrics["eval/episode_reward"]), sps=float(metrics.get("training/sps", 0.0)),
                 wall_s=time.perf_counter() - t_start)

    sac.train(seed=seed, network_factory=factory, progress_fn=progress, **brax_env(task.env), **brax_kwargs(task))


def speed(name: str, task: SacTask, rows, seed_counts=(1, 10), updates: int = 50, plain: bool = False,
          sets: dict | None = None, brax: bool = True, trace: str | None = None) -> None:
    """cdjax's env steps/s and gradient steps/s (all seeds together) over `updates` compiled updates, after one
    warm-up call, at each number of vmapped seeds; Brax SAC's from its own training/sps over a short run. With
    `trace`, one more call of each cdjax program runs under jax.profiler into TRACE/cdjax-<task>-x<seeds>, whose
    device ops `benchmarks.profile_summary` summarises into summary.md there (the profile of what the time goes to)."""
    import functools

    import jax

    from cdjax.agents import offpolicy
    from cdjax.sweep import make_sweep

    for seeds in seed_counts:
        config = cdjax_config(task, plain=plain, sets=sets)
        sweep = make_sweep(offpolicy.make_trainer(config))
        keys, hps = sweep.grid(seed=0, num_seeds=seeds, hps=[cdjax_hparams(task, sets)])
        state = sweep.init(keys, hps)
        t0 = time.perf_counter()
        program = sweep.lower(state, hps, updates).compile()
        compile_s = time.perf_counter() - t0
        state, metrics = program(state, hps)  # warm-up (and the random-action steps)
        jax.block_until_ready(metrics)
        t0 = time.perf_counter()
        state, metrics = program(state, hps)
        jax.block_until_ready(metrics)
        wall = time.perf_counter() - t0
        rows.add(task=name, framework="cdjax", case="speed", variant=variant_name("model-free", plain, sets),
                 seeds=seeds, compile_s=compile_s,
                 env_steps_per_s=seeds * updates * config.env_steps_per_update / wall,
                 grad_steps_per_s=seeds * updates * config.grad_steps / wall)
        if trace:
            from benchmarks import profile_summary

            where = pathlib.Path(trace) / f"cdjax-{name}-x{seeds}"
            with profile_summary.trace(where, program):
                jax.block_until_ready(program(state, hps))
            text = profile_summary.markdown(profile_summary.summarize(where))
            (where / "summary.md").write_text(text + "\n")
            print(text, flush=True)
    if not brax:
        return
    # two epochs of Brax's training: the last one's training/sps is measured after its compilation
    short = dataclasses.replace(task, evals=2, steps_per_eval=task.min_replay + updates * task.num_envs * 4)
    marks = []
    install_replicated()
    from brax.training.agents.sac import networks as sac_networks
    from brax.training.agents.sac import train as sac

    sac.train(seed=0, progress_fn=lambda step, m: marks.append(m), **brax_env(task.env),
              network_factory=functools.partial(sac_networks.make_sac_networks, hidden_layer_sizes=task.hidden),
              **brax_kwargs(short))
    sps = float(marks[-1].get("training/sps", float("nan")))
    rows.add(task=name, framework="brax", case="speed", seeds=1, env_steps_per_s=sps,
             grad_steps_per_s=sps / task.num_envs * task.updates_per_step)


def main(argv=None) -> int:
    from benchmarks.learning import Rows

    p = Parser(prog="python -m benchmarks.brax_sac", description=__doc__,
               formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tasks", nargs="+", default=["ant", "halfcheetah", "hopper", "humanoid"], choices=list(TASKS))
    p.add_argument("--frameworks", nargs="+", default=["cdjax", "brax"], choices=["cdjax", "brax"])
    p.add_argument("--arms", nargs="+", default=["model-free"], help="cdjax off-policy arms (default model-free)")
    p.add_argument("--cdjax-plain", action="store_true", help="cdjax as Brax's SAC: 1-step, no LayerNorm, no encoder")
    p.add_argument("--cdjax-set", action="append", metavar="FIELD=VALUE",
                   help="put an off-policy Config or HParams field over cdjax's (repeatable; named in the variant)")
    p.add_argument("--seeds", type=positive, default=5)
    p.add_argument("--first-seed", type=non_negative, default=0,
                   help="seeds first-seed .. first-seed+seeds-1 (so that several processes can share a task's seeds)")
    p.add_argument("--evals", type=positive, help="override every task's number of evaluations")
    p.add_argument("--steps-per-eval", type=positive, help="override every task's env steps between evaluations")
    p.add_argument("--speed", action="store_true", help="the speed case (1 and 10 vmapped seeds against Brax SAC)")
    p.add_argument("--trace", metavar="DIR", help="--speed: a jax.profiler trace of one call of each cdjax program, "
                   "summarised (DIR/cdjax-<task>-x<seeds>/summary.md)")
    p.add_argument("--tiny", action="store_true", help="CPU smoke: the point task, 1 seed")
    p.add_argument("--out", help="output directory (rows.jsonl, meta.json)")
    args = p.parse_args(argv)
    sets = parse_sets(args.cdjax_set)
    if args.trace and not args.speed:
        refuse(p.prog, "--trace goes with --speed (it profiles the speed case's cdjax programs)")
    if args.tiny:
        args.tasks, args.seeds = ["point"], 1
    from cdjax import io
    from cdjax.protocol import ConfigError

    out = pathlib.Path(args.out or f"benchmarks/results/{datetime.date.today()}-brax-sac")
    try:
        io.RunDir(out).check_writable()
    except (ConfigError, io.RunDirError) as err:
        refuse(p.prog, str(err))
    rows = Rows(out)
    tasks = {}
    for name in args.tasks:
        task = TASKS[name]
        tasks[name] = dataclasses.replace(task, evals=args.evals or task.evals,
                                          steps_per_eval=args.steps_per_eval or task.steps_per_eval)
    rows.write_meta("brax_sac", argv, tasks={n: dataclasses.asdict(t) for n, t in tasks.items()})
    for name, task in tasks.items():
        if args.speed:
            speed(name, task, rows, seed_counts=(1, 2) if args.tiny else (1, 10), updates=4 if args.tiny else 50,
                  plain=args.cdjax_plain, sets=sets, brax="brax" in args.frameworks, trace=args.trace)
            continue
        if "cdjax" in args.frameworks:
            for arm in args.arms:
                run_cdjax(name, task, args.seeds, rows, arm=arm, plain=args.cdjax_plain, seed=args.first_seed,
                          sets=sets)
        if "brax" in args.frameworks:
            for seed in range(args.first_seed, args.first_seed + args.seeds):
                run_brax(name, task, seed, rows)
    print(f"rows in {rows.path}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
