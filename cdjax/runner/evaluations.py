"""Evaluating a sweep's arms: the evaluation's length checked before anything runs, each arm's evaluator compiled once
per sweep (in the background while training runs, shared by the arms whose programs are the same), every run
evaluated and its records appended to eval.jsonl."""

from __future__ import annotations

import concurrent.futures
import contextlib
import threading
import time
from typing import Callable

import jax
import numpy as np

from cdjax import io, multihost, runtime
from cdjax.evaluate import MAX_EVAL_EPISODE_STEPS, Evaluator, episode_steps, eval_records, make_evaluator
from cdjax.protocol import ConfigError
from cdjax.runner.arms import Arm, _timed, timed
from cdjax.runner.spec import SweepSpec

EVAL_TAG = 0x0E7A1  # folded into each run's training key to get its evaluation key
# This process's evaluators, by the sweep (held, so that its id stays its own), episodes, kind of actions and compile
# mode: every evaluation of a sweep, and a later sweep of the same arms in this process, reuses one.
_EVALUATORS: dict = {}


def check_evaluation(arms: list[Arm], spec: SweepSpec, resume: bool, say: Callable[[str], None]) -> None:
    """Refuse (ConfigError) a sweep whose evaluations would run impractically long: an arm's eval episodes time out
    after more than MAX_EVAL_EPISODE_STEPS agent steps, stepped one after another. A resume, whose options cannot
    change, is warned instead (training goes on)."""
    if not (spec.final_eval or spec.eval_every):
        return
    for arm in arms:
        steps = episode_steps(arm.trainer.eval_env(spec.eval_episodes))
        if steps <= MAX_EVAL_EPISODE_STEPS:
            continue
        field = next((f for f in ("eval_episode_length", "episode_length") if hasattr(arm.plan.config, f)), None)
        flag = f"--{field.replace('_', '-')}" if field else "episode length"
        what = (f"arm {arm.name}'s evaluation episodes last up to {steps:,} agent steps"
                + (f" ({flag} {getattr(arm.plan.config, field):,})" if field else "")
                + ", stepped one after another, so the sweep's evaluations would run impractically long (the limit is "
                f"{MAX_EVAL_EPISODE_STEPS:,} agent steps)")
        if not resume:
            raise ConfigError(f"{what[0].upper()}{what[1:]}: give a shorter {flag}, or --no-final-eval (and no "
                              "--eval-every) to train without evaluating.")
        say(f"Warning: {what}; stop them with Ctrl-C after training (the checkpoints are kept).")
        return


def evaluator(arm: Arm, episodes: int, deterministic: bool) -> Evaluator:
    """The arm's evaluator (cdjax.evaluate.make_evaluator), made once per sweep, episodes, kind of actions and compile
    mode in this process and kept for every evaluation of the sweep; its timings are the arm's."""
    key = (id(arm.sweep), episodes, deterministic, runtime.compile_mode())
    if key not in _EVALUATORS:
        _EVALUATORS[key] = (arm.sweep, make_evaluator(arm.trainer, episodes=episodes, deterministic=deterministic))
    made = _EVALUATORS[key][1]
    made.timings, made.arm = arm.timings, arm.name
    return made


def eval_inputs(arm: Arm, abstract: bool = False) -> tuple:
    """(policy, keys, hps) of the arm's runs for its evaluator, every leaf [R_padded] laid out as the runs' state
    (`Sweep.sharding`), so that a program compiled from their shapes in advance serves them. Each run's evaluation key
    is its training key folded with EVAL_TAG. abstract=True: their ShapeDtypeStructs, from arm.abstract (nothing
    computed)."""
    sharding = arm.sweep.sharding
    if abstract:
        def shape(x):
            return jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding)

        policy = jax.tree.map(shape, jax.eval_shape(arm.trainer.policy, arm.abstract))
        return policy, arm.sweep.key_shapes(arm.num_runs), jax.tree.map(shape, arm.hps)
    keys = jax.vmap(lambda k: jax.random.fold_in(k, EVAL_TAG))(arm.keys)
    return jax.device_put((arm.trainer.policy(arm.state), keys, arm.hps), sharding)


def compile_evaluators(arms: list[Arm], episodes: int, deterministic: bool) -> None:
    """Compile the arms' evaluation programs from shapes alone in a background thread, while training runs: each
    arm's `evaluating` is the future of its compiled program (arms that lower to the same program share it:
    cdjax.evaluate). A compile that fails there (beside training, with its memory in use) is tried again where the
    evaluation waits for it (evaluate_arms), which raises what that one meets."""
    def work(pairs):
        for arm, future in pairs:
            try:
                future.set_result(evaluator(arm, episodes, deterministic).compiled(eval_inputs(arm, abstract=True),
                                                                                  room=arm.room))
            except BaseException as err:  # noqa: BLE001 - handed to the evaluation that waits for it
                future.set_exception(err)

    pairs = []
    for arm in arms:
        arm.evaluating = concurrent.futures.Future()
        arm.evaluating.set_running_or_notify_cancel()
        pairs.append((arm, arm.evaluating))
    # a daemon thread: a process stopped during training does not wait for an evaluator it will not use
    threading.Thread(target=work, args=(pairs,), name="cdjax-evaluators", daemon=True).start()


def evaluate_arms(rd: io.RunDir, arms: list[Arm], num_seeds: int, episodes: int, deterministic: bool,
                  say: Callable[[str], None]) -> list[dict]:
    """Evaluate every run of every arm at its current state; append the records to eval.jsonl.

    One jit(vmap) program over an arm's runs (cdjax.evaluate.make_evaluator), fed only the policy part of the state,
    compiled once for every evaluation of the sweep (in advance where `compile_evaluators` began it, else now) and
    shared by the arms whose programs are the same. Each run's evaluation key is its training key folded with
    EVAL_TAG. Several processes: every process evaluates its runs and gets every record; process 0 appends them.
    """
    t0 = time.perf_counter()
    timings = arms[0].timings if arms else None
    records = []
    for arm in arms:
        ready = arm.evaluating
        if ready is not None:
            waited = time.perf_counter()
            with contextlib.suppress(Exception):  # a failed compile is tried again just below, training done
                ready.result()
            _timed(arm, "evaluator", "wait", waited)
            arm.evaluating = None
        args = eval_inputs(arm)
        program = evaluator(arm, episodes, deterministic).compiled(args, room=arm.room)
        started = time.perf_counter()
        results = multihost.fetch(program(*args))
        _timed(arm, "evaluation", "evaluate", started)  # the episodes alone (the compile has rows of its own)
        records += eval_records(results, arm=arm.name, hp_labels=list(arm.plan.labels), seeds=range(num_seeds),
                                deterministic=deterministic, update=arm.updates, env_steps=arm.env_steps())
    with multihost.together():
        if multihost.is_writer():
            with timed(timings, "all", "eval.jsonl", "write"):
                io.append_jsonl(rd.eval, records)
    if timings is not None:
        timings.add("all", "evaluation", "host", t0)
    means: dict[str, list[float]] = {}
    for row in records:
        if row.get("eval/return") is not None:
            means.setdefault(row["arm"], []).append(row["eval/return"])
    text = "  ".join(f"{arm} {np.mean(v):.1f}" for arm, v in means.items())
    say(f"Evaluation ({episodes} episodes per run, {'deterministic' if deterministic else 'sampled'} actions, "
        f"{time.perf_counter() - t0:.1f} s): return {text}")
    return records


def finished_evaluation(rd: io.RunDir, arms: list[Arm], num_seeds: int, episodes: int,
                        deterministic: bool = True) -> bool:
    """Whether eval.jsonl already holds the final evaluation (of that kind) of every run of every arm."""
    final = {a.name: a.num_updates for a in arms}
    have = {(r.get("arm"), r.get("hp"), r.get("seed")) for r in io.read_jsonl(rd.eval)
            if r.get("deterministic", True) == deterministic and r.get("episodes") == episodes
            and r.get("update") == final.get(r.get("arm"))}
    return all((a.name, label, s) in have for a in arms for label in a.plan.labels for s in range(num_seeds))
