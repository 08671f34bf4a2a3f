"""cdjax.envs.resume: which leaves of an env state a resumed run needs; restoring only those continues an MJX
episode bit for bit."""

import jax
import jax.numpy as jnp
import numpy as np

from cdjax.envs import BatchedEnv, make_single_env
from cdjax.envs.point import PointMass
from cdjax.envs.resume import leaf_dependencies, needed_leaves, scan_split
from cdjax.io.checkpoints import named_leaves


def test_dependencies_follow_loops_and_branches_leaf_by_leaf():
    def f(a, b, c, d):
        loop = jax.lax.fori_loop(0, 3, lambda i, x: x * a, b)  # a while loop: depends on a, b
        scanned, _ = jax.lax.scan(lambda x, y: (x + y, None), c, jnp.arange(3.0))  # depends on c only
        branch = jax.lax.cond(d > 0, lambda: a, lambda: c)  # the predicate and both branches
        return loop, scanned, branch, d * 0 + 1  # the last depends on d (no simplification by value)

    masks = leaf_dependencies(f, *(jnp.float32(1.0),) * 4)
    assert masks == [0b0011, 0b0100, 0b1101, 0b1000]


def test_scan_split_from_shapes_equals_the_parameters():
    # JAX releases rename the scan's parameters (jax 0.11 has no num_consts): the split read from the shapes
    # must equal the one the parameters give, with consts, carries and scanned inputs of clashing shapes.
    def f(c, h, xs, ys):
        def body(carry, x):
            (a, b), (xt, yt) = carry, x
            return (a + c * xt, b * ys[0].sum()), (xt * a + yt, a)
        return jax.lax.scan(body, (h, h), (xs, ys))

    v = jnp.ones(3)
    jaxpr = jax.make_jaxpr(f)(v, v, jnp.ones((5, 3)), jnp.ones((5, 3)))
    (eqn,) = [e for e in jaxpr.jaxpr.eqns if e.primitive.name == "scan"]
    bare = eqn.replace(params={k: v for k, v in eqn.params.items() if k not in ("num_consts", "num_carry")})
    assert scan_split(bare) == scan_split(eqn) == (eqn.params["num_consts"], eqn.params["num_carry"])
    assert eqn.params["num_carry"] == 2


def _needed(env):
    return {name for name, keep in named_leaves(needed_leaves(env)) if keep}


def test_point_mass_needs_its_observations_and_time_and_the_key_only_for_fresh_resets():
    cached = _needed(BatchedEnv(PointMass(), 4, 10))
    # the point mass steps from its observation; reward and done are recomputed by every step
    assert cached == {"core.obs", "first.obs", "obs", "t"}
    assert _needed(BatchedEnv(PointMass(), 4, 10, reset_mode="fresh")) == {"core.obs", "obs", "t", "key"}


def test_mjx_pendulum_continues_exactly_from_the_needed_leaves_alone():
    env = BatchedEnv(make_single_env("inverted_pendulum"), 4, 6)  # short episodes: resets happen
    mask = jax.tree.leaves(needed_leaves(env))
    names = [name for name, _ in named_leaves(jax.eval_shape(env.reset, jax.random.key(0)))]
    kept = {n for n, keep in zip(names, mask) if keep}
    assert {"core.pipeline_state.qpos", "core.pipeline_state.qvel", "core.pipeline_state.qacc_warmstart"} <= kept
    assert "core.pipeline_state._impl.qM" not in kept and len(kept) < len(names) / 3  # derived data is dropped

    step, reset = jax.jit(env.step), jax.jit(env.reset)  # one step compiles faster than a scan of them

    def roll(state, actions):
        outs = []
        for action in actions:
            state, out = step(state, action)
            outs.append((out.next_obs, out.reward, out.terminated, out.truncated, state.obs))
        return state, [np.stack(x) for x in zip(*outs)]

    actions = jax.random.uniform(jax.random.key(1), (2, 9, 4, 1), minval=-1.0, maxval=1.0)
    state, _ = roll(reset(jax.random.key(2)), actions[0])
    fresh = reset(jax.random.key(3))  # a different start: every leaf not carried over differs
    resumed = jax.tree.map(lambda keep, x, y: x if keep else y, jax.tree.unflatten(jax.tree.structure(state), mask),
                           state, fresh)
    _, expected = roll(state, actions[1])
    _, got = roll(resumed, actions[1])
    for a, b in zip(expected, got):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert bool(expected[2].any() or expected[3].any())  # an episode ended and reset within the check


def test_the_arms_of_a_sweep_trace_their_envs_reset_once(monkeypatch):
    """Every trainer builds its own envs (an MJX reset traced to learn the observation size took ~1.1 s on a CPU, per
    arm, before the compile could start): a task's observation size is traced once per process, and it is the
    traced size. The evaluation environments take their agent's."""
    import dataclasses

    from cdjax import envs
    from cdjax.agents.obs import make_trainer

    from _shared import POINT

    traced, trace = [], envs.traced_observation_size
    monkeypatch.setattr(envs, "_OBSERVATION_SIZES", {})
    monkeypatch.setattr(envs, "traced_observation_size", lambda env: traced.append(env) or trace(env))
    trainers = [make_trainer(dataclasses.replace(POINT, arm=arm)) for arm in ("model-free", "mbmf", "cd")]
    assert len(traced) == 1
    size = trace(make_single_env("point"))
    assert size == PointMass().observation_size
    assert [t.eval_env(3).observation_size for t in trainers] == [size] * 3 and len(traced) == 1


def test_the_needed_leaves_are_analysed_once_per_env_and_settings(monkeypatch):
    """The arms of a sweep act in one env object with the same settings: the analysis of their step (seconds on an
    MJX task) runs once for all of them, and anew for other settings or another env object."""
    from cdjax.envs import resume

    analysed, analyse = [], resume._needed_leaves
    monkeypatch.setattr(resume, "_NEEDED", {})
    monkeypatch.setattr(resume, "_needed_leaves", lambda env: analysed.append(env) or analyse(env))
    point = PointMass()
    first = needed_leaves(BatchedEnv(point, 4, 10))
    assert needed_leaves(BatchedEnv(point, 4, 10)) == first and len(analysed) == 1
    fresh = needed_leaves(BatchedEnv(point, 4, 10, reset_mode="fresh"))
    assert len(analysed) == 2 and fresh != first  # fresh resets need the key (the test above)
    assert needed_leaves(BatchedEnv(PointMass(), 4, 10)) == first and len(analysed) == 3
