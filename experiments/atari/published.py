"""Published A2C returns on the ALE games early in training, to set beside the ALE tier's learning curves.

Values read on 2026-11-25 from public learning-curve data (not from papers' tables: no paper tables A2C below 40M
frames). Steps are agent steps (4 frames each); all three ran `*NoFrameskip-v4` (no sticky actions, no-op starts)
and count whole games with unclipped rewards:
- baselines: OpenAI baselines' `benchmarks_atari10M.htm` (openai/baselines at fa37beb), the A2C curve (6 runs,
  probably smoothed) at x = 0.505e6 and 1.01e6 steps, read from the plotted line's coordinates;
- sb3-zoo: DLR-RM/rl-trained-agents (cd35bde) `a2c/GAMENoFrameskip-v4_1/`, one seed, 16 envs: the mean of the last
  100 training games at the step count, from its 16 monitor files merged in time order;
- nnabla-rl: sony/nnabla-rl (8354274) `reproductions/algorithms/atari/a2c/reproduction_results/`, 3 seeds,
  separate evaluation runs with a stochastic policy (its learning rate decays over 50M steps, not 10M).
Nothing was found for Frostbite below its final score.
"""

from __future__ import annotations

# {game (cdjax's ALE preset name): {source: ((agent steps, return), ...)}}
A2C_EARLY = {
    "breakout": {"baselines": ((505_000, 2.1), (1_010_000, 2.9)),
                 "sb3-zoo": ((500_000, 1.8), (1_000_000, 2.1)),
                 "nnabla-rl": ((500_000, 8.954), (1_000_000, 28.754))},
    "seaquest": {"baselines": ((505_000, 467.8), (1_010_000, 594.6)),
                 "sb3-zoo": ((500_000, 439.2), (1_000_000, 597.0)),
                 "nnabla-rl": ((500_000, 463.111), (1_000_000, 648.986))},
    "mspacman": {"sb3-zoo": ((500_000, 574.6), (1_000_000, 671.4))},
    "frostbite": {},
}
MARKERS = {"baselines": "s", "sb3-zoo": "^", "nnabla-rl": "D"}


def points(game: str, up_to_steps: float) -> dict[str, tuple[tuple[int, float], ...]]:
    """{source: ((agent steps, return), ...)} of `game`, an ALE run's env name (e.g. "ale-seaquest"), at steps within
    the budget shown; {} for a game without published points, and for MinAtar's games (named "seaquest" and so on:
    other games, whose returns are not comparable)."""
    if not game.startswith("ale-"):
        return {}
    out = {}
    for source, pts in A2C_EARLY.get(game.removeprefix("ale-"), {}).items():
        kept = tuple(p for p in pts if p[0] <= up_to_steps * 1.02)  # baselines' nearest point lies just past 1M
        if kept:
            out[source] = kept
    return out
