"""The 40M-frame ALE tier's way across machines (experiments/atari/ale40m.py), at cpu-minatar's tiny sizes (the
sweep's programs are test_atari_cli's cut-and-resume sweep's, from the compilation cache): a sweep cut after its
first chunk, packed into parts under a size limit, brought back a call's worth at a time, unpacked elsewhere and
resumed by its unit's own command is the uninterrupted run (every logged row and every leaf of the final states);
the store here keeps a piece's newest whole set of parts, stages them for the next machine within a call's room, and
joins a game's two pieces into one run directory that the report reads; `start` unpacks and starts what was carried
in, lets a piece whose parts are not all there wait, and never starts afresh a piece that has done updates."""

from __future__ import annotations

import dataclasses
import json
import lzma
import random
import shutil

import jax
import numpy as np
import pytest

from cdjax.cli import main
from cdjax.runner import Interrupted, restore_arms, resume_spec, run_sweep
from experiments import launch
from experiments.atari import ale40m, report
from experiments.atari.units import UNITS

from _shared import logged_rows

# test_atari_cli's cut-and-resume sweep: the a2c-cd arm at cpu-minatar's sizes, 2 seeds, 2 chunks of 4 updates
ARGS = ["sweep", "--setting", "atari", "--preset", "cpu-minatar", "--arms", "a2c-cd", "--steps", str(8 * 128),
        "--chunk-updates", "4", "--no-final-eval", "--no-progress"]
PIECE = "ale40m-breakout-a2c-cd"  # a piece's name for the parts (the run is MinAtar Breakout's)


@pytest.fixture(scope="module")
def straight(tmp_path_factory):
    out = tmp_path_factory.mktemp("ale40m") / "straight"
    main(ARGS + ["--out", str(out)])
    return out


def _leaves_equal(a_dir, b_dir):
    for a, b in zip(restore_arms(a_dir)[1], restore_arms(b_dir)[1]):
        assert a.updates == b.updates == 8
        for x, y in zip(jax.tree.leaves(a.state), jax.tree.leaves(b.state)):
            x, y = (jax.random.key_data(v) if jax.dtypes.issubdtype(v.dtype, jax.dtypes.prng_key) else v
                    for v in (x, y))
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_a_run_cut_packed_brought_back_unpacked_elsewhere_and_resumed_is_the_uncut_run(straight, tmp_path):
    cut = tmp_path / "here" / "breakout"
    with pytest.raises(Interrupted):
        run_sweep(dataclasses.replace(resume_spec(straight, progress=False), out=cut),
                  after_chunk=lambda chunks, updates: chunks >= 1)
    unit_log = tmp_path / "unit.log"
    unit_log.write_text("the unit's own output\n")
    part = 40_000
    parts = ale40m.pack(cut, tmp_path / "outbox", PIECE, part_bytes=part, logs=[unit_log])
    assert len(parts) >= 3 and all(p.stat().st_size <= part for p in parts)
    assert [p.name for p in parts] == [f"{PIECE}.u000004.{i:02d}-of-{len(parts):02d}" for i in range(len(parts))]

    # brought back a call at a time: at most 2 files and 100 kB a call
    calls, got = 0, tmp_path / "files_at"
    while True:
        left = ale40m.send(tmp_path / "outbox", got / str(calls), files=2, limit=100_000)
        sent = list((got / str(calls)).iterdir())
        assert 0 < len(sent) <= 2 and sum(p.stat().st_size for p in sent) <= 100_000
        calls += 1
        if not left:
            break
    assert calls == -(-len(parts) // 2)
    back = [p for d in got.iterdir() for p in d.iterdir()]
    random.Random(0).shuffle(back)
    with pytest.raises(lzma.LZMAError):  # a set with a part missing does not unpack, and nothing is written
        ale40m.unpack(back[1:], tmp_path / "partial")
    assert not (tmp_path / "partial").exists()

    u = UNITS[PIECE]
    ctx = u.context(tmp_path / "there", 600, 900)
    run = ctx.out / "breakout"
    assert ale40m.unpack(back, run) == 4
    assert sorted(p.name for p in (run / "checkpoints" / "a2c-cd").iterdir()) == ["4"]  # the latest checkpoint alone
    assert (run / "logs" / "unit.u000004.log").read_text() == "the unit's own output\n"
    sweep, evaluate, pack = u.steps(ctx)
    assert sweep.when(ctx) and not evaluate.when(ctx)
    main(list(sweep.argv[sweep.argv.index("cdjax.cli") + 1:]))  # the unit's own resume
    assert ale40m.complete(run) and not sweep.when(ctx) and evaluate.when(ctx)
    rows = logged_rows(run)
    assert rows == logged_rows(straight) and len(rows) == 2 * 8
    _leaves_equal(run, straight)


def test_the_store_keeps_whole_sets_stages_them_within_a_calls_room_and_start_waits_for_them(straight, tmp_path,
                                                                                           monkeypatch):
    store, into = tmp_path / "store", tmp_path / "repo" / ".ale40m-in"
    small = ale40m.pack(straight, tmp_path / "a", PIECE, part_bytes=60_000)
    first, rest = small[:1], small[1:]
    brought = tmp_path / "call1"
    brought.mkdir()
    for p in first:
        shutil.copyfile(p, brought / p.name)
    assert ale40m.absorb(brought, store, say=lambda *_: None) == {}  # a set in part is not kept yet
    assert ale40m.progress(store)[PIECE]["updates"] == 0
    for p in rest:
        shutil.copyfile(p, brought / p.name)
    assert ale40m.absorb(brought, store, say=lambda *_: None) == {PIECE: 8}
    info = ale40m.progress(store)[PIECE]
    assert info["updates"] == 8 and info["parts"] == len(small) and not info["evaluated"]
    assert ale40m.updates_done(store / "runs" / PIECE) == 8

    # staged for the next machine within each call's room, the pieces' parts in order, none twice in a loan
    size = 512 + -(-60_000 // 512) * 512
    staged = ale40m.stage([PIECE, "ale40m-breakout-a2c"], store, into, room=1024 + 2 * size, first=True,
                          say=lambda *_: None)
    assert [p.name for p in staged] == [p.name for p in small[:2]]
    assert json.loads((into / ale40m.MANIFEST).read_text()) == {PIECE: 8}
    staged += ale40m.stage([PIECE, "ale40m-breakout-a2c"], store, into, room=1024 + 2 * size, say=lambda *_: None)
    assert sorted(p.name for p in staged) == sorted(p.name for p in small)[:4]

    # the device side: pieces started with their shares; one whose parts are not all here waits, never afresh
    started = []

    def fake_start(experiment, units, work, time_limit=None, gpu=None, min_s=0, args=()):
        work.mkdir(parents=True, exist_ok=True)
        (work / "queue.json").write_text(json.dumps({"units": list(units)}))
        started.append((units[0], gpu, time_limit, list(args)))
        return True

    monkeypatch.setattr(launch, "start", fake_start)
    work = tmp_path / "work"
    said = []
    ale40m.start([PIECE, "ale40m-breakout-a2c"], work, into, 1000, 2, range(8), say=said.append)
    # a2c has no state in the store: it starts from nothing; a2c-cd waits for its last part
    assert [s[:2] for s in started] == [("ale40m-breakout-a2c", 1)]
    assert started[0][2] == 1000 - ale40m.EVAL_S - ale40m.PACK_S
    assert started[0][3] == ["--end", "1000", "--param", "cpus=4-7", "--param", f"outbox={work / 'outbox'}"]
    assert any("starts once they are all carried in" in s for s in said)
    for p in small:  # the rest carried in by a later call
        shutil.copyfile(p, into / p.name)
    ale40m.start([PIECE, "ale40m-breakout-a2c"], work, into, 900, 2, range(8), say=said.append)
    assert [s[:2] for s in started] == [("ale40m-breakout-a2c", 1), (PIECE, 0)]
    assert ale40m.updates_done(work / PIECE / PIECE / "breakout") == 8
    assert any("started earlier" in s for s in said)


def test_a_games_two_pieces_are_joined_into_the_run_directory_the_report_reads(tmp_path):
    runs = []
    for arm, ret in (("a2c", 10.0), ("a2c-cd", 12.0)):
        run = tmp_path / arm
        run.mkdir()
        (run / "run.json").write_text(json.dumps({
            "seeds": 2, "base_config": {"env": "ale-breakout"}, "arms": [{"name": arm, "hp_labels": ["alpha=1.0"],
                                                                         "num_updates": 4}]}))
        (run / "metrics.jsonl").write_text("".join(
            json.dumps({"arm": arm, "hp": "alpha=1.0", "seed": s, "update": u, "env_steps": 80 * u,
                        "wall_s": float(u), "episode/return": ret + s}) + "\n" for s in range(2) for u in range(1, 5)))
        (run / "eval.jsonl").write_text("".join(
            json.dumps({"arm": arm, "hp": "alpha=1.0", "seed": s, "update": 4, "env_steps": 320, "episodes": 100,
                        "deterministic": False, "eval/return": ret + s}) + "\n" for s in range(2)))
        (run / "log.txt").write_text(f"{arm}'s log\n")
        runs.append(run)
    game = ale40m.merge_game(runs, tmp_path / "breakout")
    assert (game / "log-a2c-cd.txt").read_text() == "a2c-cd's log\n" and (game / "metrics.jsonl.xz").exists()
    data = report.load(game)
    assert set(data["arms"]) == {"a2c", "a2c-cd"} and data["game"] == "ale-breakout"
    for arm, ret in (("a2c", 10.0), ("a2c-cd", 12.0)):
        scores = report.seed_scores(data, arm)
        np.testing.assert_allclose(scores["eval"], [ret, ret + 1])
        np.testing.assert_allclose(scores["final"], [ret, ret + 1])
