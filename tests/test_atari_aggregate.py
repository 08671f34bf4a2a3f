"""The MinAtar aggregate (experiments.atari.aggregate) on hand-made scores: the normalisation puts random play at 0
and each game's pooled IQM at 1 whatever the game's scale, and the probability of improvement is 1 when every run of
one arm beats every run of the other on every game, 0.5 for the same runs, and a game's share of winning pairs."""

from __future__ import annotations

import numpy as np
import pytest

from experiments.atari import aggregate

GAMES = aggregate.GAMES


def _games(cd: dict[str, list[float]], a2c: dict[str, list[float]]) -> dict:
    return {g: {"a2c": {"eval": np.asarray(a2c[g], float), "auc": np.asarray(a2c[g], float)},
                "a2c-cd": {"eval": np.asarray(cd[g], float), "auc": np.asarray(cd[g], float)}} for g in GAMES}


def test_normalisation_maps_random_play_to_0_and_the_pooled_iqm_to_1():
    scale = {g: 10.0 ** i for i, g in enumerate(GAMES)}  # returns of 1 to 10,000
    runs = [0.0, 1.0, 2.0, 3.0]  # with the other arm's, pooled 0..7: IQM (trimming 2 of 8 each side) 3.5
    games = _games({g: [scale[g] * (x + 4) for x in runs] for g in GAMES}, {g: [scale[g] * x for x in runs] for g in GAMES})
    randoms = {g: scale[g] * 0.5 for g in GAMES}
    norm = aggregate.normalised(games, randoms, "eval")
    assert norm["a2c"].shape == (4, len(GAMES))
    for i in range(len(GAMES)):  # every game alike once normalised: (x - 0.5) / (3.5 - 0.5)
        np.testing.assert_allclose(norm["a2c"][:, i], (np.asarray(runs) - 0.5) / 3.0)
        np.testing.assert_allclose(norm["a2c-cd"][:, i], (np.asarray(runs) + 3.5) / 3.0)


def test_probability_of_improvement_by_hand():
    low, high = [1.0, 2.0, 3.0], [4.0, 5.0, 6.0]
    randoms = dict.fromkeys(GAMES, 0.0)
    ahead = aggregate.aggregate(_games(dict.fromkeys(GAMES, high), dict.fromkeys(GAMES, low)), randoms, reps=20)
    assert ahead["eval"]["poi"][0] == 1.0 and ahead["eval"]["iqm"]["a2c-cd"][0] > ahead["eval"]["iqm"]["a2c"][0]
    same = aggregate.aggregate(_games(dict.fromkeys(GAMES, low), dict.fromkeys(GAMES, low)), randoms, reps=20)
    assert same["auc"]["poi"][0] == 0.5
    # one game where a2c-cd wins 2 of the 9 pairs (3 > 1, 3 > 2), the others as `same`: the mean over games
    mixed = dict.fromkeys(GAMES, low) | {"breakout": [0.0, 0.5, 3.0]}
    result = aggregate.aggregate(_games(mixed, dict.fromkeys(GAMES, low)), randoms, reps=20)
    assert result["eval"]["poi_per_game"]["breakout"] == pytest.approx((2 + 0.5) / 9)  # 3 = 3 ties: half a pair
    assert result["eval"]["poi"][0] == pytest.approx(((2.5 / 9) + 0.5 * (len(GAMES) - 1)) / len(GAMES))
    curve, _ = result["eval"]["profiles"]["a2c"]
    assert curve[0] == 1.0 and curve[-1] == 0.0  # every run above tau 0, none above tau 2


def test_the_table_says_not_evaluated_instead_of_an_empty_episode_count():
    from experiments.atari import report

    row = dict(game="ale-breakout", arm="a2c", seeds=3, budget=1e6, final=(2.0, 1.9, 2.1, 3), auc=(1.8, 1.7, 1.9, 3),
               steps_per_s=2973.0)
    unevaluated = report.markdown([dict(row, eval=(float("nan"), float("nan"), float("nan"), 0), eval_episodes=[],
                                        eval_modes=[], eval_steps=[])]).splitlines()[2]
    assert "| n/a (not evaluated) | n/a |" in unevaluated and "( episodes" not in unevaluated
    evaluated = report.markdown([dict(row, eval=(2.07, 2.03, 2.15, 3), eval_episodes=[100], eval_modes=["sampled"],
                                      eval_steps=[1e6])]).splitlines()[2]
    assert "| 2.07 [2.03, 2.15] (100 episodes, sampled) | 1e+06 |" in evaluated


def test_published_a2c_points_are_those_of_the_game_within_the_budget_shown():
    from experiments.atari import published

    # baselines' 1.01M point counts as 1M
    assert published.points("ale-seaquest", 1e6)["baselines"] == ((505_000, 467.8), (1_010_000, 594.6))
    # a shorter budget keeps only the earlier points, and drops a source with none left
    assert published.points("ale-breakout", 6e5) == {s: pts[:1] for s, pts in published.A2C_EARLY["breakout"].items()}
    assert published.points("ale-mspacman", 1e5) == {}
    # MinAtar's games (env "seaquest", not "ale-seaquest") and games without published early points have none
    assert published.points("seaquest", 1e7) == {} and published.points("ale-frostbite", 1e7) == {}
    assert set(published.MARKERS) >= {s for game in published.A2C_EARLY.values() for s in game}


def test_the_ale_tier_aggregate_reads_the_kept_games_and_compares_their_runs_by_rank(tmp_path):
    """Over the ALE games kept in data/ale-1m: each game's P(a2c-cd > a2c) is the share of (cd run, a2c run) pairs
    where the cd run scores higher, from the runs' own scores; random play is the published reference."""
    dirs = {g: d for g, d in aggregate.ALE_DIRS.items() if (d / "run.json").exists()}
    if len(dirs) < 2:
        pytest.skip("fewer than two ALE games kept")
    text = aggregate.main(["--tier", "ale", "--out", str(tmp_path), "--bootstrap-reps", "20"])
    import json

    saved = json.loads((tmp_path / "aggregate.json").read_text())
    assert saved["random"] == {g: aggregate.ALE_RANDOM[g] for g in dirs}
    games = aggregate.load_scores(dirs)
    for game in dirs:
        cd, base = games[game]["a2c-cd"]["eval"], games[game]["a2c"]["eval"]
        pairs = [(c > b) + 0.5 * (c == b) for c in cd for b in base]
        assert saved["aggregate"]["eval"]["poi_per_game"][game] == pytest.approx(np.mean(pairs))
        assert f"| {game} | {aggregate.ALE_RANDOM[game]:g} |" in text
    assert (tmp_path / "profiles.png").exists()
