"""MinAtar across its five games: a2c-cd against a2c (probability of improvement, IQM of normalised scores, performance
profiles) and the a2c arm against the MinAtar paper's actor-critic, from the kept run directories.

    python -m experiments.atari.aggregate --out experiments/atari/results/minatar-aggregate
    python -m experiments.atari.aggregate --tier ale --out experiments/atari/results/ale-1m-aggregate
    python -m experiments.atari.aggregate --tier ale --data ale-10m --out experiments/atari/results/ale-10m-aggregate

`--tier ale`: the same statistics over the ALE tier's games (`data/ale-1m/GAME`: the paper's four games, a2c vs a2c-cd,
3 seeds, 1M agent steps; the games present), normalised with uniform random play's published scores (`ALE_RANDOM`),
without the MinAtar paper's comparison (`experiments.atari.published` holds ALE's published A2C points). Writes
OUT/aggregate.md, OUT/aggregate.json and OUT/profiles.png. `--data ale-10m`: the tier at the paper's 10M agent steps
(`data/ale-10m/GAME`, each game's two pieces joined by `python -m experiments.atari.ale40m merge`).

Runs: each game's kept run directory at its checked learning rate (`CHECKED`: RMSprop 2e-2, Space Invaders 1e-2), and
again with every game at 2e-2 (`SHARED`, Space Invaders' 2e-2 run instead). Scores per run (seed), from
`experiments.atari.report.seed_scores`: "eval", the mean return of the run's final 100 sampled-action episodes, and
"AUC", its training return averaged over env steps (sample efficiency, the paper's claim).

Normalisation, per game and the same for both arms: (score - random) / (pooled IQM - random), where "random" is the
mean return of uniform random play in the runs' own environment (their sticky actions and time-out; `RANDOM_EPISODES`
episodes, computed here on the CPU) and "pooled IQM" the IQM of that score over all runs of both arms on the game.
Random play scores 0 and the game's typical run 1, so games whose returns are 20 or 100 weigh alike, and neither arm
is the reference. The probability of improvement does not depend on it (per game it compares the two arms' runs by
rank; rliable's `probability_of_improvement`, averaged over games).

Statistics: rliable (Agarwal et al. 2021), 95% stratified-bootstrap intervals (runs resampled within games).
Writes OUT/aggregate.md, OUT/aggregate.json and OUT/profiles.png, and the five games' table and curves at the checked
rates (OUT/results.md, OUT/curves.png: experiments.atari.report's), and prints the markdown.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import warnings

import numpy as np

from cdjax import io, stats
from experiments.atari import report

DATA = pathlib.Path(__file__).resolve().parent / "data"
GAMES = ("asterix", "breakout", "freeway", "seaquest", "space_invaders")
# Each game at its checked rate: 2e-2 (RMSprop) for four games; Space Invaders at 1e-2, where the a2c arm's rate check
# (data/lr-grid-c) gave the best AUC and evaluation and the 10-seed 2e-2 run split its seeds (final [15, 102]).
CHECKED = {g: DATA / "lr2e-2" / g for g in GAMES} | {"space_invaders": DATA / "lr1e-2" / "space_invaders"}
SHARED = {g: DATA / "lr2e-2" / g for g in GAMES}  # every game at 2e-2
ARMS = ("a2c", "a2c-cd")
SCORES = ("eval", "auc")
RANDOM_EPISODES = 1000
TAUS = np.linspace(0.0, 2.0, 81)  # normalised-score thresholds of the performance profiles

# The MinAtar paper's online actor-critic with eligibility traces, AC(lambda = 0.8) and AC(0), at each game's best
# step size: "average return over final 100 episodes" of 5M frames (one frame is one agent step in MinAtar), 30 runs.
# Read by eye from the sensitivity figure of Young & Tian (2019) as kenjyoung/MinAtar's README shows it
# (img/sensitivity_curves.gif at commit 4241f24; the learning-curve figure img/learning_curves.gif agrees at 5M
# frames); about +-0.5 on Breakout, Seaquest and Asterix, +-1 on Freeway, +-3 on Space Invaders. The README says its
# Seaquest numbers are of MinAtar <= 1.0.10, whose oxygen bar flashed full one step before running out.
AC_LAMBDA = {"asterix": 19.7, "breakout": 17.3, "freeway": 47.0, "seaquest": 15.7, "space_invaders": 182.0}
AC_ZERO = {"asterix": 19.9, "breakout": 15.4, "freeway": 46.5, "seaquest": 7.3, "space_invaders": 146.0}
PAPER_FRAMES = 5_000_000

ALE_GAMES = ("breakout", "seaquest", "mspacman", "frostbite")
ALE_DIRS = {g: DATA / "ale-1m" / g for g in ALE_GAMES}
# Uniform random play on the ALE as the DQN paper lists it (Mnih et al. 2015, Nature, Extended Data Table 2: no-op
# starts, no sticky actions), the usual reference of normalised Atari scores. The tier's runs use sticky actions
# (0.25), which change little for a policy that is random anyway; random play was not measured in their environment.
ALE_RANDOM = {"breakout": 1.7, "seaquest": 68.4, "mspacman": 307.3, "frostbite": 65.2}


def random_play(run_dir: pathlib.Path, episodes: int = RANDOM_EPISODES, seed: int = 0) -> float:
    """Mean return of uniform random actions over `episodes` fresh episodes of the run's MinAtar game, with its sticky
    actions and time-out (cdjax.agents.atari.MinAtarEnv), each episode to its first end."""
    import jax
    import jax.numpy as jnp

    from cdjax.agents.atari import MinAtarEnv

    config = json.loads((run_dir / "run.json").read_text())["base_config"]
    env = MinAtarEnv(config["env"], episodes, config["episode_length"], config["sticky_prob"])

    @jax.jit
    def play(key):
        key_reset, key_act = jax.random.split(key)

        def step(carry, key):
            state, ret, done = carry
            action = jax.random.randint(key, (episodes,), 0, env.num_actions)
            state, out = env.step(state, action)
            ret = ret + jnp.where(done, 0.0, out.reward)
            return (state, ret, done | out.terminated | out.truncated | ~out.valid), None

        zeros = jnp.zeros((episodes,))
        carry = (env.reset(key_reset), zeros, zeros.astype(bool))
        (_, ret, done), _ = jax.lax.scan(step, carry, jax.random.split(key_act, config["episode_length"]))
        return ret, done

    ret, done = play(jax.random.key(seed))
    assert bool(done.all()), "every random episode ends by the time-out"
    return float(np.mean(ret))


def load_scores(dirs: dict[str, pathlib.Path]) -> dict:
    """{game: {"lr": the a2c arm's rate, "data": report.load(...), arm: {score: [S]}}}."""
    out = {}
    for game, run_dir in dirs.items():
        data = report.load(run_dir)
        run = json.loads((run_dir / "run.json").read_text())
        lr = next(a["hparams"][0]["lr"] for a in run["arms"] if a["name"] == "a2c")
        out[game] = {"lr": lr, "data": data, "dir": run_dir, **{arm: report.seed_scores(data, arm) for arm in ARMS}}
    return out


def normalised(games: dict, randoms: dict[str, float], score: str) -> dict[str, np.ndarray]:
    """{arm: [runs, games]} of (score - random) / (pooled IQM - random), games in the order of `games`."""
    columns = {arm: [] for arm in ARMS}
    for game in games:
        g = games[game]
        pooled = np.concatenate([g[arm][score] for arm in ARMS])
        scale = stats.iqm_columns(pooled[np.isfinite(pooled)][:, None, None])[0] - randoms[game]
        for arm in ARMS:
            columns[arm].append((g[arm][score] - randoms[game]) / scale)
    return {arm: np.stack(cols, axis=1) for arm, cols in columns.items()}


def _estimates(score_dict: dict, func, reps: int) -> tuple[dict, dict]:
    from rliable import library as rly

    with warnings.catch_warnings():  # arch's notice that RandomState is deprecated
        warnings.simplefilter("ignore", FutureWarning)
        return rly.get_interval_estimates(score_dict, func, reps=reps, random_state=np.random.RandomState(0))


def aggregate(games: dict, randoms: dict[str, float], reps: int) -> dict:
    """Across games, per score: each arm's IQM of normalised scores, P(a2c-cd > a2c) overall and per game, and the
    performance profiles, each with its 95% interval."""
    from rliable import library as rly
    from rliable import metrics

    saved = np.random.get_state()
    np.random.seed(0)  # the performance profiles' bootstrap draws from numpy's global generator
    out = {}
    for score in SCORES:
        norm = normalised(games, randoms, score)
        point, ci = _estimates(norm, lambda s: np.array([metrics.aggregate_iqm(s)]), reps)
        poi_point, poi_ci = _estimates({"poi": [norm["a2c-cd"], norm["a2c"]]}, metrics.probability_of_improvement,
                                       reps)
        per_game = {game: float(metrics.probability_of_improvement(norm["a2c-cd"][:, [i]], norm["a2c"][:, [i]]))
                    for i, game in enumerate(games)}
        profiles, profile_ci = rly.create_performance_profile(norm, TAUS, reps=reps)
        out[score] = {
            "iqm": {arm: (float(point[arm][0]), float(ci[arm][0, 0]), float(ci[arm][1, 0])) for arm in ARMS},
            "poi": (float(np.asarray(poi_point["poi"]).ravel()[0]), float(np.asarray(poi_ci["poi"]).ravel()[0]),
                    float(np.asarray(poi_ci["poi"]).ravel()[1])),
            "poi_per_game": per_game, "normalised": {arm: norm[arm].tolist() for arm in ARMS},
            "profiles": {arm: (profiles[arm].tolist(), profile_ci[arm].tolist()) for arm in ARMS}}
    np.random.set_state(saved)
    return out


def training_return_at(data: dict, label: str, env_steps: float, window: float = 0.1) -> np.ndarray:
    """[S]: each seed's mean training return over the logged updates in (env_steps * (1 - window), env_steps]."""
    a = data["arms"][label]
    cols = (a["steps"] > env_steps * (1 - window)) & (a["steps"] <= env_steps)
    return stats.nan_reduce(np.nanmean, a["returns"][:, cols], axis=1)


def published(games: dict) -> list[dict]:
    """The a2c arm against the MinAtar paper's AC(0.8) and AC(0), game by game."""
    rows = []
    for game in GAMES:
        g = games[game]
        data = g["data"]
        at5 = training_return_at(data, "a2c", PAPER_FRAMES)
        lengths = np.concatenate([e["lengths"] for e in io.read_jsonl(g["dir"] / "eval.jsonl") if e["arm"] == "a2c"])
        rows.append({"game": game, "lr": g["lr"], "ac_lambda": AC_LAMBDA[game], "ac_zero": AC_ZERO[game],
                     "a2c_5m_mean": float(np.nanmean(at5)), "a2c_5m_iqm": stats.iqm_interval(at5, 2000),
                     "a2c_final_mean": float(np.nanmean(g["a2c"]["final"])),
                     "a2c_eval_mean": float(np.nanmean(g["a2c"]["eval"])),
                     "eval_cut_fraction": float(np.mean(lengths >= data_episode_length(g["dir"])))})
    return rows


def data_episode_length(run_dir: pathlib.Path) -> int:
    return int(json.loads((run_dir / "run.json").read_text())["base_config"]["episode_length"])


def _ci(x: tuple) -> str:
    return f"{x[0]:.2f} [{x[1]:.2f}, {x[2]:.2f}]"


def markdown(sets: dict, per_game: dict, randoms: dict, pub: list[dict]) -> str:
    lines = ["## Across the five games: a2c-cd against a2c", "",
             "| runs | score | IQM a2c | IQM a2c-cd | P(a2c-cd > a2c) |", "|---|---|---|---|---|"]
    for name, agg in sets.items():
        for score in SCORES:
            a = agg[score]
            lines.append(f"| {name} | {score} | {_ci(a['iqm']['a2c'])} | {_ci(a['iqm']['a2c-cd'])} | {_ci(a['poi'])} |")
    lines += ["", "IQM over runs x games of normalised scores ((score - random) / (pooled IQM - random), per game: random "
              "play 0, the game's IQM over both arms' runs 1), and the probability that a run of a2c-cd scores above a "
              "run of a2c on the same game, averaged over games; [95% stratified-bootstrap interval]. eval: return of "
              "the final 100 sampled-action episodes; AUC: training return averaged over env steps.", "",
              "| game | RMSprop lr | random play | eval a2c | eval a2c-cd | P(cd > a2c) eval | P(cd > a2c) AUC |",
              "|---|---:|---:|---|---|---:|---:|"]
    checked = sets["checked rates"]
    for game in GAMES:
        g = per_game[game]
        cells = [_ci(stats.iqm_interval(g[arm]["eval"], 2000)[:3]) for arm in ARMS]
        lines.append(f"| {game} | {g['lr']:g} | {randoms[game]:.2f} | {cells[0]} | {cells[1]} | "
                     f"{checked['eval']['poi_per_game'][game]:.2f} | {checked['auc']['poi_per_game'][game]:.2f} |")
    lines += ["", f"Random play: mean return of {RANDOM_EPISODES} episodes of uniform random actions in the runs' own "
              "environment. Per game: IQM [95% interval] over 10 seeds; P: the share of (a2c-cd run, a2c run) pairs "
              "where the a2c-cd run scores higher (ties count half).", "",
              "## The a2c arm against the MinAtar paper's actor-critic", "",
              "| game | AC(0.8), paper | AC(0), paper | a2c at 5M steps: mean (IQM) | a2c final at 10M (mean) | "
              "a2c eval at 10M (mean) | eval episodes cut at 1000 steps |", "|---|---:|---:|---|---:|---:|---:|"]
    for r in pub:
        iqm = r["a2c_5m_iqm"]
        lines.append(f"| {r['game']} (lr {r['lr']:g}) | {r['ac_lambda']:g} | {r['ac_zero']:g} | {r['a2c_5m_mean']:.1f} "
                     f"({iqm[0]:.1f} [{iqm[1]:.1f}, {iqm[2]:.1f}]) | {r['a2c_final_mean']:.1f} | "
                     f"{r['a2c_eval_mean']:.1f} | {100 * r['eval_cut_fraction']:.0f}% |")
    lines += ["", "Paper: average return over the final 100 training episodes of 5M frames, 30 runs, at the best step "
              "size, read from its figure (approximate). a2c at 5M: each seed's training return over the updates in "
              "(4.5M, 5M] env steps of the 10M-step runs, mean over 10 seeds (IQM [95% interval]). Final: the training "
              "returns logged over the last 10% of the env steps; eval: the final 100 sampled-action episodes."]
    return "\n".join(lines) + "\n"


def figure(sets: dict, path: pathlib.Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = {"a2c": report.COLORS["a2c"], "a2c-cd": report.COLORS["a2c-cd"]}
    fig, axes = plt.subplots(len(sets), len(SCORES), figsize=(5.0 * len(SCORES), 3.6 * len(sets)), squeeze=False)
    for j, (name, agg) in enumerate(sets.items()):
        for k, score in enumerate(SCORES):
            ax = axes[j, k]
            for arm in ARMS:
                curve, ci = agg[score]["profiles"][arm]
                ax.plot(TAUS, curve, color=colors[arm], label=arm)
                ax.fill_between(TAUS, ci[0], ci[1], color=colors[arm], alpha=0.2, linewidth=0)
            ax.set_title(f"{score}, {name}")
            ax.set_xlabel("normalised score tau (random 0, game IQM 1)")
            ax.set_ylabel("fraction of runs above tau")
            ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def ale_markdown(agg: dict, games: dict) -> str:
    """The ALE tier's tables: across its games, then game by game."""
    names = list(games)
    lines = [f"## The ALE tier across {len(names)} games ({', '.join(names)}): a2c-cd against a2c", "",
             "| score | IQM a2c | IQM a2c-cd | P(a2c-cd > a2c) |", "|---|---|---|---|"]
    for score in SCORES:
        a = agg[score]
        lines.append(f"| {score} | {_ci(a['iqm']['a2c'])} | {_ci(a['iqm']['a2c-cd'])} | {_ci(a['poi'])} |")
    seeds = sorted({len(games[g][arm]["eval"]) for g in names for arm in ARMS})
    lines += ["", "IQM over runs x games of normalised scores ((score - random) / (pooled IQM - random), per game: "
              "random play 0 (`ALE_RANDOM`: the DQN paper's published scores), the game's IQM over both arms' runs 1), "
              "and the probability that a run of a2c-cd scores above a run of a2c on the same game, averaged over "
              "games; [95% stratified-bootstrap interval]. eval: return of the final 100 sampled-action episodes; AUC: "
              f"training return averaged over env steps. {'/'.join(map(str, seeds))} seeds per arm and game.", "",
              "| game | random play (published) | eval a2c | eval a2c-cd | P(cd > a2c) eval | P(cd > a2c) AUC |",
              "|---|---:|---|---|---:|---:|"]
    for game in names:
        g = games[game]
        cells = [_ci(stats.iqm_interval(g[arm]["eval"], 2000)[:3]) for arm in ARMS]
        lines.append(f"| {game} | {ALE_RANDOM[game]:g} | {cells[0]} | {cells[1]} | "
                     f"{agg['eval']['poi_per_game'][game]:.2f} | {agg['auc']['poi_per_game'][game]:.2f} |")
    return "\n".join(lines) + "\n"


def ale_main(out: pathlib.Path, reps: int, data: str = "ale-1m") -> str:
    """The ALE tier's aggregate over the games whose run directory is kept under data/`data`."""
    dirs = {g: DATA / data / g for g in ALE_GAMES if (DATA / data / g / "run.json").exists()}
    if len(dirs) < 2:
        raise SystemExit(f"the ALE tier's aggregate needs at least two games' runs under {DATA / data}")
    games = load_scores(dirs)
    agg = aggregate(games, {g: ALE_RANDOM[g] for g in dirs}, reps)
    text = ale_markdown(agg, games)
    out.mkdir(parents=True, exist_ok=True)
    (out / "aggregate.md").write_text(text)
    (out / "aggregate.json").write_text(json.dumps(
        {"random": {g: ALE_RANDOM[g] for g in dirs}, "runs": {g: str(d.relative_to(DATA.parents[2]))
                                                             for g, d in dirs.items()}, "aggregate": agg}, indent=1))
    figure({"ALE tier": agg}, out / "profiles.png")
    print(text)
    print(f"Wrote {out / 'aggregate.md'}, {out / 'aggregate.json'} and {out / 'profiles.png'}")
    return text


def main(argv=None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=pathlib.Path, required=True)
    parser.add_argument("--tier", choices=("minatar", "ale"), default="minatar")
    parser.add_argument("--data", default="ale-1m", help="with --tier ale: the folder of data/ (ale-1m, ale-10m)")
    parser.add_argument("--bootstrap-reps", type=int, default=2000)
    args = parser.parse_args(argv)
    from cdjax import runtime

    runtime.apply_xla_defaults()  # its XLA:CPU flag before JAX starts

    if args.tier == "ale":
        return ale_main(args.out, args.bootstrap_reps, args.data)

    checked, shared = load_scores(CHECKED), load_scores(SHARED)
    randoms = {game: random_play(CHECKED[game]) for game in GAMES}  # the same env (game, sticky, time-out) in both
    sets = {"checked rates": aggregate(checked, randoms, args.bootstrap_reps),
            "all at 2e-2": aggregate(shared, randoms, args.bootstrap_reps)}
    pub = published(checked)
    text = markdown(sets, checked, randoms, pub)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "aggregate.md").write_text(text)
    (args.out / "aggregate.json").write_text(json.dumps(
        {"random": randoms, "runs": {name: {g: str(d.relative_to(DATA.parents[2])) for g, d in dirs.items()}
                                     for name, dirs in (("checked rates", CHECKED), ("all at 2e-2", SHARED))},
         "aggregate": sets, "published": pub}, indent=1))
    figure(sets, args.out / "profiles.png")
    datas = [checked[game]["data"] for game in GAMES]
    table = report.markdown([row for data in datas for row in report.table_rows(data, args.bootstrap_reps)])
    (args.out / "results.md").write_text(table)
    report.figure(datas, args.out / "curves.png", args.bootstrap_reps)
    print(table + "\n" + text)
    print(f"Wrote {', '.join(str(args.out / n) for n in ('aggregate.md', 'aggregate.json', 'profiles.png', 'results.md'))}"
          f" and {args.out / 'curves.png'}")
    return text


if __name__ == "__main__":
    main()
