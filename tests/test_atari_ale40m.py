"""The 40M-frame ALE tier's way across machines (experiments/atari/ale40m.py), at cpu-minatar's tiny sizes (the
sweep's programs are test_atari_cli's cut-and-resume sweep's, from the compilation cache): a sweep cut after its
first chunk, packed into parts under a size limit, brought back a call's worth at a time, unpacked elsewhere and
resumed by its unit's own command is the uninterrupted run (every leaf of the final states; the logged rows, of which
the packs carry every n-th update's);
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
    parts = ale40m.pack(cut, tmp_path / "outbox", PIECE, part_bytes=part, logs=[unit_log], every=2)
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
    # the metrics travel thinned to every 2nd update (`every`), the same rows wherever the run is cut
    rows, whole = logged_rows(run), logged_rows(straight)
    assert rows == [r for r in whole if r["update"] > 4 or r["update"] % 2 == 0] and len(whole) == 2 * 8
    _leaves_equal(run, straight)
    again = ale40m.pack(run, tmp_path / "outbox2", PIECE, every=2)
    assert [p.name for p in again] == [f"{PIECE}.u000008.00-of-01"]
    ale40m.unpack(again, tmp_path / "back" / "breakout")
    assert logged_rows(tmp_path / "back" / "breakout") == [r for r in whole if r["update"] % 2 == 0]
    # a call whose files were lost: they are sent again
    assert sorted(p.name for p in ale40m.send(tmp_path / "outbox", tmp_path / "lost", files=0, again=True)) == \
        sorted(p.name for p in parts)


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

    # the device side (launch.start faked): pieces started with their shares of GPUs and cores as their parts come in,
    # a call at a time (each call's carry replaces the carried folder there)
    started, said = [], []

    def fake_start(experiment, units, work, time_limit=None, gpu=None, min_s=0, args=()):
        work.mkdir(parents=True, exist_ok=True)
        (work / "queue.json").write_text(json.dumps({"units": list(units)}))
        started.append((units[0], gpu, time_limit, list(args)))
        return True

    monkeypatch.setattr(launch, "start", fake_start)
    work, pieces = tmp_path / "work", [PIECE, "ale40m-breakout-a2c"]
    size = 512 + -(-60_000 // 512) * 512
    # the first call: the loan's first two parts (within its room, in the pieces' order) and the MANIFEST
    staged = ale40m.stage(pieces, store, into, room=1024 + 2 * size, first=True, say=lambda *_: None)
    assert [p.name for p in staged] == [p.name for p in small[:2]]
    assert json.loads((into / ale40m.MANIFEST).read_text()) == {PIECE: 8}
    ale40m.start(pieces, work, into, 1000, 2, range(8), say=said.append)
    # a2c has no state in the store: it starts from nothing; a2c-cd, done to 8 updates, waits for its parts
    assert [s[:2] for s in started] == [("ale40m-breakout-a2c", 1)]
    assert started[0][2] == 1000 - ale40m.EVAL_S - ale40m.PACK_S
    assert started[0][3] == ["--end", "1000", "--param", "cpus=4-7", "--param", f"outbox={work / 'outbox'}"]
    assert said[-2] == f"{PIECE}: done to 8 updates, 2 of its {len(small)} parts at 8 updates here; it starts once " \
        "they are all carried in"
    # the next call: the next two parts, none of the first two again
    staged = ale40m.stage(pieces, store, into, room=1024 + 2 * size, say=lambda *_: None)
    assert [p.name for p in staged] == [p.name for p in small[2:4]]
    ale40m.start(pieces, work, into, 900, 2, range(8), say=said.append)
    assert len(started) == 1 and f"4 of its {len(small)} parts" in said[-2] and "started earlier" in said[-1]
    # a call with room for the rest: the set is whole on the device, unpacked and started
    staged = ale40m.stage(pieces, store, into, room=10**9, say=lambda *_: None)
    assert sorted(p.name for p in staged) == [p.name for p in small[4:]]
    ale40m.start(pieces, work, into, 800, 2, range(8), say=said.append)
    assert [s[:2] for s in started] == [("ale40m-breakout-a2c", 1), (PIECE, 0)]
    assert ale40m.updates_done(work / PIECE / PIECE / "breakout") == 8
    # a new loan stages from the first part again
    assert [p.name for p in ale40m.stage(pieces, store, into, room=10**9, first=True, say=lambda *_: None)] == \
        [p.name for p in small]


def _piece_dir(path, game, arm, ret):
    """A piece's run directory (one arm, 2 seeds, 4 updates) whose seed s returns ret + s in training and evaluation."""
    path.mkdir(parents=True)
    (path / "run.json").write_text(json.dumps({
        "seeds": 2, "base_config": {"env": f"ale-{game}"}, "arms": [{"name": arm, "hp_labels": ["alpha=1.0"],
                                                                    "hparams": [{"lr": 7e-4}], "num_updates": 4}]}))
    (path / "metrics.jsonl").write_text("".join(
        json.dumps({"arm": arm, "hp": "alpha=1.0", "seed": s, "update": u, "env_steps": 80 * u, "wall_s": float(u),
                    "episode/return": ret + s}) + "\n" for s in range(2) for u in range(1, 5)))
    (path / "eval.jsonl").write_text("".join(
        json.dumps({"arm": arm, "hp": "alpha=1.0", "seed": s, "update": 4, "env_steps": 320, "episodes": 100,
                    "deterministic": False, "eval/return": ret + s}) + "\n" for s in range(2)))
    (path / "log.txt").write_text(f"{arm}'s log\n")
    (path / "logs").mkdir()
    (path / "logs" / "unit.u000004.log").write_text(f"{arm}'s unit\n")
    return path


def test_a_games_two_pieces_are_joined_into_the_run_directory_the_report_and_aggregate_read(tmp_path, monkeypatch):
    from experiments.atari import aggregate

    store = tmp_path / "store"
    for game, base in (("breakout", 10.0), ("seaquest", 100.0)):
        for arm, ret in (("a2c", base), ("a2c-cd", base + 1)):
            _piece_dir(store / "runs" / f"ale40m-{game}-{arm}", game, arm, ret)
    written = ale40m.merge(store, tmp_path / "data" / "ale-10m", say=lambda *_: None)
    assert [p.name for p in written] == ["breakout", "seaquest"]  # mspacman and frostbite have no pieces kept
    game = written[0]
    assert (game / "log-a2c-cd.txt").read_text() == "a2c-cd's log\n" and (game / "metrics.jsonl.xz").exists()
    assert (game / "logs-a2c" / "unit.u000004.log").read_text() == "a2c's unit\n"
    data = report.load(game)
    assert set(data["arms"]) == {"a2c", "a2c-cd"} and data["game"] == "ale-breakout"
    for arm, ret in (("a2c", 10.0), ("a2c-cd", 11.0)):
        scores = report.seed_scores(data, arm)
        np.testing.assert_allclose(scores["eval"], [ret, ret + 1])
        np.testing.assert_allclose(scores["final"], [ret, ret + 1])
    monkeypatch.setattr(aggregate, "DATA", tmp_path / "data")
    aggregate.main(["--tier", "ale", "--data", "ale-10m", "--out", str(tmp_path / "agg"), "--bootstrap-reps", "20"])
    saved = json.loads((tmp_path / "agg" / "aggregate.json").read_text())
    assert set(saved["random"]) == {"breakout", "seaquest"}
    # a2c-cd's seeds score 11 and 12 against a2c's 10 and 11 (+ 90 on seaquest): 3 of 4 pairs higher, the tie half
    assert saved["aggregate"]["eval"]["poi_per_game"] == {"breakout": 0.875, "seaquest": 0.875}
