"""Run by test_multihost.py as one of two processes of one machine (argv: coordinator port, process id, directory),
each with one CPU device: the parts of a sweep that several processes must build apart, checked without a sweep's
compilations. It prints one JSON line:
- model_processes: the processes whose devices hold an MJX environment's model as this process built it (MJX puts a
  model on jax.devices()[0], process 0's device, unless cdjax.envs names this process's own);
- saved: the newest complete checkpoint of two arms that saved the same step at once (orbax names its barriers by the
  step: without names of their own, the second arm's barrier would find the first one's "already ongoing")."""

import json
import pathlib
import sys

port, process, root = int(sys.argv[1]), int(sys.argv[2]), pathlib.Path(sys.argv[3])

from cdjax import multihost  # noqa: E402

multihost.initialize(f"127.0.0.1:{port}", 2, process)

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.sharding import Mesh, NamedSharding, PartitionSpec  # noqa: E402

from cdjax import envs, io  # noqa: E402

env = envs.make_single_env("inverted_pendulum")
model_processes = sorted({d.process_index for leaf in jax.tree.leaves(env.sys) if isinstance(leaf, jax.Array)
                          for d in leaf.devices()})

mesh = Mesh(np.array(jax.devices()), ("runs",))
runs = PartitionSpec("runs")


def chunk(x):  # each device's runs: a loop as long as their first number says (process 1's: a few seconds)
    return jax.lax.fori_loop(0, x[0, 0].astype(jnp.int32), lambda i, y: jnp.sin(y), x)


# the state a chunk leaves, still being computed on process 1 when both processes start saving it, as in a sweep
# where one process is behind: process 0's two saves then wait in their barriers together
lengths = multihost.put(np.array([[0.0] * 4, [3e7] * 4], np.float32), NamedSharding(mesh, runs))
state = {"w": jax.jit(jax.shard_map(chunk, mesh=mesh, in_specs=runs, out_specs=runs))(lengths)}
arms = [io.Checkpoints(root / "checkpoints" / arm) for arm in ("mbmf", "cd")]
for ckpt in arms:  # both saves under way at once, as a round of chunks leaves them
    ckpt.save(1, state, {"updates": 1})
for ckpt in arms:
    ckpt.wait()
print(json.dumps({"model_processes": model_processes, "saved": [ckpt.latest() for ckpt in arms]}), flush=True)
multihost.ending(0)
