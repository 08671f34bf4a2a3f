"""The Atari experiment's GPU units: `python -m experiments.atari list`, `... run UNIT --out DIR`.

  ale-GAME      the ALE tier (issue 23; GAME breakout, seaquest, mspacman or frostbite): `cdjax sweep --setting atari
                --preset GAME --arms a2c a2c-cd --seeds 3 --steps STEPS` (default 1,000,000 agent steps = 4M frames
                per run; the 3 seeds' 48 emulators one ale-py vector environment, one thread per CPU core: one unit
                per machine), stopped by --time-limit (default 1080 s, compile included), then every run evaluated
                at its last checkpoint (100 episodes, sampled actions) within `eval_s` (at least 60 s, fewer where it
                would end past --end less 120 s), plotted and reported (DIR/GAME, DIR/report)
  minatar-GAME  A2C against A2C + consistency on a MinAtar game (its preset: 10 seeds vmapped per arm), stopped by
                --time-limit, evaluated over 100 episodes per run where the time limit stopped it before its own final
                evaluation, reported (DIR/GAME, DIR/report)

ale-py and gymnasium must import (the GPU image lacks them: experiments/wheels.sh installs carried wheels).
"""

from __future__ import annotations

import signal

from cdjax.agents.atari.minatar import GAMES
from experiments.launch import Context, Step, Unit, python

ALE_GAMES = ("breakout", "seaquest", "mspacman", "frostbite")
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
    units += [Unit(f"minatar-{g}", f"MinAtar {g}: the preset's a2c and a2c-cd, 10 seeds, its steps or the time "
                   "limit, evaluated over 100 episodes", 23, _minatar(g), {"sweep": ""}) for g in GAMES]
    return {u.name: u for u in units}


UNITS = _units()
