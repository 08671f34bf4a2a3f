"""Run by test_sweep.py in a fresh process with 2 forced CPU devices (XLA_FLAGS set by the caller): the sharded sweep
of 6 runs of POINT, its metrics and its runs' keys; the caller runs each run alone on its one device (a program
compiled for 1 device and for 2 have different compilation-cache keys: there it is the one tests/test_train.py
compiles). The environments' state carries one more leaf, of size 0 (as MJX's data does: no mocap bodies, no
equality constraints), which changes no number; the caller checks that its sharding follows the run axis."""

import json
import re
import sys

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(__import__("pathlib").Path(__file__).parent))
from _shared import POINT  # noqa: E402
from cdjax import HParams, make_agent  # noqa: E402
from cdjax.sweep import make_sweep, unpad  # noqa: E402



class WithEmptyLeaf:
    """An agent whose environments' state holds a leaf of size 0 beside its own."""

    def __init__(self, agent):
        self.agent = agent

    def __getattr__(self, name):
        return getattr(self.agent, name)

    def reset(self, key):
        return self.agent.reset(key), jnp.zeros((0, 3))

    def init_from(self, key, hp, env_state):
        return self.agent.init_from(key, hp, env_state[0]), env_state[1]

    def update(self, state, hp):
        inner, metrics = self.agent.update(state[0], hp)
        return (inner, state[1]), metrics


def specs(tree) -> list[list]:
    """The distinct partition specs of the leaves of `tree` (each as the list of its axes' mesh names)."""
    return sorted(map(list, {tuple(leaf.sharding.spec) for leaf in jax.tree.leaves(tree)}))


assert jax.device_count() == 2, jax.devices()
sweep = make_sweep(WithEmptyLeaf(make_agent(POINT)))
hps = [HParams(alpha=0.0), HParams(alpha=1.0)]
keys, stacked = sweep.grid(seed=7, num_seeds=3, hps=hps)  # 6 runs -> even, no padding on 2 devices
state = sweep.init(keys, stacked)
init_specs = specs(state)
# One sharded program (a chunk of 1 update), compiled once and called UPDATES times: compiling is most of this
# process's time, and the collectives below are counted in the same program.
UPDATES = 6  # as tests/test_train.py runs POINT alone
compiled = sweep.lower(state, stacked, 1).compile()
chunks = []
for _ in range(UPDATES):
    state, metrics = compiled(state, stacked)
    chunks.append(np.asarray(metrics["loss/total"]))
devices_used = sorted({d.id for leaf in jax.tree.leaves(state[0].params) for d in leaf.sharding.device_set})
spec = str(jax.tree.leaves(state[0].params)[0].sharding.spec)
total = np.concatenate(chunks, axis=1)  # [R, UPDATES]
# padding: 3 runs on 2 devices -> 4, and unpad drops the extra one
keys3, hps3 = sweep.grid(seed=7, num_seeds=3, hps=hps[:1])
collectives = {op: len(re.findall(re.escape(op) + r"[.(\s-]", compiled.as_text()))
               for op in ("all-gather", "all-reduce", "all-to-all", "collective-permute")}
print(json.dumps({"collectives": collectives, "devices_used": devices_used, "spec": spec, "sharded": total.tolist(),
                  "specs": {"init": init_specs, "chunk": specs(state), "metrics": specs(metrics)},
                  "keys": np.asarray(jax.random.key_data(keys)).tolist(), "padded_runs": int(keys3.shape[0]),
                  "unpadded_runs": int(unpad(keys3, 3).shape[0])}))
