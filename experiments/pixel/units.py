"""The pixel experiment's GPU units (issue 22 and after): `python -m experiments.pixel list`, `... run UNIT --out DIR`.

Each unit fits one GPU for about 30 minutes: its sweeps stop by --time-limit (default 1260 s from its start, compile
included) and its evaluation, plots and strips end by --end (default 1680 s). The units:

  roofline      experiments.pixel.roofline on halfcheetah's preset (30 runs, the real task's data): every
                compute_dtype/conv_impl variant, with a profile of each (roofline.json, .md, profile/)
  core          the update's speed with core_impl flax and fused, halfcheetah's ltq-cd at the preset's sizes
                (bfloat16/per-run), 10 runs, SyntheticWorld's frames, one roofline process each
  grad-dtype    the update's speed with output_grad float32 and compute (bfloat16/per-run, core fused), 30 runs
  profile       the roofline of the presets' update (30 runs, synthetic frames) with a profile, then the same with
                XLA's dynamic-slice fusion (skipped where the XLA refuses the flag)
  sweep-speed   halfcheetah's preset sweep (30 runs) for `updates` updates, once as the model of before (float32,
                grouped, flax, the policy at the model's rate) and once as the presets run it
  sweep-long    the presets' sweep at the fourth pass's length (`updates`, default 1,400), stopped by `limit_s`
  devices       (several GPUs) the sweep's frames/s on 1, 2 and 4 of them in one process (experiments.pixel.speed)
  precision     a reference (`reference`, default the presets) against `candidate` at equal updates: halfcheetah's
                preset arms, 10 seeds, `updates` updates each, each sweep stopped by half the time limit; then
                experiments.pixel.precision (precision.md)
  lr-check      the ltq arm on halfcheetah, 5 seeds, a grid of the model's rate x the policy's
  TASK-ARM      the experiment at the presets' length: TASK halfcheetah, reacher or pusher; ARM ltq, ltq-cd (alpha 100,
                cc_policy 0 and 1: 20 runs), ltq-cd0 or ltq-cd1 (ltq-cd with cc_policy 0 or 1 alone: 10 runs; not
                the CLI's arm ltq-cdN, which is ltq-cd with horizon N), 10 seeds, 10,000 updates or what fits the time
                limit, then evaluated from pixels, plotted and its strips drawn (DIR/pixel, DIR/strips)
  expert-TASK   the state-based expert: cdjax's model-free arm on the state (obs setting, 1 seed) for the time limit,
                evaluated, exported (DIR/expert.msgpack)
  cost-TASK     experiments.pixel.data_cost: the dataset kept on the device against rendered on the fly (10 runs)

The experts are the kept ones (experiments/pixel/data/three-tasks-x2/TASK/expert.msgpack) unless `expert` says
otherwise.
"""

from __future__ import annotations

import signal

from experiments.launch import Context, Step, Unit, python

TASKS = ("halfcheetah", "reacher", "pusher")
ARMS = ("ltq", "ltq-cd", "ltq-cd0", "ltq-cd1")
EXPERTS = "experiments/pixel/data/three-tasks-x2"
LIMIT_S, END_S = 1260, 1680
EVAL_S = 300  # a TASK-ARM unit's evaluation at most; at least 120, less where the strips would end past --end
STRIPS_S = 180  # the strips (up to 150 s) and the plot, after the evaluation
FRAMES_PER_UPDATE = 800  # halfcheetah's preset: 8 sequences x 100 steps (the --steps of a number of updates)
THIN = {"points": 250, "tail": 60}

ROOFLINE = python("experiments.pixel.roofline", "--env", "halfcheetah")
SYNTHETIC = ("--variants", "bfloat16/per-run", "--synthetic")


def _sweep(task: str = "halfcheetah", expert: str | None = None) -> tuple[str, ...]:
    return python("cdjax.cli", "sweep", "--setting", "pixel", "--preset", f"pixel-{task}", "--expert",
                  expert or f"{EXPERTS}/{task}/expert.msgpack")


def _split(text: str) -> tuple[str, ...]:
    return tuple(text.split())


def _roofline(ctx: Context) -> list[Step]:
    return [Step((*ROOFLINE, "--runs", "30", "--profile", str(ctx.out / "profile"),
                  "--out", str(ctx.out / "roofline.json")))]


def _core(ctx: Context) -> list[Step]:
    return [Step((*ROOFLINE, "--runs", "10", *SYNTHETIC, "--set", f"core_impl={impl}",
                  "--out", str(ctx.out / f"{impl}.json")), log=f"{impl}.log") for impl in ("flax", "fused")]


def _grad_dtype(ctx: Context) -> list[Step]:
    return [Step((*ROOFLINE, "--runs", "30", *SYNTHETIC, "--set", "core_impl=fused", f"output_grad={grad}",
                  "--out", str(ctx.out / f"{name}.json")), log=f"{name}.log")
            for grad, name in (("float32", "grad-float32"), ("compute", "grad-bfloat16"))]


def _profile(ctx: Context) -> list[Step]:
    flag = "xla_gpu_enable_dynamic_slice_fusion"
    base = (*ROOFLINE, "--runs", "30", *SYNTHETIC)
    return [Step((*base, "--profile", str(ctx.out / "profile"), "--out", str(ctx.out / "presets.json")),
                 log="presets.log"),
            Step((*base, "--out", str(ctx.out / "slice-fusion.json")), log="slice-fusion.log",
                 env={"XLA_FLAGS": f"--{flag}=true"}, failed=f"this XLA refuses {flag} (slice-fusion.log)")]


def _sweep_speed(ctx: Context) -> list[Step]:
    sweep = (*_sweep(), "--steps", str(int(ctx.params["updates"]) * FRAMES_PER_UPDATE), "--chunk-updates", "100",
             "--no-progress", "--no-final-eval", "--time-limit", "300")
    before = ("--compute-dtype", "float32", "--conv-impl", "grouped", "--core-impl", "flax", "--lr-policy", "0")
    return [Step((*sweep, *before, "--out", str(ctx.out / "before")), log="before.log", timeout=420),
            Step((*sweep, "--out", str(ctx.out / "presets")), log="presets.log", timeout=420)]


def _sweep_long(ctx: Context) -> list[Step]:
    limit = int(ctx.params["limit_s"])
    return [Step((*_sweep(), "--steps", str(int(ctx.params["updates"]) * FRAMES_PER_UPDATE), "--no-progress",
                  "--no-final-eval", "--time-limit", str(limit), "--out", str(ctx.out / "presets")),
                 log="presets.log", timeout=limit + 120)]


def _devices(ctx: Context) -> list[Step]:
    return [Step(python("experiments.pixel.speed", "--env", "halfcheetah", "--runs", "32", "--devices",
                        *_split(ctx.params["counts"]), "--out", str(ctx.out / "devices.json")))]


def _precision(ctx: Context) -> list[Step]:
    half = ctx.limit // 2
    sweep = (*_sweep(), "--seeds", "10", "--steps", str(int(ctx.params["updates"]) * FRAMES_PER_UPDATE),
             "--no-progress", "--no-final-eval", "--time-limit", str(half))
    ref, cand = ctx.params["reference"], ctx.params["candidate"]
    return [Step((*sweep, *_split(ref), "--out", str(ctx.out / "reference")), timeout=half + 120),
            Step((*sweep, *_split(cand), "--out", str(ctx.out / "candidate")), timeout=half + 120),
            Step(python("experiments.pixel.precision", str(ctx.out / "reference"), str(ctx.out / "candidate"),
                        "--labels", ref or "presets", cand, "--out", str(ctx.out / "precision.md")))]


def _lr_check(ctx: Context) -> list[Step]:
    p = ctx.params
    return [Step((*_sweep(), "--arms", "ltq", "--seeds", "5", "--lr", *_split(p["lrs"]), "--lr-policy",
                  *_split(p["lr_policies"]), "--steps", str(int(p["updates"]) * FRAMES_PER_UPDATE), *_split(p["set"]),
                  "--no-progress", "--no-final-eval", "--time-limit", str(ctx.limit), "--out", str(ctx.out / "lr")),
                 timeout=ctx.limit + 300),
            Step(python("cdjax.cli", "plot", str(ctx.out / "lr")))]


def eval_seconds(ctx: Context, most: int) -> int:
    """What a TASK-ARM unit's evaluation may take: what is left before --end less the strips' time, within
    [120, most]."""
    left = int(ctx.end - ctx.elapsed() - STRIPS_S)
    return max(120, min(most, left))


def _task_arm(task: str, arm: str):
    arms = ("--arms", arm) if arm in ("ltq", "ltq-cd") else ("--arms", "ltq-cd", "--cc-policy", arm[-1])

    def steps(ctx: Context) -> list[Step]:
        run = str(ctx.out / "pixel")
        return [Step((*_sweep(task, ctx.params["expert"] or None), *arms, *_split(ctx.params["set"]),
                      "--no-progress", "--no-final-eval", "--time-limit", str(ctx.limit), "--out", run),
                     timeout=ctx.limit + 300),
                Step(python("cdjax.cli", "eval", run, "--episodes", "4"),
                     timeout=lambda c: eval_seconds(c, int(c.params["eval_s"])), signal=signal.SIGTERM, kill_after=30),
                Step(python("cdjax.cli", "plot", run)),
                Step(python("experiments.pixel.report", "--strips", run, str(ctx.out / "strips")), timeout=150,
                     signal=signal.SIGTERM, kill_after=10)]
    return steps


def _expert(task: str):
    def steps(ctx: Context) -> list[Step]:
        run = str(ctx.out / "expert-run")
        return [Step(python("cdjax.cli", "sweep", "--setting", "obs", "--preset", task, "--arms", "model-free",
                            "--seeds", "1", "--steps", ctx.params["steps"], "--no-progress", "--out", run,
                            "--time-limit", str(ctx.limit)), timeout=ctx.limit + 300),
                Step(python("cdjax.cli", "eval", run, "--episodes", "16"),
                     when=lambda c: '"deterministic": true' not in _text(c.out / "expert-run" / "eval.jsonl")),
                Step(python("cdjax.runner.export_expert", run, str(ctx.out / "expert.msgpack")))]
    return steps


def _cost(task: str):
    def steps(ctx: Context) -> list[Step]:
        return [Step(python("experiments.pixel.data_cost", "--env", task, "--expert",
                            ctx.params["expert"] or f"{EXPERTS}/{task}/expert.msgpack", "--runs", "10",
                            "--out", str(ctx.out / "cost.json")), timeout=240, signal=signal.SIGTERM, kill_after=20)]
    return steps


def _text(path) -> str:
    return path.read_text() if path.exists() else ""


def _units() -> dict[str, Unit]:
    units = [
        Unit("roofline", "halfcheetah's update, every compute_dtype/conv_impl variant, 30 runs, profiled", 10,
             _roofline, show=lambda c: ["roofline.md"]),
        Unit("core", "the update with core_impl flax and fused, 10 runs, synthetic frames", 3, _core,
             show=lambda c: ["flax.md", "fused.md"]),
        Unit("grad-dtype", "the update with output_grad float32 and compute, 30 runs, synthetic frames", 4,
             _grad_dtype, show=lambda c: ["grad-float32.md", "grad-bfloat16.md"]),
        Unit("profile", "the presets' update profiled, 30 runs, then with XLA's dynamic-slice fusion", 4, _profile,
             show=lambda c: ["presets.md", "slice-fusion.md"]),
        Unit("sweep-speed", "halfcheetah's preset sweep, 30 runs, `updates` updates, as before and as now", 8,
             _sweep_speed, {"updates": "200"}),
        Unit("sweep-long", "halfcheetah's preset sweep, 30 runs, `updates` updates, stopped by `limit_s`", 6,
             _sweep_long, {"updates": "1400", "limit_s": "480"}),
        Unit("devices", "the sweep's frames/s on `counts` GPUs of one machine, 32 runs", 10, _devices,
             {"counts": "1 2 4"}),
        Unit("precision", "halfcheetah's preset arms, 10 seeds, `updates` updates, `reference` against `candidate`",
             25, _precision, {"updates": "300", "reference": "",
                              "candidate": "--compute-dtype bfloat16 --conv-impl auto"},
             show=lambda c: ["precision.md"]),
        Unit("lr-check", "ltq on halfcheetah, 5 seeds, `lrs` x `lr_policies`, `updates` updates", 25, _lr_check,
             {"updates": "500", "lrs": "3e-5 1e-4 3e-4 1e-3", "lr_policies": "0 1e-3", "set": ""}),
    ]
    for task in TASKS:
        for arm in ARMS:
            runs = 20 if arm == "ltq-cd" else 10
            units.append(Unit(f"{task}-{arm}", f"pixel-{task}, {arm}, {runs} runs, 10,000 updates or the time limit, "
                              "evaluated, strips", 28, _task_arm(task, arm),
                              {"expert": "", "set": "", "eval_s": str(EVAL_S)}))
        units.append(Unit(f"expert-{task}", f"the obs setting's model-free arm on {task}, 1 seed, for the time "
                          "limit; evaluated and exported", 25, _expert(task), {"steps": "20000000"}))
        units.append(Unit(f"cost-{task}", f"{task}'s dataset on the device against rendered on the fly, 10 runs", 3,
                          _cost(task), {"expert": ""}))
    return {u.name: u for u in units}


UNITS = _units()
