"""What each subcommand of `cdjax` does once its options are read: sweep, eval, plot, envs."""

from __future__ import annotations

import argparse
import contextlib
import pathlib
import shlex
import sys

from cdjax import agents, io, multihost
from cdjax.cli.parser import sweep_spec
from cdjax.options import UsageError
from cdjax.protocol import Setting
from cdjax.runner.spec import INT32_MAX

def cmd_sweep(args: argparse.Namespace, setting: Setting, command: str, limit=None) -> None:
    from cdjax.runner import run_sweep

    rd = io.RunDir(pathlib.Path(args.out))
    rd.check_name()
    # what a lost process's sentence says before the sweep's loop says which checkpoints are intact (cdjax.runner)
    multihost.tail(lambda: f" before training started; no update was trained in {rd.path}" + (
        f"; resume with `cdjax sweep --out {shlex.quote(str(rd.path))} --resume --distributed`." if rd.exists()
        else "; run the command again."))
    out = run_sweep(sweep_spec(args, setting, command), resume=args.resume, after_chunk=limit,
                    restart=tuple(args.restart_arm))
    if multihost.is_writer():
        print(f"Done: {out}")


def say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def _say_unnamed_arms(rd: io.RunDir, tell=say) -> None:
    """`cdjax eval` and `cdjax plot` say, as a resume does (cdjax.runner.loop), when the directory holds logs or
    checkpoints of arms its run.json does not name (`RunDir.unnamed_arms`): a note, the command goes on."""
    if note := rd.unnamed_arms():
        tell(note)


def cmd_eval(args: argparse.Namespace) -> None:
    import jax

    from cdjax.evaluate import render_video
    from cdjax.runner import evaluate_arms, restore_arms
    from cdjax.runner.console import library_log, stopped

    if not 1 <= args.episodes <= INT32_MAX:
        raise UsageError(f"--episodes must be an integer from 1 to {INT32_MAX:,}, got {args.episodes}.")
    rd = io.RunDir(pathlib.Path(args.run_dir))
    writer = multihost.is_writer()
    tell = say if writer else (lambda text: None)  # several processes: process 0 speaks for all
    multihost.tail(lambda: f"; nothing was added to {rd.eval}.")
    try:  # a peer lost in the first collective (the checks) ends this process as one lost later does, same sentence
        with multihost.together():
            rd.check_name("RUN_DIR")
            rd.read()  # a clear error for a directory that holds no run
            if writer:  # what the evaluation writes, checked before any episode runs
                rd.check_run_writable(dirs=("videos",) if args.video else (), files=("eval.jsonl", ".lock"))
        with contextlib.ExitStack() as held, library_log(rd.process_log(multihost.index()), tell):
            with multihost.together():
                if writer:  # a live sweep turns its checkpoints over and appends to eval.jsonl: not beside it
                    held.enter_context(rd.lock("evaluate it when it has ended (its checkpoints turn over while it "
                                               "trains)"))
                    _say_unnamed_arms(rd, tell)
                spec, arms = restore_arms(args.run_dir)
            sampled = args.stochastic or (agents.get(spec.setting).eval_sampled and not args.deterministic)
            records = evaluate_arms(rd, arms, spec.seeds, args.episodes, not sampled, tell)
    except KeyboardInterrupt as err:
        raise stopped(err, f"Interrupted before the evaluation was done; nothing was added to {rd.eval}.") from None
    except multihost.PeerLost as err:
        raise multihost.PeerLost(f"{err}; nothing was added to {rd.eval}.", complete=True) from None
    if not writer:
        return
    _print_eval(records)
    print(f"Appended {len(records)} records to {rd.eval}")
    if args.video:
        try:
            for arm in arms:
                for i, label in enumerate(arm.plan.labels):
                    policy = jax.tree.map(lambda x: x[i * spec.seeds], arm.trainer.policy(arm.state))  # seed 0
                    path = render_video(arm.trainer, policy, jax.random.key(spec.seed),
                                        rd.path / "videos" / f"{arm.name}-{label}-seed0.mp4",
                                        steps=arm.trainer.eval_env(1).episode_length)
                    if path is not None:
                        print(f"Wrote {path}")
        except KeyboardInterrupt as err:
            raise stopped(err, f"Interrupted while rendering videos into {rd.path / 'videos'}; the evaluation is in "
                               f"{rd.eval}.") from None


def _print_eval(records: list[dict]) -> None:
    import numpy as np

    groups: dict[tuple[str, str], list[float]] = {}
    for row in records:
        groups.setdefault((row["arm"], row["hp"]), [])
        if row.get("eval/return") is not None:
            groups[(row["arm"], row["hp"])].append(float(row["eval/return"]))
    width = max([len(a) + len(h) + 3 for a, h in groups] + [8])
    print(f"{'arm / hp':<{width}}  {'seeds':>5}  {'mean return':>11}  {'std over seeds':>14}")
    for (arm, hp), values in groups.items():
        mean, std = (np.mean(values), np.std(values)) if values else (float("nan"), float("nan"))
        print(f"{arm + ' / ' + hp:<{width}}  {len(values):>5}  {mean:>11.2f}  {std:>14.2f}")


def cmd_plot(args: argparse.Namespace) -> None:
    from cdjax.plots import plot_run, plot_runs
    from cdjax.runner.console import stopped
    from cdjax.runner.plan import recorded_return_note

    dirs, runs = [], []
    for run_dir in args.run_dirs:
        rd = io.RunDir(pathlib.Path(run_dir))
        rd.check_name("RUN_DIR")
        runs.append(rd.read())  # a clear error for a directory that holds no run
        rd.check_logs("nothing was plotted: restore it, or decompress its readable part into the plain log beside "
                      "it (xz -dc or gzip -dc) and remove it, to plot what it holds.")
        _say_unnamed_arms(rd)
        dirs.append(rd.path)
    if len(set(d.resolve() for d in dirs)) < len(dirs):
        raise UsageError("a RUN_DIR is named twice; name each run once.")
    if len(dirs) > 1 and args.out is None:
        raise UsageError("several RUN_DIRs are pooled into one summary: name where it goes with --out DIR.")
    if not 1 <= args.bootstrap_reps <= INT32_MAX:
        raise UsageError(f"--bootstrap-reps must be an integer from 1 to {INT32_MAX:,}, got {args.bootstrap_reps}.")
    out = dirs[0] if args.out is None else pathlib.Path(args.out)
    if args.out is not None:
        io.RunDir(out).check_name("--out")
        if out.exists() and not out.is_dir():
            raise UsageError(f"--out {out} is a file; name a directory.")
        if len(dirs) > 1 and out.resolve() in {d.resolve() for d in dirs}:
            raise UsageError(f"--out {out} is one of the runs, whose own summary the pooled one would replace; "
                             "name another directory.")
        another = io.RunDir(out).exists() or (out / "checkpoints").is_dir()  # run.json, or a run's checkpoints
        if another and out.resolve() not in {d.resolve() for d in dirs}:
            raise UsageError(f"--out {out} holds another run (its run.json or checkpoints/), whose summary and plots "
                             "these would replace; name that run's own directory or one that holds no run.")
    again = " ".join(shlex.quote(str(a)) for a in (*dirs, *(("--out", out) if args.out is not None else ())))
    notes = [note] if (note := recorded_return_note(runs)) else []  # what the sweep said of its ranking, as recorded
    try:
        if len(dirs) == 1 and args.out is None:
            written = plot_run(out, reps=args.bootstrap_reps, say=say, notes=notes)
        else:
            written = plot_runs(dirs, out, reps=args.bootstrap_reps, say=say, notes=notes)
    except KeyboardInterrupt as err:
        raise stopped(err, f"Interrupted while plotting; the plots and summary of {out} may be partly rewritten: "
                           f"run `cdjax plot {again}` again.") from None
    for path in written.values():
        print(f"Wrote {path}")


def cmd_envs() -> None:
    """Print every env name `--env` takes, one a line, with what it is (cdjax.envs.describe)."""
    from cdjax import envs

    for name, about in envs.describe().items():
        print(f"{name:<29} {about}")
