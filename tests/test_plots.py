"""plot_run on a hand-written run directory: files, exact plotted numbers, summary ranking, NaN tolerance."""

import csv
import json
import math

import numpy as np
import pytest
import scipy.stats
from rliable import metrics as rly_metrics

from cdjax import io, plots, stats

UPDATES = 20
STEPS_PER_UPDATE = 512
RNG = np.random.default_rng(0)
# arm name -> (arm type, seeds, level of the return curve)
ARMS = {"good": ("cd", 5, 100.0), "bad": ("model-free", 5, 10.0), "few": ("mbmf", 3, 50.0)}


def _return(level, seed, u):
    """A rising curve with a seed offset: NaN at update 0 (no episode finished yet)."""
    if u == 0:
        return None
    return level * (u / UPDATES) + 3.0 * seed + RNG.normal()


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    run = tmp_path_factory.mktemp("run")
    info = {"version": 1, "base_config": {"env": "point"}, "seeds": 5, "seed": 0, "total_env_steps": 0,
            "chunk_updates": 10, "command": "synthetic",
            "arms": [{"name": name, "arm": arm, "config": {"arm": arm}, "hparams": [{}], "hp_labels": ["alpha=1.0"]}
                     for name, (arm, _, _) in ARMS.items()]}
    (run / "run.json").write_text(json.dumps(info))
    table = {}
    with (run / "metrics.jsonl").open("w") as f:
        for name, (arm, seeds, level) in ARMS.items():
            for s in range(seeds):
                for u in range(UPDATES):
                    ret = _return(level, s, u)
                    if name == "good" and s == 4 and u == 7:
                        ret = None  # a late gap in one seed
                    row = {"arm": name, "hp": "alpha=1.0", "seed": s, "update": u,
                           "env_steps": (u + 1) * STEPS_PER_UPDATE, "wall_s": 0.1 * u,
                           "episode/return": ret, "episode/discounted_return": None if ret is None else ret / 10,
                           "loss/total": 1.0 / (u + 1)}
                    if arm != "model-free":
                        row["model/openloop_mse_k"] = 0.5 / (u + 1) + 0.01 * s
                        row["model/openloop_mse_50"] = None if u < 3 else 5.0 / (u + 1)
                    if arm == "cd":
                        row["loss/consistency"] = 0.2 + 0.01 * s
                    table[(name, s, u)] = ret
                    f.write(json.dumps(row) + "\n")
        f.write('{"arm": "good", "hp": "alpha=1.0", "seed": 0, "upd')  # a run killed mid-line
    with (run / "eval.jsonl").open("w") as f:
        for name, (_, seeds, level) in ARMS.items():
            for s in range(seeds):
                for update, bonus in ((10, 0.0), (19, 1.0)):  # the latest evaluation counts
                    f.write(json.dumps({"arm": name, "hp": "alpha=1.0", "seed": s, "update": update,
                                        "deterministic": True, "episodes": 4, "eval/return": level * bonus + s,
                                        "eval/discounted_return": None}) + "\n")
    paths = plots.plot_run(run, reps=500)
    return run, paths, table


def _csv(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def test_files_exist(run_dir):
    run, paths, _ = run_dir
    for key in ("return", "return_csv", "discounted_return", "discounted_return_csv", "model", "model_csv",
                "summary_md", "summary_csv"):
        assert paths[key].exists() and paths[key].stat().st_size > 0, key
    assert paths["return"].parent == run / "plots" and paths["summary_md"] == run / "summary.md"
    assert paths["return"].read_bytes()[:4] == b"\x89PNG"


def test_load_metrics_shapes_and_nans(run_dir):
    run, _, table = run_dir
    said = []
    curves = plots.load_metrics(run, say=said.append)
    assert len(said) == 1 and "left out 1 line(s) that do not parse" in said[0]  # the torn last line, said
    assert list(curves) == [(name, "alpha=1.0") for name in ARMS]  # run.json order
    good = curves[("good", "alpha=1.0")]
    assert good.metrics["episode/return"].shape == (5, UPDATES) and good.arm_type == "cd"
    assert np.isnan(good.metrics["episode/return"][:, 0]).all() and np.isnan(good.metrics["episode/return"][4, 7])
    assert good.metrics["episode/return"][2, 5] == pytest.approx(table[("good", 2, 5)])
    np.testing.assert_allclose(good.env_steps, (np.arange(UPDATES) + 1) * STEPS_PER_UPDATE)
    assert "loss/consistency" not in curves[("bad", "alpha=1.0")].metrics


def test_csv_iqm_equals_hand_computation(run_dir):
    _, paths, table = run_dir
    rows = {(r["arm"], int(r["update"])): r for r in _csv(paths["return_csv"])}
    # 5 seeds: the 25% trimmed mean drops the lowest and the highest value
    values = np.array([table[("bad", s, 12)] for s in range(5)])
    hand = np.sort(values)[1:4].mean()
    row = rows[("bad", 12)]
    assert float(row["iqm"]) == pytest.approx(hand, rel=1e-9)
    assert float(row["iqm"]) == pytest.approx(rly_metrics.aggregate_iqm(values[:, None]), rel=1e-9)
    assert float(row["ci_low"]) <= hand <= float(row["ci_high"]) and int(row["n_seeds"]) == 5
    assert float(row["env_steps"]) == 13 * STEPS_PER_UPDATE
    # the gap: only 4 seeds at update 7 of "good", IQM of those 4 (middle two)
    four = np.sort([table[("good", s, 7)] for s in range(4)])
    assert float(rows[("good", 7)]["iqm"]) == pytest.approx(four[1:3].mean()) and rows[("good", 7)]["n_seeds"] == "4"
    # fewer than 4 seeds: the IQM is the mean
    three = [table[("few", s, 12)] for s in range(3)]
    assert float(rows[("few", 12)]["iqm"]) == pytest.approx(np.mean(three))
    # before any finished episode: nothing plotted, no crash
    assert rows[("good", 0)]["iqm"] == "" and rows[("good", 0)]["n_seeds"] == "0"


def test_iqm_columns_matches_rliable():
    scores = RNG.normal(size=(7, 1, 6))
    expected = [rly_metrics.aggregate_iqm(scores[..., p]) for p in range(6)]
    np.testing.assert_allclose(stats.iqm_columns(scores), expected)


def test_probability_of_improvement_uses_the_finite_runs_and_gives_no_interval_for_one_run():
    full = stats.probability_of_improvement(np.array([1.0, 3.0]), np.array([0.0, 1.0, 2.0]), reps=50)
    # a run that never finished an episode (NaN) is left out, as every statistic here leaves it out
    assert stats.probability_of_improvement(np.array([1.0, np.nan, 3.0]), np.array([0.0, 1.0, 2.0]), reps=50) == full
    assert full[0] == pytest.approx(4.5 / 6) and full[1] < full[0] < full[2]
    # one run against one: a point estimate, no interval to resample; nothing finite: nothing at all
    point, low, high = stats.probability_of_improvement(np.array([1.0]), np.array([0.0]))
    assert point == 1.0 and np.isnan(low) and np.isnan(high)
    assert all(np.isnan(v) for v in stats.probability_of_improvement(np.array([np.nan]), np.array([0.0])))
    # several tasks: a run counts where it is finite on every task
    x, y = np.array([[1.0, 2.0], [3.0, np.nan], [2.0, 2.0]]), np.array([[0.0, 0.0], [5.0, 5.0]])
    assert stats.probability_of_improvement(x, y, reps=50) == stats.probability_of_improvement(x[[0, 2]], y, reps=50)


def test_stats_helpers_refuse_what_they_cannot_compute_in_one_sentence():
    curve = np.array([[1.0, 2.0], [3.0, 4.0]])
    with pytest.raises(ValueError, match="stat is 'iqm' or 'mean', got 'median'"):
        stats.interval_curve(curve, stat="median")
    with pytest.raises(ValueError, match=r"takes values \[seeds, points\], got an array of shape \(2,\)"):
        stats.interval_curve(curve[0])
    with pytest.raises(ValueError, match="fraction is a share of the points in \\(0, 1\\], got 2"):
        stats.final_values(curve, np.ones_like(curve, bool), fraction=2)
    # steps as a list: the same area as an array (the second point stands for 3 steps, the first for 1)
    assert stats.area_under_curve(curve, np.ones_like(curve, bool), [1, 4]).tolist() == [1.75, 3.75]


def test_model_csv_mean_across_seeds(run_dir):
    _, paths, _ = run_dir
    rows = _csv(paths["model_csv"])
    assert {r["metric"] for r in rows} == {"model/openloop_mse_k", "model/openloop_mse_50", "loss/consistency"}
    assert {r["arm"] for r in rows} == {"good", "few"}  # model-free logs no model metrics
    row = next(r for r in rows if r["metric"] == "model/openloop_mse_k" and r["arm"] == "few" and r["update"] == "4")
    assert float(row["mean"]) == pytest.approx(np.mean([0.5 / 5 + 0.01 * s for s in range(3)]))
    early = next(r for r in rows if r["metric"] == "model/openloop_mse_50" and r["update"] == "1")
    assert early["mean"] == ""


def test_summary_ranks_and_columns(run_dir):
    run, paths, table = run_dir
    rows = _csv(paths["summary_csv"])
    assert [r["arm"] for r in rows] == ["good", "few", "bad"]
    for col in ("arm", "hp", "arm_type", "seeds", "env_steps", "final_return_iqm", "final_return_ci_low",
                "final_return_ci_high", "auc_return_iqm", "final_discounted_return_iqm",
                "auc_discounted_return_iqm", "eval_det_return_iqm", "eval_det_return_ci_low"):
        assert col in rows[0], col
    good = rows[0]
    assert good["seeds"] == "5" and float(good["env_steps"]) == UPDATES * STEPS_PER_UPDATE
    # final: mean of the last 10% (2 of 20) updates per seed, then IQM over seeds
    finals = np.array([np.mean([table[("good", s, u)] for u in (18, 19)]) for s in range(5)])
    assert float(good["final_return_iqm"]) == pytest.approx(scipy.stats.trim_mean(finals, 0.25))
    # AUC: nan-mean over the whole curve per seed (update 0 and the gap are skipped)
    aucs = np.array([np.mean([table[("good", s, u)] for u in range(1, UPDATES) if table[("good", s, u)] is not None])
                     for s in range(5)])
    assert float(good["auc_return_iqm"]) == pytest.approx(scipy.stats.trim_mean(aucs, 0.25))
    assert float(good["final_return_ci_low"]) <= float(good["final_return_iqm"]) <= float(good["final_return_ci_high"])
    # eval: latest update per seed -> 100 + s for s in 0..4, IQM = middle three
    assert float(good["eval_det_return_iqm"]) == pytest.approx(102.0)
    assert good["eval_det_discounted_return_iqm"] == ""  # all null: n/a, not a crash
    md = paths["summary_md"].read_text()
    assert "| rank | arm | hp | seeds |" in md and "final return" in md and "eval return (deterministic)" in md
    assert md.index("| 1 | good") < md.index("| 3 | bad")


def test_single_seed_and_empty_metrics(tmp_path):
    """One seed: no interval but a value; an arm whose returns are all null: n/a; no eval.jsonl."""
    with (tmp_path / "metrics.jsonl").open("w") as f:
        for u in range(5):
            f.write(json.dumps({"arm": "solo", "hp": "", "seed": 0, "update": u, "env_steps": u,
                                "episode/return": float(u), "episode/discounted_return": float("nan") if u < 2 else 1.0}
                               ).replace("NaN", "null") + "\n")
            f.write(json.dumps({"arm": "dead", "hp": "", "seed": 0, "update": u, "env_steps": u,
                                "episode/return": None, "episode/discounted_return": None}) + "\n")
    paths = plots.plot_run(tmp_path, reps=100)
    rows = _csv(paths["summary_csv"])
    assert [r["arm"] for r in rows] == ["solo", "dead"]
    assert float(rows[0]["final_return_iqm"]) == 4.0 and rows[0]["final_return_ci_low"] == ""
    assert rows[1]["final_return_iqm"] == "" and "model" not in paths
    assert not any(k.startswith("eval") for k in rows[0])
    assert "n/a" in paths["summary_md"].read_text()
    assert math.isclose(float(_csv(paths["return_csv"])[-1]["iqm"]), 4.0)


def test_the_seeds_column_counts_only_seeds_with_a_finite_final_return_and_says_which_were_left_out(tmp_path):
    """A seed whose returns are all null (or NaN) is in no figure, so it is not in the seeds column either: the row
    says "4 of 5" and a note names the seed; an arm whose seeds all have returns keeps its plain count."""
    with (tmp_path / "metrics.jsonl").open("w") as f:
        for arm in ("holed", "whole"):
            for s in range(5):
                for u in range(10):
                    ret = None if (arm, s) == ("holed", 2) else 10.0 * s + u
                    f.write(json.dumps({"arm": arm, "hp": "alpha=1.0", "seed": s, "update": u, "env_steps": 100 * (u + 1),
                                        "episode/return": ret, "episode/discounted_return": ret}) + "\n")
    paths = plots.plot_run(tmp_path, reps=100)
    rows = {r["arm"]: r for r in _csv(paths["summary_csv"])}
    holed, whole = rows["holed"], rows["whole"]
    assert (holed["seeds"], holed["logged_seeds"], holed["left_out_seed_ids"]) == ("4", "5", "2")
    assert (whole["seeds"], whole["logged_seeds"], whole["left_out_seed_ids"]) == ("5", "5", "")
    finals = np.array([10.0 * s + 9.0 for s in (0, 1, 3, 4)])  # the last 10% of 10 updates: update 9
    assert float(holed["final_return_iqm"]) == pytest.approx(scipy.stats.trim_mean(finals, 0.25))
    assert holed["final_return_seeds"] == holed["auc_discounted_return_seeds"] == "4"
    md = paths["summary_md"].read_text()
    assert "| alpha=1.0 | **4 of 5** |" in md and "| alpha=1.0 | 5 |" in md
    note = next(line for line in md.splitlines() if line.startswith("**Seeds left out**"))
    assert "holed alpha=1.0 seeds 2" in note and "whole" not in note


def test_an_evaluation_column_over_other_seeds_than_the_seeds_column_says_over_how_many(tmp_path):
    """The seeds column counts the seeds with a finite final return; an evaluation column whose own count differs
    (a seed not evaluated, an evaluation that is not finite, a left-out seed that was evaluated) says n = N in its
    cell and a note names the arm, the column and the count; columns over the seeds column's seeds say nothing."""
    with (tmp_path / "metrics.jsonl").open("w") as f:
        for arm in ("short", "holed", "whole"):
            for s in range(4):
                for u in range(5):
                    ret = None if (arm, s) == ("holed", 1) else 10.0 * s + u
                    f.write(json.dumps({"arm": arm, "hp": "", "seed": s, "update": u, "env_steps": 100 * (u + 1),
                                        "episode/return": ret, "episode/discounted_return": ret}) + "\n")
    with (tmp_path / "eval.jsonl").open("w") as f:
        for arm, seeds in (("short", range(3)), ("holed", range(4)), ("whole", range(4))):  # short: seed 3 not
            for s in seeds:
                ret = None if (arm, s) == ("short", 0) else float(s)  # short: seed 0's evaluation not finite
                f.write(json.dumps({"arm": arm, "hp": "", "seed": s, "update": 4, "deterministic": True,
                                    "episodes": 2, "eval/return": ret, "eval/discounted_return": float(s)}) + "\n")
    paths = plots.plot_run(tmp_path, reps=50)
    rows = {r["arm"]: r for r in _csv(paths["summary_csv"])}
    assert [(rows[a]["seeds"], rows[a]["eval_det_return_seeds"], rows[a]["eval_det_discounted_return_seeds"])
            for a in ("short", "holed", "whole")] == [("4", "2", "3"), ("3", "4", "4"), ("4", "4", "4")]
    md = paths["summary_md"].read_text()
    cells = {line.split(" | ")[1]: line.removesuffix(" |").split(" | ")[5:] for line in md.splitlines()
             if line.startswith("| ")}
    assert cells["short"][4].endswith("(**n = 2**)") and cells["short"][5].endswith("(**n = 3**)")
    assert cells["holed"][4].endswith("(**n = 4**)") and cells["holed"][5].endswith("(**n = 4**)")
    assert not any("n = " in cell for cell in cells["short"][:4] + cells["holed"][:4] + cells["whole"])
    note = next(line for line in md.splitlines() if line.startswith("**Seed counts**"))
    assert note.endswith(": holed eval return (deterministic): n = 4 (seeds column 3); holed eval disc. return "
                         "(deterministic): n = 4 (seeds column 3); short eval return (deterministic): n = 2 (seeds "
                         "column 4); short eval disc. return (deterministic): n = 3 (seeds column 4)."), note  # ranked


def test_fallback_bootstrap_matches_rliable():
    """The local bootstrap (used when rliable.library cannot import) reproduces rliable's numbers."""
    if stats.rly is None:
        pytest.skip(f"rliable.library does not import here ({stats.RLIABLE_ERROR}); pin pandas<3 to use it")
    scores = RNG.normal(size=(6, 1, 4))
    np.random.seed(1)
    point, interval = stats.rly.get_interval_estimates({"x": scores}, stats.iqm_columns, reps=300)
    np.random.seed(1)
    point2, interval2 = stats.stratified_bootstrap(scores, stats.iqm_columns, reps=300)
    np.testing.assert_allclose(point2, point["x"])
    np.testing.assert_allclose(interval2, interval["x"])


def test_auc_weights_each_point_by_the_env_steps_it_stands_for(tmp_path):
    """An Mb-Mf phase point (update 0 at 1000 env steps) weighs 1000 steps; later points 100 each."""
    with (tmp_path / "metrics.jsonl").open("w") as f:
        for s, (phase_ret, ret) in enumerate(((10.0, 20.0), (0.0, 40.0))):
            f.write(json.dumps({"arm": "mbmf", "hp": "", "seed": s, "update": 0, "env_steps": 1000,
                                "episode/return": phase_ret}) + "\n")
            for u in range(1, 4):
                f.write(json.dumps({"arm": "mbmf", "hp": "", "seed": s, "update": u, "env_steps": 1000 + 100 * u,
                                    "episode/return": None if u == 2 else ret}) + "\n")
    (c,) = plots.load_metrics(tmp_path).values()
    auc = plots.per_seed_auc(c, plots.RETURN)
    # the NaN point (update 2) is skipped with its 100 steps
    np.testing.assert_allclose(auc, [(10 * 1000 + 20 * 200) / 1200, (0 * 1000 + 40 * 200) / 1200])


def _small_run(path, base_seed, seeds, level, env="point", updates=6, steps=3072, log_every=1, evals=True,
               config=None, hparams=None):
    """A run directory by hand of one arm, return = level + seed index + base seed x 100 at every logged update."""
    path.mkdir(parents=True)
    config = {"env": env, "num_envs": 32, "yardstick": f"/{path.name}/yardstick/point.npz", **(config or {})}
    info = {"version": 1, "base_config": {"env": env}, "seeds": seeds, "seed": base_seed, "command": "synthetic",
            "arms": [{"name": "cd", "arm": "cd", "config": config, "hparams": [{"alpha": 1.0, **(hparams or {})}],
                      "hp_labels": ["alpha=1.0"], "total_env_steps": steps}]}
    (path / "run.json").write_text(json.dumps(info))
    with (path / "metrics.jsonl").open("w") as f:
        for s in range(seeds):
            for u in range(0, updates, log_every):
                f.write(json.dumps({"arm": "cd", "hp": "alpha=1.0", "seed": s, "update": u, "env_steps": 512 * (u + 1),
                                    "episode/return": level + s + 100 * base_seed}) + "\n")
    if evals:
        with (path / "eval.jsonl").open("w") as f:
            for s in range(seeds):
                f.write(json.dumps({"arm": "cd", "hp": "alpha=1.0", "seed": s, "update": updates - 1,
                                    "deterministic": True, "episodes": 2, "eval/return": 10.0 * base_seed + s}) + "\n")
    return path


def test_plot_runs_pools_the_seeds_of_runs_of_other_base_seeds(tmp_path):
    """`cdjax plot A B --out C`: one arm holds every run's seeds (ids kept apart), on the updates either logged,
    its evaluations too; the summary's statistics are those of all the seeds together."""
    a = _small_run(tmp_path / "a", 0, 3, 10.0)
    b = _small_run(tmp_path / "b", 1, 2, 10.0, log_every=2)  # logs every other update
    paths = plots.plot_runs([a, b], tmp_path / "pooled", reps=200)
    (row,) = _csv(paths["summary_csv"])
    assert row["seeds"] == "5" and row["eval_det_seeds"] == "5"
    finals = np.array([10.0, 11.0, 12.0, 110.0, 111.0])  # every seed's return is flat: its final value
    assert float(row["final_return_iqm"]) == pytest.approx(scipy.stats.trim_mean(finals, 0.25))
    evals = np.array([0.0, 1.0, 2.0, 10.0, 11.0])
    assert float(row["eval_det_return_iqm"]) == pytest.approx(scipy.stats.trim_mean(evals, 0.25))
    assert "pooled (base seeds 0, 1)" in paths["summary_md"].read_text()
    assert not (a / "summary.md").exists()  # the runs are read, not written
    c = plots.pool_curves(plots.load_metrics(a)[("cd", "alpha=1.0")], plots.load_metrics(b)[("cd", "alpha=1.0")])[0]
    assert list(c.seeds) == [0, 1, 2, 3, 4] and list(c.updates) == list(range(6))
    assert c.present[3:].tolist() == [[True, False] * 3] * 2 and np.isnan(c.metrics["episode/return"][4, 1])


@pytest.mark.parametrize("second, message", [
    (dict(base_seed=0), "both ran base seed 0, so their seeds are the same keys"),
    (dict(base_seed=1, env="reacher"), "is a run of environment 'reacher' and"),
    (dict(base_seed=1, steps=6144), "arm cd ran 6,144 env steps per run in"),
    (dict(base_seed=1, config={"num_envs": 16}), r"arm cd \(alpha=1.0\) ran with num_envs=16 in .*b and 32 in .*a; "
                                                 "pool runs of one configuration"),
    (dict(base_seed=1, hparams={"gamma": 0.9}), r"ran with gamma=0.9 in .*b and None in .*a; pool runs of one "
                                                "hyper-parameters"),
])
def test_plot_runs_refuses_runs_that_do_not_pool(tmp_path, second, message):
    a = _small_run(tmp_path / "a", 0, 2, 1.0)
    b = _small_run(tmp_path / "b", seeds=2, level=1.0, **second)
    with pytest.raises(io.RunDirError, match=message):
        plots.plot_runs([a, b], tmp_path / "out", reps=50)
    assert not (tmp_path / "out").exists()
    with pytest.raises(io.RunDirError, match="given no run directory"):
        plots.plot_runs([], tmp_path / "out")


def test_cdjax_plot_of_several_runs_needs_out(tmp_path, capsys):
    from cdjax.cli import main

    a, b = _small_run(tmp_path / "a", 0, 2, 1.0), _small_run(tmp_path / "b", 1, 2, 1.0)
    for argv, said in ((["plot", str(a), str(b)], "name where it goes with --out DIR"),
                       (["plot", str(a), str(a), "--out", str(tmp_path / "o")], "a RUN_DIR is named twice"),
                       (["plot", str(a), str(b), "--out", str(b)], "is one of the runs")):
        with pytest.raises(SystemExit) as stop:
            main(argv)
        assert stop.value.code != 0 and said in capsys.readouterr().err
    main(["plot", str(a), str(b), "--out", str(tmp_path / "o"), "--bootstrap-reps", "50"])
    assert _csv(tmp_path / "o" / "summary.csv")[0]["seeds"] == "4" and (tmp_path / "o" / "plots" / "return.png").exists()
