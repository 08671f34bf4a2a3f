"""The common yardstick of the observation-space experiment: held-out real trajectories per task, collected once.

    python -m experiments.paper_obs_space.yardstick [--tasks ant humanoid halfcheetah swimmer] [--out DIR]

writes DIR/<task>.npz (default experiments/paper_obs_space/yardstick/): TRAJECTORIES trajectories of STEPS steps
from the task's reset states under uniform random actions drawn from jax.random.key(SEED), a policy that no arm
trained and every arm's model can be scored on (the Mb-Mf phase of every arm with a model starts from the same
kind of data). The physics runs on through the task's terminations (see `collect`). The
`paper-*` presets name these files (Config.yardstick), so every update of every arm with a model logs
`model/yardstick_mse_k` and `model/yardstick_mse_50` (cdjax/agents/obs/yardstick.py). The files are kept in
git: collecting them again on another machine or jax version could change the trajectories in the last bits.
"""

from __future__ import annotations

import argparse
import datetime
import pathlib

HERE = pathlib.Path(__file__).resolve().parent
DIR = HERE / "yardstick"
TRAJECTORIES, STEPS, SEED = 16, 150, 0  # humanoid's 16 x 151 observations of 244 floats are ~2.4 MB


def path_of(task: str, root: pathlib.Path = DIR) -> pathlib.Path:
    return root / f"{task}.npz"


def collect(task: str, trajectories: int = TRAJECTORIES, steps: int = STEPS, seed: int = SEED):
    """(obs [N, T+1, O], action [N, T, A], length [N], reward [N, T], meta) of uniform random actions from reset
    states (the simulator's rewards are kept to check cdjax.envs.rewards against).

    The physics is followed through the task's terminations (no reset): a model predicts physics, and under
    random actions the humanoid falls within a few dozen steps, so most of its windows show a body falling and
    lying on the floor, states that PPO's episodes end at. A trajectory stops only where the physics turns
    non-finite (`length`). meta["terminated_at"] says where each trajectory's episode would have ended.
    """
    import jax
    import numpy as np

    from cdjax.envs import make_single_env, strong_types

    env = make_single_env(task)

    @jax.jit
    def play(key):
        key_reset, key_act = jax.random.split(key)

        def step(state, k):
            action = jax.random.uniform(k, (trajectories, env.action_size), minval=-1.0, maxval=1.0)
            state = strong_types(jax.vmap(env.step)(state, action))
            return state, (state.obs, action, state.reward, state.done > 0.5)

        state = strong_types(jax.vmap(env.reset)(jax.random.split(key_reset, trajectories)))
        _, (next_obs, action, reward, done) = jax.lax.scan(step, state, jax.random.split(key_act, steps))
        return state.obs, next_obs, action, reward, done

    first, next_obs, action, reward, done = (np.asarray(x) for x in play(jax.random.key(seed)))
    obs = np.concatenate([first[None], next_obs]).swapaxes(0, 1).astype(np.float32)  # [N, T+1, O]
    finite = np.isfinite(obs).all(-1)  # [N, T+1]
    length = np.where(finite.all(1), steps, finite.argmin(1) - 1).astype(np.int32)
    obs = np.where(finite[..., None], obs, 0.0)
    done = done.T  # [N, T]
    meta = {"env": task, "policy": f"uniform random actions in [-1, 1], jax.random.key({seed})", "seed": seed,
            "trajectories": trajectories, "steps": steps, "action_repeat": 1, "through_terminations": True,
            "terminated_at": [int(d.argmax()) + 1 if d.any() else None for d in done],
            "created": datetime.date.today().isoformat(), "jax": jax.__version__}
    return obs, action.swapaxes(0, 1), length, reward.T.astype(np.float32), meta


def main(argv=None) -> int:
    from experiments.paper_obs_space import TASKS

    p = argparse.ArgumentParser(prog="python -m experiments.paper_obs_space.yardstick", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tasks", nargs="+", default=list(TASKS))
    p.add_argument("--out", type=pathlib.Path, default=DIR)
    p.add_argument("--trajectories", type=int, default=TRAJECTORIES)
    p.add_argument("--steps", type=int, default=STEPS)
    p.add_argument("--seed", type=int, default=SEED)
    args = p.parse_args(argv)
    import experiments  # noqa: F401  (cdjax's XLA flags before anything runs)
    from cdjax.agents.obs import yardstick

    for task in args.tasks:
        obs, action, length, reward, meta = collect(task, args.trajectories, args.steps, args.seed)
        path = yardstick.save(path_of(task, args.out), obs, action, length, meta, reward=reward)
        print(f"{path}: {obs.shape[0]} trajectories, {action.shape[1]} steps, lengths {sorted(set(length.tolist()))}, "
              f"{path.stat().st_size / 1e6:.2f} MB", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
