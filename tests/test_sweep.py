"""Sweeps: runs sharded over devices (2 forced CPU devices in a subprocess) equal each run alone."""

import json
import os
import pathlib
import subprocess
import sys

import numpy as np
import pytest


def test_runs_sharded_over_two_devices_equal_runs_alone():
    """6 runs of POINT (3 seeds x alpha 0 and 1) sharded over 2 forced CPU devices (a subprocess), 6 updates: each
    run's losses equal the run's alone, here on one device (the single-run program tests/test_train.py compiles),
    and every leaf of the state, one of size 0 among them, stays on the run axis."""
    import jax
    from _shared import POINT

    from cdjax import HParams, make_train

    env = dict(os.environ, XLA_FLAGS=f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2",
               JAX_PLATFORMS="cpu")
    script = pathlib.Path(__file__).with_name("_sharded_sweep.py")
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["devices_used"] == [0, 1]
    assert "runs" in out["spec"]
    # every leaf of the state (the one of size 0 too) and of the metrics lies on the run axis, after init and after
    # the chunks: the next program, compiled for the run axis, would refuse another sharding
    assert out["specs"] == {"init": [["runs"]], "chunk": [["runs"]], "metrics": [["runs"]]}, out["specs"]
    sharded = np.array(out["sharded"])  # [runs, updates]
    train = jax.jit(make_train(POINT.replace(num_updates=sharded.shape[1])))
    keys = jax.random.wrap_key_data(np.array(out["keys"], np.uint32))
    alone = [np.asarray(train(keys[r], HParams(alpha=[0.0, 1.0][r // 3]))[1]["loss/total"]) for r in range(6)]
    np.testing.assert_allclose(sharded, np.array(alone), rtol=2e-5, atol=1e-6)
    assert out["padded_runs"] == 4 and out["unpadded_runs"] == 3
    # each device runs its own runs: the point-mass trainer's compiled chunk holds no collective (the pixel
    # setting's vmapped convolutions would be all-gathered by the partitioner: its trainer splits "local"ly, below)
    assert out["collectives"] == {"all-gather": 0, "all-reduce": 0, "all-to-all": 0, "collective-permute": 0}


def test_pixel_runs_split_over_two_devices_hold_no_collective_and_equal_one_device(tmp_path):
    """The pixel sweep splits its runs "local"ly (a shard_map of the update programs): on 2 forced CPU devices its
    compiled chunk holds no collective (XLA's partitioner, for contrast, all-gathers a convolution with per-run
    kernels under the runs' vmap, which the local split does not); its 4 runs' metrics equal each run's on one device
    (this process: the model tests/test_pixel_model.py compiles); a checkpoint of the two-device runs, restored
    here on one device, continues as they do. The observation-space trainers (MJX's init crashed XLA:GPU's compiler
    under shard_map) keep the partitioner's split."""
    import jax
    from _shared import PENDULUM, PIXEL_HP, POINT, host_trainer, pixel_programs

    from cdjax import io
    from cdjax.agents import pixel
    from cdjax.sweep import make_sweep

    assert make_sweep(host_trainer(POINT)).split == make_sweep(host_trainer(PENDULUM)).split == "partition"
    learner, init, _, _ = pixel_programs()
    # its own jit of the update (test_pixel_model counts its update's traces; the sweep's keys and the restored state
    # come committed to the device, another trace), compiled as that one: the persistent cache holds the program
    update = jax.jit(learner.update)
    trainer = pixel.trainer_of(learner)
    hps = [PIXEL_HP, PIXEL_HP.replace(lr=1e-3)]  # run r: hps[r // 2], seeds' keys as the sweep's grid gives them
    keys, _ = make_sweep(trainer).grid(seed=3, num_seeds=2, hps=hps)
    fresh = [init(keys[r], hps[r // 2]) for r in range(4)]
    leaves = [np.stack([jax.random.key_data(x) if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key) else x
                        for x in run]) for run in zip(*(jax.tree.leaves(f) for f in fresh))]
    np.savez(tmp_path / "fresh.npz", **{str(i): x for i, x in enumerate(leaves)})

    env = dict(os.environ, XLA_FLAGS=f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2",
               JAX_PLATFORMS="cpu")
    script = pathlib.Path(__file__).with_name("_sharded_pixel_sweep.py")
    proc = subprocess.run([sys.executable, str(script), str(tmp_path)], check=False, capture_output=True, text=True,
                          env=env, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["split"] == "local" and out["devices"] == [0, 1]
    none = {"all-gather": 0, "all-reduce": 0, "all-to-all": 0, "collective-permute": 0}
    assert out["collectives"] == none
    assert out["contrast"]["partition"]["all-gather"] > 0 and out["contrast"]["local"] == none, out["contrast"]

    def updates(states, n):  # each run alone on this process's one device: (states, metrics {name: [R, n]})
        rows = []
        for r in range(4):
            metrics = []
            for _ in range(n):
                states[r], m = update(states[r], hps[r // 2])
                metrics.append(m)
            rows.append(metrics)
        return states, {name: [[float(m[name]) for m in row] for row in rows] for name in out["first"]}

    _, first = updates(list(fresh), 2)
    stacked = jax.tree.map(lambda *x: jax.numpy.stack(x), *fresh)  # the template: shapes and the unsaved data
    ckpt = io.Checkpoints(tmp_path / "ckpt")
    restored, progress = ckpt.restore(stacked, set_aside=False)
    ckpt.close()
    assert progress["updates"] == 2
    _, later = updates([jax.tree.map(lambda x, r=r: x[r], restored) for r in range(4)], 2)
    # two runs' vmapped (grouped) convolutions and each run's own may round apart in the last places
    for name in first:
        assert np.isfinite(first[name]).all() and later[name] != first[name], name
        np.testing.assert_allclose(out["first"][name], first[name], rtol=1e-6, err_msg=name)
        np.testing.assert_allclose(out["later"][name], later[name], rtol=1e-6, err_msg=name)


def test_a_checkpoint_restores_on_another_device_count(tmp_path):
    """A sweep's state is padded to a multiple of the device count by repeating its last run; a checkpoint saved
    with one padding restores into a sweep padded otherwise (trained on 4 GPUs, evaluated on 1): the real runs
    are kept and the padding repeats the last of them. Only the padding may differ: a checkpoint that does not
    record its real runs, or records more than the other padding holds, is refused (never re-padded into a
    fabricated run)."""
    import jax.numpy as jnp

    from cdjax import io

    real = np.arange(3 * 2, dtype=np.float32).reshape(3, 2)
    padded = np.concatenate([real, real[-1:]])  # 3 runs padded to 4 (2 devices)
    saved = {"w": jnp.asarray(padded), "step": jnp.full((4,), 5, jnp.int32)}
    ckpt = io.Checkpoints(tmp_path / "arm")
    ckpt.save(5, saved, {"updates": 5, "run": {"num_runs": 3}})
    ckpt.save(6, saved, {"updates": 6})  # no record of its real runs
    ckpt.wait()
    for runs in (3, 5):  # one device (no padding), and a padding to 5
        like = {"w": jnp.zeros((runs, 2), jnp.float32), "step": jnp.zeros((runs,), jnp.int32)}
        with pytest.raises(io.CheckpointMismatch, match=f"arm/6 does not belong to the run asked for: it holds 4 runs "
                                                        f"where this run has {runs}"):
            ckpt.restore(like, set_aside=False)
        ckpt.set_aside(6, "test")
        state, progress = ckpt.restore(like, set_aside=False)
        want = np.concatenate([real, np.repeat(real[-1:], runs - 3, axis=0)])
        np.testing.assert_array_equal(np.asarray(state["w"]), want)
        np.testing.assert_array_equal(np.asarray(state["step"]), np.full(runs, 5))
        assert progress["updates"] == 5
        ckpt.save(6, saved, {"updates": 6})
        ckpt.wait()
    like = {"w": jnp.zeros((2, 2), jnp.float32), "step": jnp.zeros((2,), jnp.int32)}  # fewer runs than recorded
    ckpt.set_aside(6, "test")
    with pytest.raises(io.CheckpointMismatch, match="it holds 4 runs where this run has 2"):
        ckpt.restore(like, set_aside=False)
    ckpt.close()
