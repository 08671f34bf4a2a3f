"""Benchmarks: the tiny CPU suite runs end to end in this process; ratios, targets and tables follow
from the raw numbers; the matched configuration is what Brax PPO's semantics say."""

import dataclasses
import inspect
import json
import math
import os
import pathlib
import subprocess
import sys

import pytest

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))  # `benchmarks` is not an installed package
from benchmarks import profile_summary, report  # noqa: E402
from benchmarks.common import FULL, TINY  # noqa: E402
from benchmarks.run import main  # noqa: E402
from benchmarks.scaling import seed_scaling  # noqa: E402
from benchmarks.throughput import DESIGNATED_CD, PAPER_CD  # noqa: E402
from _shared import benchmark_refuses  # noqa: E402

COMPARE = ["brax-ppo", "ceiling", "collect", "model-free", "mbmf", DESIGNATED_CD, PAPER_CD]


def test_matched_config_follows_brax_ppo_semantics():
    # Brax: batch_size * num_minibatches / num_envs unrolls of unroll_length per env per training step.
    assert FULL.unrolls_per_env == 4 and FULL.rollout_len == 80
    assert FULL.env_steps_per_update == 327_680 == FULL.batch_size * FULL.unroll_length * FULL.num_minibatches
    config = FULL.config(arm="cd")
    assert (config.num_envs, config.rollout_len, config.num_epochs, config.num_minibatches) == (4096, 80, 8, 32)
    # minibatches of sequences of Brax's unroll length, as many as Brax's batch_size
    assert config.segment == FULL.unroll_length and config.minibatch_seqs == FULL.batch_size
    assert config.minibatch_seqs * config.segment == FULL.samples_per_minibatch == 10_240
    assert config.horizon == 20 and config.env_steps_per_update == FULL.env_steps_per_update
    kw = FULL.brax_kwargs()
    assert (kw["num_envs"], kw["unroll_length"], kw["batch_size"], kw["num_minibatches"], kw["num_updates_per_batch"]) \
        == (4096, 20, 512, 32, 8)
    # the network widths are Brax's own PPO defaults
    from brax.training.agents.ppo import networks as ppo_networks

    params = inspect.signature(ppo_networks.make_ppo_networks).parameters
    assert tuple(params["policy_hidden_layer_sizes"].default) == FULL.policy_hidden == config.policy_hidden
    assert tuple(params["value_hidden_layer_sizes"].default) == FULL.value_hidden == config.value_hidden
    # num_envs scaling keeps rollout length and SGD schedule
    for n in (512, 1024, 2048, 8192):
        s = FULL.with_num_envs(n)
        assert s.rollout_len == 80 and s.config().num_minibatches == 32 and s.env_steps_per_update == n * 80
    assert FULL.with_num_envs(256).config().minibatch_seqs == 32
    hp, kw = FULL.hparams(), FULL.brax_kwargs()  # the same learning hyper-parameters on both sides
    assert (hp.gamma, hp.reward_scale, hp.ent_coef, hp.lr_policy, hp.lr_value, hp.clip_eps, hp.max_grad_norm) == (
        kw["discounting"], kw["reward_scaling"], kw["entropy_cost"], kw["learning_rate"], kw["learning_rate"],
        kw["clipping_epsilon"], kw["max_grad_norm"])


def test_learning_benchmark_tiny_evaluates_both_learners_at_the_same_env_steps(tmp_path):
    """`python -m benchmarks.learning --tiny`: both learners, every seed, evaluated at the same env-step counts;
    the report's table and verdict come from those rows. One update between the evaluations: the point task is
    benchmarks.run's --tiny Spec, so cdjax's program of 2 vmapped seeds for one update and Brax's training epoch of
    one step are the ones the `tiny` fixture's seeds suite and Brax case (--brax-steps-per-epoch 1) compile, and the
    compilation cache serves them to the fixture, which runs after this test."""
    from benchmarks import learning, learning_report
    from cdjax import io
    from cdjax.agents.obs.config import Config
    from conftest import CACHE

    out = tmp_path / "learning"
    learning.main(["--tiny", "--seeds", "2", "--evals", "1", "--updates-per-eval", "1", "--out", str(out),
                   "--cache-dir", str(CACHE)])
    rows = [json.loads(line) for line in (out / "rows.jsonl").read_text().splitlines()]
    task = dataclasses.replace(learning.TASKS["point"], evals=1, updates_per_eval=1)  # as run
    assert task.spec == TINY
    steps = {(r["framework"], r["seed"]): [] for r in rows}
    for r in rows:
        steps[(r["framework"], r["seed"])].append(r["env_steps"])
        assert math.isfinite(r["eval_return"])
    expected = [0, task.updates_per_eval * task.spec.env_steps_per_update]
    assert sorted(steps) == [("brax", 0), ("brax", 1), ("cdjax", 0), ("cdjax", 1)]
    assert all(sorted(v) == expected for v in steps.values())
    text = learning_report.report([out], str(out / "report.md"), reps=50)
    assert "| point | brax-ppo | 2 |" in text and "| point | cdjax default | 2 |" in text
    assert f"at {expected[-1]:,} env steps" in text and (out / "report.png").exists()
    # meta.json holds the Config each cdjax variant ran with: what `default` meant when the rows were made
    meta = json.loads((out / "meta.json").read_text())
    config = meta["configs"]["point"]["default"]
    assert config == json.loads(json.dumps(io.dataclass_to_json(learning.cdjax_config(task, "default"))))
    assert config["num_updates"] == task.updates_per_eval == 1
    assert config["arm"] == "model-free" and config["policy_head_scale"] == Config().policy_head_scale
    assert config["num_envs"] == task.spec.num_envs and set(meta["code"]) >= {"commit", "jax"}


def test_learning_report_names_every_device_a_learners_seeds_ran_on():
    """A learner whose seeds come from runs on two devices: its row of the table names both, once each, in the
    order they first appear; a learner measured on one device names that one."""
    from benchmarks import learning_report

    def row(framework, seed, steps, ret, device):
        return dict(task="t", framework=framework, variant="default", seed=seed, env_steps=steps, eval_return=ret,
                    train_s=1.0, device=device)

    rows = [row("brax", s, st, float(s + st), dev) for s, dev in ((0, "H200"), (1, "H200"), (2, "H100"))
            for st in (0, 10)]
    rows += [row("cdjax", s, st, float(s), "H100") for s in range(3) for st in (0, 10)]
    by_learner = {e["learner"]: e for e in learning_report.table(rows, reps=50)}
    assert by_learner["brax-ppo"]["device"] == "H200 + H100"
    assert by_learner["cdjax default"]["device"] == "H100"


def test_learning_report_leaves_out_a_seed_cut_short_and_says_so():
    """A seed whose run a time limit stopped early is left out of the final return (while at least half the seeds
    reached the end), named with where it stopped, instead of every seed being read where it stopped; with fewer
    than half at the end, the last evaluation all reached is read over all of them. A learner whose final return
    is then read at other env steps than Brax PPO's is said not compared."""
    from benchmarks import learning_report

    def row(framework, seed, steps, ret):
        return dict(task="t", framework=framework, variant="default", seed=seed, env_steps=steps, eval_return=ret,
                    train_s=1.0, device="H100")

    steps = (0, 10, 20, 30)
    rows = [row("cdjax", s, st, 100.0 * s + st) for s in range(4) for st in steps]
    rows += [row("brax", s, st, 1.0 * st) for s in range(4) for st in steps if s != 3 or st <= 10]
    by = {e["learner"]: e for e in learning_report.table(rows, reps=50)}
    assert by["brax-ppo"]["seeds"] == 3 and by["brax-ppo"]["env_steps"] == 30
    assert by["brax-ppo"]["per_seed"] == [30.0, 30.0, 30.0] and by["brax-ppo"]["left_out"] == [(3, 10, False)]
    assert by["cdjax default"]["seeds"] == 4 and by["cdjax default"]["left_out"] == []
    text = learning_report.report_text(rows, [], reps=50)
    assert "brax-ppo seed 3 left out" in text and "stopped at 10 env steps" in text
    assert "cdjax default final IQM" in text and "at 30 env steps" in text
    # cdjax's finals 30, 130, 230, 330 against the kept Brax finals 30, 30, 30: 9 of 12 pairs above, 3 ties
    # counted half, P(X > Y) = 10.5 / 12
    assert "P(cdjax default > Brax PPO) = 0.88" in text
    from cdjax.stats import probability_of_improvement

    assert probability_of_improvement([1.0, 2.0], [1.0, 2.0], reps=50)[0] == 0.5

    # a seed whose last evaluation is NaN (it ran to the end) is left out for that reason, not as cut short
    nan_rows = [dict(r, eval_return=None) if r["framework"] == "cdjax" and r["seed"] == 2 and r["env_steps"] == 30
                else r for r in rows]
    (cd,) = [e for e in learning_report.table(nan_rows, reps=50) if e["learner"] == "cdjax default"]
    assert cd["seeds"] == 3 and cd["left_out"] == [(2, 30, True)]
    assert "seed 2 left out of the final return and the mean over evaluations: its evaluation at 30 env steps is " \
        "not a number" in learning_report.report_text(nan_rows, [], reps=50)

    # three of four cdjax seeds cut after 10 env steps: all four read at 10, and the verdict says why none is given
    rows = [r for r in rows if r["framework"] == "brax" or r["seed"] == 0 or r["env_steps"] <= 10]
    by = {e["learner"]: e for e in learning_report.table(rows, reps=50)}
    assert by["cdjax default"]["env_steps"] == 10 and by["cdjax default"]["seeds"] == 4
    assert by["cdjax default"]["left_out"] == []
    assert "cdjax default not compared: its final return is read at 10 env steps, Brax PPO's at 30" in \
        learning_report.report_text(rows, [], reps=50)


def test_learning_report_sources_rename_cdjax_rows_and_refuse_a_seed_twice(tmp_path, capsys):
    """DIR@cdjax=NAME: DIR's cdjax rows only, reported as variant NAME, so one setting's seeds from two runs under
    two variant names pool into one learner; the same seed from two sources is refused, not silently overwritten."""
    from benchmarks import learning_report

    def write(d, framework, variant, seeds):
        d.mkdir()
        (d / "rows.jsonl").write_text("".join(json.dumps(dict(
            task="t", framework=framework, variant=variant, seed=s, env_steps=st, eval_return=float(s), train_s=1.0))
            + "\n" for s in seeds for st in (0, 10)))

    write(tmp_path / "a", "cdjax", "head-0.1", range(3))
    write(tmp_path / "b", "cdjax", "default", range(100, 103))
    write(tmp_path / "c", "brax", "brax-ppo", range(2))
    assert learning_report.split_source(f"{tmp_path / 'a'}@cdjax=x") == (tmp_path / "a", "cdjax", "x")
    assert learning_report.split_source(f"{tmp_path / 'a'}@brax") == (tmp_path / "a", "brax", None)
    assert learning_report.split_source(f"{tmp_path / 'a'}@brax=x")[1] is None  # only cdjax rows are renamed
    rows, _ = learning_report.load([tmp_path / "a", f"{tmp_path / 'b'}@cdjax=head-0.1", f"{tmp_path / 'c'}@cdjax=y"])
    assert {r["variant"] for r in rows} == {"head-0.1"} and len(rows) == 12  # c has no cdjax rows
    (entry,) = learning_report.table(rows, reps=50)
    assert entry["learner"] == "cdjax head-0.1" and entry["seeds"] == 6
    rows, _ = learning_report.load([tmp_path / "a", f"{tmp_path / 'a'}@cdjax"])
    with pytest.raises(ValueError, match="seed 0 at 0 env steps"):
        learning_report.curves(rows)
    from benchmarks import learning  # the command says either in one sentence (exit 2), not with a traceback

    for sources in ([str(tmp_path / "a"), f"{tmp_path / 'a'}@cdjax"], [f"{tmp_path / 'a'}@cdjax="], [str(tmp_path)]):
        capsys.readouterr()
        assert learning.main(["--report", *sources]) == 2
        err = capsys.readouterr().err
        assert err.startswith("python -m benchmarks.learning: ") and err.count("\n") == 1, err


def test_learning_benchmark_refuses_bad_arguments_in_one_sentence_before_anything_runs(tmp_path, capsys, monkeypatch):
    """python -m benchmarks.learning: report options without --report, counts that are not positive, a negative base
    seed, an --out that is a file: one sentence naming the option, exit status 2, nothing run or written; --report of
    a directory without rows, or with a --write whose directory does not exist, likewise (no empty table, no plot)."""
    from benchmarks import learning

    def never(*args, **kwargs):
        pytest.fail("the benchmark started")

    monkeypatch.setattr(learning, "run_cdjax", never)
    monkeypatch.setattr(learning, "run_brax", never)
    out, afile = tmp_path / "out", tmp_path / "afile"
    afile.write_text("")

    def refused(argv, option):
        capsys.readouterr()
        with pytest.raises(SystemExit) as stop:
            learning.main(argv)
        err = capsys.readouterr().err
        assert stop.value.code == 2 and err.startswith("python -m benchmarks.learning: ") and err.count("\n") == 1, err
        assert option in err, err
        return err

    tiny = ["--tiny", "--out", str(out)]
    assert "runs the benchmark" in refused([*tiny, "--write", str(tmp_path / "L.md")], "--write goes with --report")
    refused([*tiny, "--parity-variants", "tanh"], "--parity-variants")
    for option, value in (("--seeds", "0"), ("--seeds", "-2"), ("--evals", "-1"), ("--evals", "0"),
                          ("--updates-per-eval", "0"), ("--first-seed", "-1"), ("--budget-s", "0")):
        refused([*tiny, option, value], f"argument {option}: '{value}' is not")
    refused(["--tiny", "--out", str(afile)], f"{afile} is a file")
    assert not out.exists() and not (tmp_path / "L.md").exists()
    capsys.readouterr()
    with pytest.raises(SystemExit):
        learning.main(["--help"])
    assert "B*1000 ... B*1000 + seeds - 1" in " ".join(capsys.readouterr().out.split())  # the rows cdjax labels

    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "rows.jsonl").write_text("\n")
    for write in ([], ["--write", str(tmp_path / "L.md")]):
        capsys.readouterr()
        assert learning.main(["--report", str(empty), *write]) == 2
        err = capsys.readouterr().err
        assert err == f"python -m benchmarks.learning: no rows in {empty / 'rows.jsonl'}: its run measured nothing (yet)\n"
    full = tmp_path / "full"
    full.mkdir()
    (full / "rows.jsonl").write_text(json.dumps(dict(task="t", framework="cdjax", variant="default", seed=0,
                                                     env_steps=0, eval_return=1.0, train_s=1.0)) + "\n")
    assert learning.main(["--report", f"{full}@brax"]) == 2  # sources that leave no row
    refused(["--report", str(full), "--write", str(tmp_path / "nodir" / "L.md")], "--write")
    refused(["--report", str(full), "--write", str(tmp_path)], "is a directory")
    err = refused(["--report", str(full), "--seeds", "3", "--out", str(out)], "--seeds, --out set up a benchmark run")
    assert "without --report" in err  # run-only options the report would ignore
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "empty", "full"]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """One run of the tiny suite (a subset of `--tiny --suite all`: every part except the devices
    comparison, which needs several devices; one num_envs, the compare one, so that its programs come from the
    compilation cache). Brax's epochs of one training step, and 2 vmapped seeds (one count: the ratios to one seed
    are checked on hand-made rows in test_targets_and_scaling_on_hand_made_numbers): the programs
    test_learning_benchmark_tiny_evaluates_both_learners_at_the_same_env_steps compiled, from the cache."""
    out = tmp_path_factory.mktemp("bench")
    main(["--tiny", "--suite", "compare", "seeds", "envs", "--cases", *COMPARE, "--seed-counts", "2",
          "--scaling-cases", "model-free", "--env-counts", "16", "--out", str(out), "--brax-steps-per-epoch", "1",
          "--trace", str(out / "trace"), "--trace-top", "10",
          "--budget-s", "86400"])  # every case is asserted below: no case may be skipped because the CPU is busy
    return out, json.loads((out / "results.json").read_text())


def test_benchmark_run_refuses_bad_arguments_in_one_sentence_before_anything_compiles(tmp_path, capsys, monkeypatch):
    """python -m benchmarks.run: counts below 1, non-positive seconds, sizes or a task no Spec or Config takes, --merge
    sources that hold no results, outputs that cannot be written: one sentence naming the option, exit status 2,
    before any suite starts (none would have failed before its first case compiled, some not at all)."""
    from benchmarks import run

    for name in ("run_compare", "run_seeds", "run_envs", "run_devices"):
        monkeypatch.setattr(run, name, lambda *args: pytest.fail("a suite started"))
    out, afile, bad = tmp_path / "out", tmp_path / "afile", tmp_path / "bad.json"
    afile.write_text("")
    bad.write_text("not json")
    (tmp_path / "empty").mkdir()

    def refused(argv, *said):
        capsys.readouterr()
        with pytest.raises(SystemExit) as stop:
            main(argv)
        err = capsys.readouterr().err
        assert stop.value.code == 2 and err.startswith("python -m benchmarks.run: ") and err.count("\n") == 1, err
        assert all(s in err for s in said), err
        return err

    tiny = ["--tiny", "--suite", "all", "--out", str(out)]
    for option, value in (("--num-envs", "-5"), ("--num-envs", "0"), ("--env-counts", "0"), ("--seed-counts", "0"),
                          ("--updates", "0"), ("--updates", "-3"), ("--max-case-s", "0"), ("--budget-s", "-1")):
        refused([*tiny, option, value], f"argument {option}: '{value}' is not")
    refused([*tiny, "--env", "nosuchenv"], "--env nosuchenv: Unknown env 'nosuchenv'")
    refused([*tiny, "--num-envs", "1"], "--num-envs 1: eval_envs=2 is larger than num_envs=1")  # a Config's refusal
    refused([*tiny, "--env-counts", "16", "1"], "--env-counts 1: ")
    refused(["--suite", "compare", "--num-envs", "100", "--dry-run"], "--num-envs 100: ", "a multiple of num_envs")
    refused([*tiny, "--write-results", str(tmp_path / "nodir" / "R.md")], "--write-results", "does not exist")
    refused(["--tiny", "--out", str(afile)], f"{afile} is a file")
    for source, said in ((tmp_path / "none", "does not exist"), (tmp_path / "empty", "holds no results.json"),
                         (bad, "is not a results.json"), (afile, "is not a results.json")):
        refused(["--merge", str(source), "--out", str(out)], f"--merge: {source} {said}")
    refused(["--merge", str(bad), "--tiny", "--num-envs", "8"], "--tiny, --num-envs set up a run")  # it would ignore them
    # --trace: a directory that could not be made (found only after the cases ran), suites and cases that trace nothing
    assert "--out" not in refused([*tiny, "--trace", str(afile / "trace")],
                                  f"--trace: cannot write into {afile / 'trace'}: Not a directory")
    assert "--out" not in refused([*tiny, "--trace", str(afile)], f"--trace: {afile} is a file, not a directory")
    refused(["--tiny", "--suite", "envs", "devices", "--trace", str(out)], "--trace traces", "none of which")
    refused(["--tiny", "--cases", "ceiling", "collect", "--trace", str(out)], "--trace traces", "none of which")
    refused(["--tiny", "--trace-top", "5"], "--trace-top goes with --trace")
    assert main(["--tiny", "--suite", "envs", "seeds", "--trace", str(out / "trace"), "--dry-run"]) == {}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "bad.json", "empty"]


def test_tiny_suite_measures_every_case(tiny):
    out, results = tiny
    parts = results["parts"]
    assert [r["case"] for r in parts["compare"]] == COMPARE
    # the scaling parts on model-free only (CD's vmapped programs are tested in test_train; compiling them
    # again here cost ~1 min of CI)
    assert {(r["case"], r["seeds"]) for r in parts["seeds"]} == {("model-free", 2)}
    assert {(r["case"], r["num_envs"]) for r in parts["envs"]} == {("ceiling", 16), ("model-free", 16)}
    for part, rows in parts.items():
        for r in rows:
            assert r["status"] == "ok", (part, r)
            assert math.isfinite(r["env_steps_per_s"]) and r["env_steps_per_s"] > 0, (part, r)
            assert r["update_s"] > 0 and r["compile_s"] >= 0, (part, r)
            assert r.get("finite", True), (part, r)
    brax = parts["compare"][0]
    assert len(brax["epoch_s_all"]) == 5 and brax["env_class"] == "PointMass"
    meta = results["metas"][0]
    assert meta["tiny"] and meta["device_count"] >= 1 and meta["command"].startswith("python -m benchmarks.run")
    # the compile mode and per-program options the cdjax cases were compiled with (no process flag says them)
    from cdjax import runtime

    assert meta["compile_mode"] == runtime.compile_mode() and meta["compiler_options"] == runtime.compiler_options()
    assert (out / "results.png").stat().st_size > 0


def test_traced_cases_carry_an_op_level_profile(tiny):
    out, results = tiny
    rows = {r["case"]: r for r in results["parts"]["compare"]}
    for case in ("model-free", DESIGNATED_CD):
        profile = rows[case]["profile"]
        assert profile["source"] == "XLA ops (CPU)" and profile["hlo_grouping"], profile
        assert len(profile["ops"]) == 10 and profile["device_ms"] > 0
        assert sum(g["pct"] for g in profile["groups"]) == pytest.approx(100.0, abs=0.01)
        assert "gemm" in {g["group"] for g in profile["groups"]}  # the MLPs
        assert rows[case]["profile_md"].rstrip("\n") in (out / "results.md").read_text()
    assert "profile" not in rows["collect"] and "profile" not in rows["ceiling"]
    # the seeds suite's rows are traced too: one update of all their vmapped seeds
    for row in results["parts"]["seeds"]:
        assert row["trace_dir"].endswith(f"model-free-x{row['seeds']}"), row
        assert row["profile"]["device_ms"] > 0 and "gemm" in {g["group"] for g in row["profile"]["groups"]}
        assert row["profile_md"].rstrip("\n") in (out / "results.md").read_text()
        assert f"`model-free` update of {row['seeds']} vmapped seeds" in (out / "results.md").read_text()
    assert "`model-free` update (`--trace`" in (out / "results.md").read_text()  # the compare row: one seed


def test_profile_summary_finds_the_matmul(tmp_path):
    """A real trace on CPU of a matmul followed by elementwise ops: the dot is found, percentages add up."""
    import jax
    import jax.numpy as jnp

    def f(x, w):
        return jnp.tanh(x @ w) * 2.0 + 1.0

    x, w = jnp.ones((256, 512)), jnp.full((512, 512), 0.01)
    compiled = jax.jit(f).lower(x, w).compile()
    jax.block_until_ready(compiled(x, w))
    with profile_summary.trace(tmp_path / "trace", compiled):
        for _ in range(3):
            jax.block_until_ready(compiled(x, w))
    summary = profile_summary.summarize(tmp_path / "trace")
    assert summary["source"] == "XLA ops (CPU)" and summary["hlo_grouping"]
    dots = [o for o in summary["ops"] if o["group"] == "gemm"]
    assert len(dots) == 1 and dots[0]["count"] == 3 and "dot_general" in dots[0]["source"], summary["ops"]
    assert sum(o["pct"] for o in summary["ops"]) == pytest.approx(100.0, abs=0.01)
    assert sum(g["pct"] for g in summary["groups"]) == pytest.approx(100.0, abs=0.01)
    assert sum(o["total_ms"] for o in summary["ops"]) == pytest.approx(summary["device_ms"])
    # the command line: the same tables, to a file
    md = profile_summary.main([str(tmp_path), "--top", "5", "--out", str(tmp_path / "ops.md")])
    assert (tmp_path / "ops.md").read_text() == md and "| gemm |" in md
    _assert_tables_rectangular(md)
    # without the HLO text the ops are grouped by name; the times do not change
    for f in (tmp_path / "trace").glob("*.hlo.txt"):
        f.unlink()
    by_name = profile_summary.summarize(tmp_path / "trace")
    assert not by_name["hlo_grouping"] and by_name["device_ms"] == summary["device_ms"]


def test_profile_summary_of_a_gpu_trace_reads_stream_kernels(tmp_path):
    """Hand-made events in the layout of a GPU trace: only kernels on Stream lines count (not the XLA Ops
    line that spans them again), grouped by kernel name."""
    events = [
        {"ph": "M", "pid": 1, "name": "process_name", "args": {"name": "/device:GPU:0"}},
        {"ph": "M", "pid": 1, "tid": 7, "name": "thread_name", "args": {"name": "Stream #7(Compute)"}},
        {"ph": "M", "pid": 1, "tid": 9, "name": "thread_name", "args": {"name": "XLA Ops"}},
        {"ph": "M", "pid": 2, "name": "process_name", "args": {"name": "/host:CPU"}},
        {"ph": "X", "pid": 1, "tid": 7, "ts": 0.0, "dur": 60.0, "args": {"hlo_op": "custom-call.3"},
         "name": "void cutlass::Kernel<cutlass_80_tensorop_s1688gemm_128x128>(Params)"},
        {"ph": "X", "pid": 1, "tid": 7, "ts": 70.0, "dur": 30.0, "name": "loop_add_fusion",
         "args": {"hlo_op": "loop_add_fusion",
                  "kernel_details": "regs:40 static_shared:0 dynamic_shared:0 grid:3,2,1 block:128,2,1 occ_pct:50.0"}},
        {"ph": "X", "pid": 1, "tid": 7, "ts": 100.0, "dur": 10.0, "name": "Memset", "args": {}},
        {"ph": "X", "pid": 1, "tid": 9, "ts": 0.0, "dur": 100.0, "name": "custom-call.3", "args": {}},
        {"ph": "X", "pid": 2, "tid": 3, "ts": 0.0, "dur": 500.0, "name": "host work", "args": {"hlo_op": "x"}},
    ]
    run = tmp_path / "plugins" / "profile" / "run1"
    run.mkdir(parents=True)
    with profile_summary.gzip.open(run / "perfetto_trace.json.gz", "wt") as f:
        json.dump({"traceEvents": events}, f)
    summary = profile_summary.summarize(tmp_path)
    assert summary["source"] == "GPU kernels" and summary["device_ms"] == pytest.approx(0.1)
    assert [(o["group"], round(o["pct"])) for o in summary["ops"]] == [("gemm", 60), ("fusion", 30), ("memset", 10)]
    assert summary["ops"][0]["name"].startswith("custom-call.3: cutlass::Kernel<")
    # the launch shape of a kernel, from the profiler's kernel details: 3 x 2 blocks of 128 x 2 threads
    assert [o["launch"] for o in summary["ops"]] == ["", "6 x 256 (50%)", ""]
    assert "| 6 x 256 (50%) |" in profile_summary.markdown(summary)
    assert (summary["span_ms"], summary["busy_ms"]) == pytest.approx((0.11, 0.1)) and summary["concurrency"] == 1.0
    # kernels of one CUDA graph that run side by side overlap on their stream's line: each keeps its whole duration
    events[5] = dict(events[5], ts=40.0)  # the fusion from 40 to 70 us, beside the gemm's last 20
    with profile_summary.gzip.open(run / "perfetto_trace.json.gz", "wt") as f:
        json.dump({"traceEvents": events}, f)
    summary = profile_summary.summarize(tmp_path)
    assert summary["device_ms"] == pytest.approx(0.1) and round(summary["ops"][1]["pct"]) == 30
    assert (summary["span_ms"], summary["busy_ms"]) == pytest.approx((0.11, 0.08))
    assert summary["concurrency"] == pytest.approx(100 / 80)
    assert "0.080 ms of it, 1.25 at once" in profile_summary.markdown(summary)


def test_profile_summary_splits_a_cuda_graph_into_its_launches():
    """A loop body's graph launched 3 times, each launch a GEMM, two fusions side by side, then the same GEMM again
    (an unrolled chain's repeated kernel): 4 kernels a launch, its span and busy time per launch; another graph's
    kernels and a kernel outside any graph do not mix in."""
    def kernel(name, graph, ts, dur):
        return {"ph": "X", "pid": 1, "tid": 7, "ts": ts, "dur": dur, "name": name, "args": {"hlo_op": graph}}

    events = []
    for start in (0.0, 100.0, 200.0):  # each launch: 0-10 gemm, 12-20 and 14-22 fusions, 30-40 gemm, then idle
        events += [kernel("gemm", "command_buffer_5", start, 10.0), kernel("fusion_a", "command_buffer_5", start + 12, 8.0),
                   kernel("fusion_b", "command_buffer_5", start + 14, 8.0), kernel("gemm", "command_buffer_5", start + 30, 10.0)]
    events += [kernel("copy", "command_buffer_9", 50.0, 5.0), kernel("loose", "custom-call.1", 60.0, 5.0)]
    (big, small) = profile_summary.graphs(events, summed_us=sum(e["dur"] for e in events))
    assert (big["graph"], big["launches"], big["kernels_per_launch"]) == ("command_buffer_5", 3, 4.0)
    assert big["span_us"] == pytest.approx(40.0) and big["busy_us"] == pytest.approx(30.0)  # 10 + (12..22) + 10
    assert big["total_ms"] == pytest.approx(0.108) and big["pct"] == pytest.approx(100 * 108 / 118)
    assert (small["graph"], small["launches"], small["kernels"]) == ("command_buffer_9", 1, 1)
    md = profile_summary.markdown({"source": "GPU kernels", "device_ms": 0.118, "events": 14, "distinct_ops": 5,
                                   "hlo_grouping": False, "span_ms": 0.24, "busy_ms": 0.1, "concurrency": 1.1,
                                   "ops": [], "groups": [], "graphs": [big, small]})
    assert "| `command_buffer_5` | 3 | 4.0 | 0.108 | 91.5 | 40.0 | 30.0 | 36.0 |" in md


def test_profile_summary_refuses_what_it_cannot_read_or_write(tmp_path, capsys):
    for argv, said in (([str(tmp_path / "none")], "does not exist"), ([str(tmp_path)], "no perfetto_trace.json.gz"),
                       ([str(tmp_path), "--top", "0"], "--top"),
                       ([str(tmp_path), "--out", str(tmp_path / "no" / "x.md")], "does not exist")):
        with pytest.raises(SystemExit) as e:
            profile_summary.main(argv)
        err = capsys.readouterr().err.strip()
        assert e.value.code == 2 and said in err and "\n" not in err, (argv, err)


def test_ratios_follow_from_raw_numbers(tiny):
    _, results = tiny
    rows = {r["case"]: r for r in results["parts"]["compare"]}
    ceiling, brax, mf = rows["ceiling"], rows["brax-ppo"], rows["model-free"]
    for r in rows.values():
        assert r["vs_ceiling"] == pytest.approx(r["env_steps_per_s"] / ceiling["env_steps_per_s"])
        assert r["vs_brax"] == pytest.approx(r["env_steps_per_s"] / brax["env_steps_per_s"])
    cd = rows[DESIGNATED_CD]
    assert cd["wall_vs_model_free"] == pytest.approx(cd["update_s"] / mf["update_s"])
    assert cd["env_steps_per_s"] == pytest.approx(cd["steps_per_update"] / cd["update_s"])
    seeds = {(r["case"], r["seeds"]): r for r in results["parts"]["seeds"]}
    two = seeds[("model-free", 2)]  # the scaling parts run model-free at 2 seeds only (the tiny fixture)
    assert two["steps_per_update"] == 2 * TINY.with_num_envs(16).env_steps_per_update
    assert two["speedup_vs_1"] is None  # no 1-seed row to divide by (hand-made rows: a ratio where there is one)
    assert two["s_per_seed_update"] == pytest.approx(two["update_s"] / 2)
    by = {t["target"]: t for t in report.targets(results)}
    assert by["cd_vs_brax"]["value"] == pytest.approx(cd["env_steps_per_s"] / brax["env_steps_per_s"])
    assert by["mf_vs_brax"]["value"] == pytest.approx(mf["env_steps_per_s"] / brax["env_steps_per_s"])
    assert by["cd_compile_s"]["value"] == pytest.approx(cd["compile_s"])
    paper, mbmf = rows[PAPER_CD], rows["mbmf"]
    assert paper["wall_vs_mbmf"] == pytest.approx(paper["update_s"] / mbmf["update_s"])
    assert by["paper_wall_vs_mbmf"]["value"] == pytest.approx(paper["wall_vs_mbmf"])
    assert by["paper_seeds10_vs_mbmf"]["met"] is None  # 10 seeds of cd-paper and mbmf not measured here
    assert paper["overrides"]["cc_epochs"] == 0 and paper["num_windows"] == TINY.unroll_length - TINY.horizon + 1
    assert by["seeds32_vs_1"]["met"] is None  # 32 seeds not measured at tiny sizes


def test_markdown_lists_every_case(tiny):
    out, results = tiny
    md = (out / "results.md").read_text()
    compare_section = md.split("### seeds")[0]
    for case in COMPARE:
        assert f"| {case} " in compare_section or f"**{case}**" in compare_section, case
    assert "### seeds" in md and "### envs" in md and md.rstrip().split("### targets")[-1].count("\n|") >= 6
    assert "| model-free | 2 | 16 |" in md
    assert "tiny CPU smoke" in md
    _assert_tables_rectangular(md)
    # RESULTS.md generator: device, exact command, tables, plot
    target = out / "RESULTS.md"
    report.write_results_md(results, target, "python -m benchmarks.run --merge x --write-results RESULTS.md")
    text = target.read_text()
    assert results["metas"][0]["command"] in text and results["metas"][0]["device"] in text
    assert "![throughput and scaling](RESULTS.png)" in text and (out / "RESULTS.png").exists()


def _assert_tables_rectangular(md: str):
    """Every markdown table has as many cells in each row as in its header."""
    blocks, current = [], []
    for line in md.splitlines() + [""]:
        if line.startswith("|"):
            current.append(line)
        elif current:
            blocks.append(current)
            current = []
    assert blocks
    for block in blocks:
        assert len({line.count("|") for line in block}) == 1, block


def _row(case, sps, update_s, **kw):
    return {"case": case, "status": "ok", "env_steps_per_s": sps, "update_s": update_s, **kw}


def test_targets_and_scaling_on_hand_made_numbers():
    steps = 327_680
    results = {"metas": [{"device": "H200", "device_count": 1}], "part_meta": {"compare": 0, "seeds": 0},
               "parts": {"compare": [
                   _row("brax-ppo", 245_000.0, steps / 245_000, kind="brax", steps_per_update=steps),
                   _row("ceiling", 1_800_000.0, 0.5, kind="ceiling", steps_per_update=900_000),
                   _row("model-free", 490_000.0, steps / 490_000, kind="cdjax", arm="model-free",
                        steps_per_update=steps),
                   _row("mbmf", 400_000.0, steps / 400_000, kind="cdjax", arm="mbmf", steps_per_update=steps),
                   _row(DESIGNATED_CD, 300_000.0, steps / 300_000, kind="cdjax", arm="cd", compile_s=70.0,
                        steps_per_update=steps),
                   _row(PAPER_CD, 250_000.0, steps / 250_000, kind="cdjax", arm="cd", steps_per_update=steps,
                        sgd_steps=256),
                   {"case": "cd-default", "status": "error", "error": "boom"}],
                   "seeds": [_row(DESIGNATED_CD, 10_000.0, 2.0, seeds=1, mesh_devices=1, mem_bytes=1_000),
                             _row(DESIGNATED_CD, 90_000.0, 7.1, seeds=32, mesh_devices=1, mem_bytes=32_000),
                             {"case": DESIGNATED_CD, "status": "OOM", "seeds": 128, "mesh_devices": 1},
                             _row("mbmf", 50_000.0, 1.0, seeds=10, mesh_devices=1),
                             _row(PAPER_CD, 40_000.0, 1.2, seeds=10, mesh_devices=1)]}}
    report.add_ratios(results)
    by = {t["target"]: t for t in report.targets(results)}
    assert by["cd_vs_brax"]["value"] == pytest.approx(300 / 245) and by["cd_vs_brax"]["met"]
    assert by["mf_vs_brax"]["value"] == pytest.approx(2.0) and by["mf_vs_brax"]["met"]
    assert by["cd_wall_vs_mf"]["value"] == pytest.approx(490 / 300) and by["cd_wall_vs_mf"]["met"] is False
    assert by["seeds32_vs_1"]["value"] == pytest.approx(9.0) and by["seeds32_vs_1"]["met"]
    assert by["cd_compile_s"]["met"] is False
    assert by["paper_wall_vs_mbmf"]["value"] == pytest.approx(400 / 250) and by["paper_wall_vs_mbmf"]["met"] is False
    assert by["paper_seeds10_vs_mbmf"]["value"] == pytest.approx(1.2) and by["paper_seeds10_vs_mbmf"]["met"]
    md = report.markdown(results)
    assert "**MISSED**" in md and "boom" in md and "first OOM at 128" in md and "largest count that ran: 32" in md
    _assert_tables_rectangular(md)
    assert "cd_wall_vs_mf missed" in md and "cd_compile_s missed" in md and "paper_wall_vs_mbmf missed" in md
    # without the collect case a missed target still names its update time and says what the split needs
    results["parts"]["compare"] = [r for r in results["parts"]["compare"] if r["case"] != "collect"]
    results["parts"]["compare"][2] = _row("model-free", 300_000.0, steps / 300_000, kind="cdjax", arm="model-free",
                                          steps_per_update=steps)  # 1.22x Brax: missed
    report.add_ratios(results)
    assert (f"- mf_vs_brax missed. model-free: {steps / 300_000:.3f} s/update; no split (add the `collect` and "
            "`ceiling` cases).") in report.markdown(results)
    # linear fit through (1, 1000), (32, 32000): 1000 bytes per seed -> 64,000 bytes fit 64 seeds
    assert report.estimate_max_seeds(results["parts"]["seeds"], 64_000) == 64
    first = {"compare": [{"case": "x"}], "seeds": [{"case": "y", "seeds": 1}, {"case": "y", "seeds": 8, "v": 1}]}
    second = {"compare": [{"case": "w"}], "seeds": [{"case": "z", "seeds": 1}, {"case": "y", "seeds": 8, "v": 2}]}
    merged = report.merge([{"metas": [{"device": "a"}], "part_meta": {"compare": 0, "seeds": 0}, "parts": first},
                           {"metas": [{"device": "b"}], "part_meta": {"compare": 0, "seeds": 0}, "parts": second}])
    assert merged["part_meta"] == {"compare": 1, "seeds": 0} and len(merged["metas"]) == 2
    assert [r["case"] for r in merged["parts"]["compare"]] == ["w"]  # compare: one process, never mixed
    assert [(r["case"], r["seeds"], r.get("v")) for r in merged["parts"]["seeds"]] == [("y", 1, None), ("z", 1, None),
                                                                                      ("y", 8, 2)]


def test_seed_scaling_stops_growing_after_oom():
    calls = []

    def fake_run_case(label, fn):
        calls.append(label)
        runs = int(label.split("x")[-1])
        return {"status": "OOM"} if runs >= 8 else _row("model-free", 1.0 * runs, 1.0, seeds=runs)

    rows = list(seed_scaling(TINY, ["model-free"], [1, 8, 32, 128], None, fake_run_case))
    assert calls == ["model-free x1", "model-free x8"]
    assert [r["status"] for r in rows] == ["ok", "OOM"] + ["not tried (smaller count was OOM)"] * 2
    assert [r["seeds"] for r in rows] == [1, 8, 32, 128]


def test_distributed_runs_the_sweep_suites_and_skips_a_case_on_every_process(capsys, monkeypatch):
    """--distributed takes the suites whose sweeps span every process (compare and envs are single-device); a case
    is skipped on every process when one process's time budget is used (the exchange faked: process 1's)."""
    import argparse

    from benchmarks.run import Suite
    from cdjax import multihost

    with pytest.raises(SystemExit) as info:
        main(["--tiny", "--suite", "seeds", "compare", "--distributed"])
    assert info.value.code == 2 and "give --suite seeds devices" in capsys.readouterr().err
    suite = Suite(argparse.Namespace(budget_s=1e9, distributed=True), {}, None)
    monkeypatch.setattr(multihost, "exchange", lambda text: [text, "1"])  # process 1: its budget is used
    row = suite.run_case("model-free x2", lambda: pytest.fail("a case skipped by another process ran here"))
    assert row["status"].startswith("skipped (time budget")
    monkeypatch.setattr(multihost, "exchange", lambda text: [text, ""])
    ran = {"status": "ok", "env_steps_per_s": 1.0, "update_s": 1.0, "compile_s": 1.0}
    assert suite.run_case("model-free x2", lambda: dict(ran))["status"] == "ok"


def test_ale_benchmark_refuses_bad_arguments_in_one_sentence(tmp_path, capsys, monkeypatch):
    """benchmarks.ale: a game no ALE preset names, counts below 1, and (without the `atari` extra, faked here) the
    install hint `cdjax sweep` gives, before ale-py is imported or anything is written. One sentence each, exit
    status 2, no sweep started."""
    from benchmarks import ale
    from cdjax import runner
    from cdjax.agents.atari import config as atari_config

    monkeypatch.setattr(atari_config, "ale_available", lambda: False)
    monkeypatch.setattr(runner, "run_sweep", lambda *args, **kwargs: pytest.fail("a sweep started"))
    out, afile = tmp_path / "out", tmp_path / "afile"
    afile.write_text("")

    def refused(main, argv, prog, said):
        benchmark_refuses(capsys, main, argv, prog, said)

    refused(ale.main, ["--game", "nosuch", "--out", str(out)], "ale", "argument --game: invalid choice: 'nosuch'")
    refused(ale.main, ["--tiny", "--totals", "0", "--out", str(out)], "ale", "argument --totals: '0' is not")
    refused(ale.main, ["--tiny", "--seconds", "0", "--out", str(out)], "ale", "argument --seconds: '0' is not")
    refused(ale.main, ["--tiny", "--out", str(out)], "ale", 'pip install -e ".[atari]"')
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]


def test_compile_workers_reads_its_variable(monkeypatch):
    from cdjax.protocol import ConfigError
    from cdjax.runner import arms

    monkeypatch.setenv("CDJAX_COMPILE_WORKERS", "1")
    assert arms.compile_workers() == 1
    monkeypatch.setenv("CDJAX_COMPILE_WORKERS", "0")
    with pytest.raises(ConfigError, match="whole number >= 1"):  # the command line's one sentence
        arms.compile_workers()
    monkeypatch.delenv("CDJAX_COMPILE_WORKERS")
    assert arms.compile_workers() == max(1, arms.usable_cores() // 2)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(16)), raising=False)  # pinned to 16 cores
    assert arms.usable_cores() == 16 and arms.compile_workers() == 8
    monkeypatch.delattr(os, "sched_getaffinity")  # an OS without it: the machine's cores
    assert arms.usable_cores() == (os.cpu_count() or 1)


def test_apply_xla_defaults_adds_cdjaxs_flags_and_keeps_the_users_own(monkeypatch):
    from cdjax import runtime

    monkeypatch.delenv("XLA_FLAGS", raising=False)
    monkeypatch.setattr(runtime, "_backends_started", lambda: False)  # as at a fresh `import cdjax`
    ours = [runtime.CPU_SCHEDULER_FLAG, runtime.GPU_AUTOTUNE_FLAG, runtime.GPU_GEMM_TILINGS_FLAG]
    runtime.apply_xla_defaults()
    assert os.environ["XLA_FLAGS"].split() == ours
    runtime.apply_xla_defaults()  # a second import (a reload) adds nothing twice
    assert os.environ["XLA_FLAGS"].split() == ours
    # a level the user names (XLA's own default 4, say) wins, and the user's other flags stay first, as given
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=2 --xla_gpu_autotune_level=4")
    runtime.apply_xla_defaults()
    assert os.environ["XLA_FLAGS"].split() == ["--xla_force_host_platform_device_count=2",
                                               "--xla_gpu_autotune_level=4", ours[0], *ours[2:]]
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_enable_concurrency_optimized_scheduler=true")
    runtime.apply_xla_defaults()
    assert os.environ["XLA_FLAGS"].split() == ["--xla_cpu_enable_concurrency_optimized_scheduler=true", *ours[1:]]
    # the tilings option named empty (XLA's own search) is the user's: it stays, and cdjax adds no value of its own
    monkeypatch.setenv("XLA_FLAGS", "--xla_gpu_experimental_cost_model_gemm_tiling_options=")
    runtime.apply_xla_defaults()
    assert os.environ["XLA_FLAGS"].split() == ["--xla_gpu_experimental_cost_model_gemm_tiling_options=", *ours[:2]]
    # an option is the user's only when named as such: a longer option that contains its name is not it
    monkeypatch.setenv("XLA_FLAGS", "--xla_gpu_autotune_level_extra=3")
    runtime.apply_xla_defaults()
    assert os.environ["XLA_FLAGS"].split() == ["--xla_gpu_autotune_level_extra=3", *ours]
    # the graph scheduling is per program (runtime.compiler_options), never in XLA_FLAGS, so Brax's programs or a
    # user's own in the same process keep XLA's
    assert runtime.SCHEDULING_OPTION not in os.environ["XLA_FLAGS"]
    # with a backend already started, adding a flag is told of (naming it), adding none is not
    monkeypatch.setattr(runtime, "_backends_started", lambda: True)
    monkeypatch.setenv("XLA_FLAGS", " ".join(ours[1:]))
    with pytest.warns(RuntimeWarning, match=r"started before cdjax.runtime.apply_xla_defaults\(\) was called.*concurrency_optimized_scheduler=false"
                                           r"\) do not apply"):
        runtime.apply_xla_defaults()
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        runtime.apply_xla_defaults()
    # a fresh process: importing benchmarks (an entry point) sets them before JAX starts, and XLA:CPU accepts the GPU flags (it aborts on
    # a flag it does not know); `import benchmarks` imports cdjax first (the suites start a backend to name the
    # device); a backend started before cdjax is imported is told of, naming the flags that cannot apply
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    flags = subprocess.run(
        [sys.executable, "-c", "import os, benchmarks, jax; jax.numpy.ones(2).block_until_ready(); "
                               "print(os.environ['XLA_FLAGS'])"],
        env=env, capture_output=True, text=True, check=True, cwd=pathlib.Path(__file__).parents[1]).stdout
    assert all(flag in flags for flag in ours)
    late = subprocess.run([sys.executable, "-c", "import jax; jax.devices(); import benchmarks"], env=env,
                          capture_output=True, text=True, check=True, cwd=pathlib.Path(__file__).parents[1]).stderr
    assert "A JAX backend started before cdjax.runtime.apply_xla_defaults() was called" in late and runtime.GPU_AUTOTUNE_FLAG in late


def test_compile_mode_goes_to_xla_with_each_program_the_runner_compiles(monkeypatch):
    import types

    import jax
    import jax.numpy as jnp
    import numpy as np

    from cdjax import runtime
    from cdjax.protocol import ConfigError
    from cdjax.runner import arms

    seen = []
    original = jax.stages.Lowered.compile

    def spy(self, compiler_options=None, **kwargs):
        seen.append(compiler_options)
        return original(self, compiler_options, **kwargs)

    monkeypatch.setattr(jax.stages.Lowered, "compile", spy)
    monkeypatch.setattr(runtime, "_mode", None)
    monkeypatch.delenv(runtime.MODE_ENV, raising=False)
    arm, owner, f, x = types.SimpleNamespace(name="x"), object(), jax.jit(lambda x: x @ x.T + 1.0), jnp.eye(3) * 2.0
    default = arms._compiled(arm, "t", f.lower, x, owner=owner)
    monkeypatch.setenv(runtime.MODE_ENV, "fast")
    fast = arms._compiled(arm, "t", f.lower, x, owner=owner)  # another mode, another program: XLA takes its options
    runtime.configure(compile_mode="default")  # configure's mode wins over the variable's
    assert arms._compiled(arm, "t", f.lower, x, owner=owner) is default and fast is not default
    assert seen == [runtime.SCHEDULING, {"xla_gpu_enable_triton_gemm": False, **runtime.SCHEDULING}]
    # the deterministic mode's options are XLA's own names: XLA takes them for a program (an unknown one it refuses)
    assert runtime.COMPILE_MODES["deterministic"] == {"xla_gpu_deterministic_ops": True, "xla_gpu_autotune_level": 0}
    for mode in ("deterministic", "tuned"):
        np.testing.assert_array_equal(f.lower(x).compile(runtime.compiler_options(mode))(x), default(x))
    # the tuned mode undoes, per program, exactly the two autotuning flags `import cdjax` adds
    added = {flag.split("=")[0].lstrip("-") for flag in (runtime.GPU_AUTOTUNE_FLAG, runtime.GPU_GEMM_TILINGS_FLAG)}
    assert set(runtime.COMPILE_MODES["tuned"]) == added
    assert runtime.COMPILE_MODES["tuned"]["xla_gpu_autotune_level"] == 4  # XLA's own level
    with pytest.raises(Exception, match="xla_gpu_no_such_option"):
        f.lower(x).compile({"xla_gpu_no_such_option": True})
    np.testing.assert_array_equal(default(x), fast(x))  # on a CPU the GPU option changes nothing
    with pytest.raises(ConfigError, match="compile_mode must be one of default, fast, deterministic, tuned, "
                                          "got 'turbo'"):
        runtime.configure(compile_mode="turbo")
    monkeypatch.setattr(runtime, "_mode", None)
    monkeypatch.setenv(runtime.MODE_ENV, "turbo")
    with pytest.raises(ConfigError, match=r"\$CDJAX_COMPILE_MODE must be one of"):
        runtime.compiler_options()
    # the CLI: the flag, else the variable's mode, else default; a later call without the flag drops an earlier one's
    import argparse

    from cdjax import cli

    def flags(mode):
        return argparse.Namespace(compile_mode=mode, cache_dir=None, debug_nans=False, disable_jit=False)

    monkeypatch.delenv(runtime.MODE_ENV)
    cli._configure(flags("fast"))
    assert runtime.compile_mode() == "fast"
    cli._configure(flags(None))
    assert runtime.compile_mode() == "default"
    monkeypatch.setenv(runtime.MODE_ENV, "fast")
    cli._configure(flags(None))
    assert runtime.compile_mode() == "fast"
    cli._configure(flags("default"))
    assert runtime.compile_mode() == "default"


def test_cdjax_xla_options_reach_cdjax_programs_and_bad_ones_are_refused_in_one_sentence(monkeypatch):
    """$CDJAX_XLA_OPTIONS: NAME=VALUE words (XLA_FLAGS' spelling) added to the options cdjax compiles
    its own programs with, on top of the compile mode's and the scheduling; XLA applies them (copy insertion with
    region analysis leaves a small loop fewer copies); a word that is not NAME=VALUE, the scheduling option, an option
    XLA does not know and a value of the wrong type are each refused in one sentence naming the variable."""
    import types

    import jax
    import jax.numpy as jnp

    from cdjax import runtime
    from cdjax.protocol import ConfigError
    from cdjax.runner import arms, budget

    monkeypatch.setattr(runtime, "_mode", None)
    monkeypatch.delenv(runtime.MODE_ENV, raising=False)
    monkeypatch.setenv("XLA_FLAGS", "")
    monkeypatch.delenv(runtime.OPTIONS_ENV, raising=False)
    assert runtime.environment_options() == {} and runtime.compiler_options() == runtime.SCHEDULING

    def body(c):  # a loop whose carried values are read after their successors are computed: XLA copies some
        i, a, b, d, e = c
        na, nb = jnp.where(a > b, a * 0.5, b), jnp.where(a > b, b, a + d)
        return i + 1, na, nb, jnp.where(na > nb, d, e), jnp.where(na > nb, e * 2, d)

    f = jax.jit(lambda x: jax.lax.while_loop(lambda c: c[0] < 10, body, (0, x, x + 1, x * 2, x * 3)))
    x = jnp.ones(8)
    plain = arms._compiled(types.SimpleNamespace(name="a", room=None, in_order={}), "chunk", f.lower, x,
                           owner=object())
    region = "xla_cpu_copy_insertion_use_region_analysis"
    monkeypatch.setenv(runtime.OPTIONS_ENV, "--xla_gpu_cuda_data_dir=/a,b=c")  # a text value with ',' and '=' in it
    assert runtime.environment_options() == {"xla_gpu_cuda_data_dir": "/a,b=c"}
    monkeypatch.setenv(runtime.OPTIONS_ENV, f"--{region}=true  xla_gpu_autotune_level=2")
    assert runtime.environment_options() == {region: True, "xla_gpu_autotune_level": 2}
    assert runtime.compiler_options() == {**runtime.SCHEDULING, region: True, "xla_gpu_autotune_level": 2}
    assert runtime.compiler_options("fast", in_order=True) == {"xla_gpu_enable_triton_gemm": False, region: True,
                                                               "xla_gpu_autotune_level": 2}
    owner = object()
    regions = arms._compiled(types.SimpleNamespace(name="a", room=None, in_order={}), "chunk", f.lower, x,
                             owner=owner)
    outside, _ = budget.compile_fitting(f.lower(x))
    copies = [program.as_text().count(" copy(") for program in (plain, regions, outside)]
    assert copies[1] < copies[0] and copies[2] == copies[1], copies
    assert all(jnp.array_equal(a, b) for a, b in zip(jax.tree.leaves(plain(x)), jax.tree.leaves(regions(x))))
    for text, match in ((f"{region}", "takes NAME=VALUE words"),
                        (f"{runtime.SCHEDULING_OPTION}=LHS", f"put --{runtime.SCHEDULING_OPTION}=LHS in XLA_FLAGS"),
                        ("xla_no_such_option=1", "XLA refuses it .*xla_no_such_option"),
                        (f"{region}=maybe", f"XLA refuses it .*{region}")):
        monkeypatch.setenv(runtime.OPTIONS_ENV, text)
        with pytest.raises(ConfigError, match=r"^\$CDJAX_XLA_OPTIONS") as err:
            runtime.compiler_options()
        assert err.match(match) and "\n" not in str(err.value)


def test_a_program_scheduled_by_data_flow_that_would_not_fit_is_compiled_in_program_order(monkeypatch):
    """cdjax compiles its programs with the GPU's kernels scheduled by data flow (runtime.SCHEDULING, per program), and
    again in XLA's program order where the program's outputs and temporaries exceed the room beside the states: in a
    sweep (arms._compiled, noted on the arm; init and reset, whose outputs are the states, are never held to it; both
    programs cached, each picked by the room) and outside one (budget.compile_fitting). A user who names the option in
    XLA_FLAGS keeps it for every program, and nothing is compiled twice."""
    import types

    import jax
    import jax.numpy as jnp
    import numpy as np

    from cdjax import runtime
    from cdjax.runner import arms, budget

    seen = []
    original = jax.stages.Lowered.compile

    def spy(self, compiler_options=None, **kwargs):
        seen.append(dict(compiler_options or {}))
        return original(self, compiler_options, **kwargs)

    monkeypatch.setattr(jax.stages.Lowered, "compile", spy)
    monkeypatch.setattr(runtime, "_mode", None)
    monkeypatch.delenv(runtime.MODE_ENV, raising=False)
    monkeypatch.setenv("XLA_FLAGS", "")
    f, x = jax.jit(lambda x: jnp.tanh(x @ x.T) + 1.0), jnp.eye(64) * 0.5
    need = budget.program_bytes(original(f.lower(x)))  # on a CPU both schedulings take the same bytes
    assert need > 0 and budget.fits(original(f.lower(x)), need) and not budget.fits(original(f.lower(x)), need - 1)
    owner = object()
    roomy = types.SimpleNamespace(name="a", room=None, in_order={})
    wide = arms._compiled(roomy, "chunk", f.lower, x, owner=owner)
    assert seen == [runtime.SCHEDULING] and roomy.in_order == {}
    tight = types.SimpleNamespace(name="a", room=need - 1, in_order={})
    narrow = arms._compiled(tight, "chunk", f.lower, x, owner=owner)
    assert narrow is not wide and seen[1:] == [{}] and tight.in_order == {"chunk": (need, need)}
    again = types.SimpleNamespace(name="a", room=need - 1, in_order={})
    assert arms._compiled(again, "chunk", f.lower, x, owner=owner) is narrow and again.in_order == tight.in_order
    assert arms._compiled(roomy, "chunk", f.lower, x, owner=owner) is wide and len(seen) == 2  # both from the cache
    arms._compiled(tight, "init", f.lower, x, owner=owner)  # the states themselves: no room to keep to
    assert seen[2:] == [runtime.SCHEDULING] and "init" not in tight.in_order
    np.testing.assert_array_equal(wide(x), narrow(x))
    assert budget.compile_fitting(f.lower(x), room=need - 1)[1] and seen[3:] == [runtime.SCHEDULING, {}]
    assert not budget.compile_fitting(f.lower(x), room=need)[1] and seen[5:] == [runtime.SCHEDULING]
    # the user's choice in XLA_FLAGS: no per-program option, so no second program either
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=1 --xla_gpu_command_buffer_scheduling_mode=LHS")
    assert runtime.compiler_options() == {} and runtime.compiler_options("fast") == {"xla_gpu_enable_triton_gemm": False}
    program, in_order = budget.compile_fitting(f.lower(x), room=0)
    assert not in_order and seen[6:] == [{}]
    user = types.SimpleNamespace(name="a", room=0, in_order={})
    assert arms._compiled(user, "chunk", f.lower, x, owner=owner) is not wide and user.in_order == {}
    assert seen[7:] == [{}]