"""The Atari experiment's GPU units: `python -m experiments.atari list`, `... run UNIT --out DIR`.

  ale-GAME      the ALE tier (issue 23; GAME breakout, seaquest, mspacman or frostbite): `cdjax sweep --setting atari
                --preset GAME --arms a2c a2c-cd --seeds 3 --steps STEPS` (default 1,000,000 agent steps = 4M frames
                per run; the 3 seeds' 48 emulators one ale-py vector environment, one thread per CPU core: one unit
                per machine), stopped by --time-limit (default 1080 s, compile included), then every run evaluated
                at its last checkpoint (100 episodes, sampled actions) within `eval_s` (at least 60 s, fewer where it
                would end past --end less 120 s), plotted and reported (DIR/GAME, DIR/report)
  ale40m-GAME-ARM  one arm of the ALE tier at the paper's budget (experiments/atari/ale40m.py; ARM a2c or a2c-cd):
                `cdjax sweep --setting atari --preset GAME --arms ARM --seeds 3 --steps 10000000` (40M frames per run;
                its 48 emulators, one thread per core it is given: `cpus`, a taskset list), or `--resume` where the
                directory holds the run already (brought back from an earlier machine, `ale40m.py start`), stopped by
                --time-limit; once it has reached its steps, evaluated (100 episodes per run) within `eval_s`; then
                its resumable state (run directory with each arm's latest checkpoint) packed into parts of at most
                16 MiB under `outbox` (DIR/GAME, DIR/outbox)
  minatar-GAME  A2C against A2C + consistency on a MinAtar game (its preset: 10 seeds vmapped per arm), stopped by
                --time-limit, evaluated over 100 episodes per run where the time limit stopped it before its own final
                evaluation, reported (DIR/GAME, DIR/report)

ale-py and gymnasium must import (the GPU image lacks them: experiments/wheels.sh installs carried wheels).
"""

from __future__ import annotations

import signal

from cdjax.agents.atari.minatar import GAMES
from experiments.atari import ale40m
from experiments.launch import Context, Step, Unit, python

ALE_GAMES = ale40m.GAMES  # the paper's four: breakout, seaquest, mspacman, frostbite
LIMIT_S, END_S = 1080, 1380
EVAL_S = 360  # an ALE unit's evaluation at most
TAIL_S = 120  # the plot and the report, after the evaluation (50 s each at most)
MINATAR_EVAL_S = 210  # a MinAtar run's evaluation where its sweep did not evaluate it
# an ALE run keeps its last 1,250 updates whole: the last 10% of 1M agent steps, which its final return averages
THIN = {"points": 1500, "tail": 1250}


def eval_seconds(ctx: Context, most: int) -> int:
    """What an ALE unit's evaluation may take: what is left before --end less TAIL_S, within [60, most]."""
    return max(60, min(most, int(ctx.end - ctx.elapsed() - TAIL_S)))


def _final_evals(ctx: Context, game: str) -> int:
    path = ctx.out / game / "eval.jsonl"
    return path.read_text().count('"episodes": 100') if path.exists() else 0


def _ale(game: str):
    def steps(ctx: Context) -> list[Step]:
        run = str(ctx.out / game)
        return [Step(python("cdjax.cli", "sweep", "--setting", "atari", "--preset", game, "--arms", "a2c", "a2c-cd",
                            "--seeds", "3", "--steps", ctx.params["steps"], "--no-progress", "--no-final-eval",
                            "--time-limit", str(ctx.limit), "--out", run, *ctx.params["sweep"].split()),
                     timeout=ctx.limit + 120),
                Step(python("cdjax.cli", "eval", run, "--episodes", "100"),
                     timeout=lambda c: eval_seconds(c, int(c.params["eval_s"])), signal=signal.SIGTERM, kill_after=10),
                Step(python("cdjax.cli", "plot", run), timeout=50, signal=signal.SIGTERM, kill_after=10),
                Step(python("experiments.atari.report", run, "--out", str(ctx.out / "report")), timeout=50,
                     signal=signal.SIGTERM, kill_after=10)]
    return steps


def _ale40m(game: str, arm: str):
    """One arm of a game at the paper's budget, continued from where the run directory left it (ale40m.py)."""
    piece = f"ale40m-{game}-{arm}"

    def steps(ctx: Context) -> list[Step]:
        run = ctx.out / game
        cpus, box = ctx.params["cpus"], ctx.params["outbox"] or str(ctx.out / "outbox")
        if (run / "run.json").exists():  # brought here from an earlier machine (or an earlier call): its own settings
            sweep = ("cdjax.cli", "sweep", "--out", str(run), "--resume")
        else:
            sweep = ("cdjax.cli", "sweep", "--setting", "atari", "--preset", game, "--arms", arm, "--seeds",
                     str(ale40m.SEEDS), "--steps", ctx.params["steps"], "--no-final-eval", "--out", str(run),
                     *ctx.params["sweep"].split())
        eval_s = int(ctx.params["eval_s"])
        return [Step(ale40m.pinned(cpus, python(*sweep, "--no-progress", "--time-limit", str(ctx.limit))),
                     timeout=ctx.limit + 120, when=lambda c: not ale40m.complete(run)),
                Step(ale40m.pinned(cpus, python("cdjax.cli", "eval", str(run), "--episodes", "100")),
                     timeout=lambda c: max(30, min(eval_s, int(c.end - c.elapsed() - ale40m.PACK_S))),
                     signal=signal.SIGTERM, kill_after=10,
                     when=lambda c: ale40m.complete(run) and not ale40m.evaluated(run)),
                Step(ale40m.pinned(cpus, python("experiments.atari.ale40m", "pack", str(run), box, "--name", piece,
                                                "--log", str(ctx.out / "unit.log"))),
                     timeout=ale40m.PACK_S, signal=signal.SIGTERM, kill_after=10,
                     when=lambda c: (run / "run.json").exists())]
    return steps


def _minatar(game: str):
    def steps(ctx: Context) -> list[Step]:
        run = str(ctx.out / game)
        return [Step(python("cdjax.cli", "sweep", "--setting", "atari", "--preset", f"minatar-{game}", "--out", run,
                            "--no-progress", "--time-limit", str(ctx.limit), *ctx.params["sweep"].split()),
                     timeout=ctx.limit + 120),
                Step(python("cdjax.cli", "eval", run, "--episodes", "100"), timeout=MINATAR_EVAL_S,
                     signal=signal.SIGTERM, kill_after=30, when=lambda c: _final_evals(c, game) == 0),
                Step(python("experiments.atari.report", run, "--out", str(ctx.out / "report")))]
    return steps


def _units() -> dict[str, Unit]:
    units = [Unit(f"ale-{g}", f"ALE {g}: a2c and a2c-cd, 3 seeds, `steps` agent steps or the time limit, evaluated "
                  "over 100 episodes", 23, _ale(g), {"steps": "1000000", "sweep": "", "eval_s": str(EVAL_S)})
             for g in ALE_GAMES]
    units += [Unit(f"ale40m-{g}-{arm}", f"ALE {g}, {arm} alone: 3 seeds, `steps` agent steps (the paper's 40M "
                   "frames), resumed where its directory holds the run, stopped by the time limit, evaluated over 100 "
                   "episodes once it reached `steps`, packed for the next machine", 30, _ale40m(g, arm),
                   {"steps": str(ale40m.STEPS), "sweep": "", "eval_s": str(ale40m.EVAL_S), "cpus": "", "outbox": ""})
               for g in ALE_GAMES for arm in ale40m.ARMS]
    units += [Unit(f"minatar-{g}", f"MinAtar {g}: the preset's a2c and a2c-cd, 10 seeds, its steps or the time "
                   "limit, evaluated over 100 episodes", 23, _minatar(g), {"sweep": ""}) for g in GAMES]
    return {u.name: u for u in units}


UNITS = _units()
