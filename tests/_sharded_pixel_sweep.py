"""Run by test_sweep.py in a fresh process with 2 forced CPU devices (XLA_FLAGS set by the caller):
`python _sharded_pixel_sweep.py DIR`. The pixel sweep's runs split over the devices ("local": each device runs its own
runs) from the initial state the caller wrote (DIR/fresh.npz: the stacked leaves of 4 runs, keys as key data); it
prints its metrics and the compiled chunk's collectives, and checkpoints its state after the first chunk in DIR/ckpt
for the caller to restore on one device.

Compiling is most of the time on a CPU, so this process compiles the two-device chunk (and the contrast's two small
chunks, from shapes) and nothing else: the caller inits the runs and runs them on one device with the programs it
shares with tests/test_pixel_model.py."""

import json
import os
import pathlib
import re
import sys

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).parent))
from _shared import PIXEL_HP, PIXEL_TINY

from cdjax import io, runtime
from cdjax.agents import pixel
from cdjax.agents.pixel.learner import PixelLearner
from cdjax.agents.pixel.synthetic import SyntheticWorld
from cdjax.sweep import make_sweep

assert jax.device_count() == 2, jax.devices()
runtime.configure(cache_dir=os.environ.get(runtime.CACHE_ENV, pathlib.Path(__file__).resolve().parents[1] / ".jax_cache"))
DIR = pathlib.Path(sys.argv[1])
HPS = [PIXEL_HP, PIXEL_HP.replace(lr=1e-3)]  # the caller's
LENGTH = 2  # updates per chunk
NAMES = ("loss/total", "model/elbo_per_frame", "loss/imitation", "loss/consistency", "heldout/loglik_k", "grad/norm")


def collectives(compiled) -> dict:
    text = compiled.as_text()
    return {op: len(re.findall(re.escape(op) + r"[.(\s-]", text))
            for op in ("all-gather", "all-reduce", "all-to-all", "collective-permute")}


def scalars(metrics) -> dict:
    return {n: np.asarray(metrics[n]).tolist() for n in NAMES}


trainer = pixel.trainer_of(PixelLearner(PIXEL_TINY, world=SyntheticWorld(PIXEL_TINY)))
two = make_sweep(trainer)  # the pixel trainer's own split ("local") over both devices
keys, hps = two.grid(seed=3, num_seeds=2, hps=HPS)  # 4 runs: 2 per device
shapes = jax.eval_shape(jax.vmap(trainer.init), keys, hps)
with np.load(DIR / "fresh.npz") as saved:
    leaves = [jax.random.wrap_key_data(saved[str(i)]) if jnp.issubdtype(s.dtype, jax.dtypes.prng_key) else saved[str(i)]
              for i, s in enumerate(jax.tree.leaves(shapes))]
state, hps = jax.device_put((jax.tree.unflatten(jax.tree.structure(shapes), leaves), hps), two.sharding)
devices = sorted({d.id for x in jax.tree.leaves(state.params) for d in x.sharding.device_set})
chunk = two.lower_chunk(state, hps, LENGTH).compile()
state, first = chunk(state, hps, jnp.int32(LENGTH))
ckpt = io.Checkpoints(DIR / "ckpt")
ckpt.save(LENGTH, state, {"updates": LENGTH}, keep=trainer.saved_leaves())
ckpt.wait()
ckpt.close()
_, later = chunk(state, hps, jnp.int32(LENGTH))


# For contrast, a program XLA's partitioner does all-gather: one convolution with per-run kernels, vmapped over the
# runs (the pixel model's encoder and decoder layers are such convolutions), split either way; cheap to compile.
class ConvRuns:
    def init(self, key, hp):
        return {"w": jax.random.normal(key, (4, 4, 12, 4)), "x": jax.random.normal(key, (2, 16, 16, 12))}

    def update(self, state, hp):
        def loss(w):
            y = jax.lax.conv_general_dilated(state["x"], w, (2, 2), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC"))
            return (y ** 2).mean()

        value, grad = jax.value_and_grad(loss)(state["w"])
        return dict(state, w=state["w"] - hp.lr * grad), {"loss": value}


contrast = {}
for split in ("partition", "local"):
    sweep = make_sweep(ConvRuns(), split=split)
    conv_keys, conv_hps = sweep.grid(seed=0, num_seeds=4, hps=[PIXEL_HP])
    conv_state = jax.tree.map(lambda x, on=sweep.sharding: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=on),
                              jax.eval_shape(sweep.init, conv_keys, conv_hps))
    contrast[split] = collectives(sweep.lower_chunk(conv_state, conv_hps, LENGTH).compile())

print(json.dumps({
    "split": two.split, "devices": devices,
    "collectives": collectives(chunk), "contrast": contrast, "first": scalars(first), "later": scalars(later)}))
