"""Random-shooting model-predictive control (MPC) in pure JAX.

This is the controller of Mb-Mf (Nagabandi et al., 2017), which Sodhani et al.
(2019) use as their model-based baseline: at every environment step, sample
``num_candidates`` action sequences uniformly from ``[-1, 1]^(horizon x action_size)``,
roll each one out through a dynamics function, sum the (discounted) predicted
rewards, and execute the first action of the best sequence. With ``num_elites > 1``
it executes the mean first action of the ``num_elites`` best sequences instead
(one step of the cross-entropy method's refit, without iterating): the best
sequence's first action is mostly noise when the horizon is long, because the
first action decides a small part of the sequence's return.

The controller is generic over the dynamics. ``step_fn(state, action) ->
(next_state, reward)`` may be

* a learned model over observation vectors (``state`` is an ``(obs_dim,)`` array),
* the true simulator (``state`` is a Brax ``State`` and ``step_fn`` calls
  ``env.step``), or
* any other pure JAX function over an arbitrary pytree ``state``.

Everything here is a module-level pure function without a hidden ``jax.jit``:
callers jit (typically the whole closed-loop episode). ``horizon``,
``num_candidates`` and ``action_size`` are static Python ints, so wrap callers
with ``functools.partial`` or ``static_argnames`` accordingly.

Notation for shapes: ``N`` = num_candidates, ``H`` = horizon,
``A`` = action_size, ``B`` = batch (number of environments).
"""

from __future__ import annotations

import numbers
from typing import Any, Callable, Dict, Tuple

import jax
import jax.numpy as jnp
from jax import lax

__all__ = [
    "StepFn",
    "sample_action_sequences",
    "rollout_returns",
    "select_best",
    "select_elite_mean",
    "random_shooting",
    "batched_random_shooting",
]

PyTree = Any
# step_fn(state, action[A]) -> (next_state with the same structure/shapes/dtypes, reward[])
StepFn = Callable[[PyTree, jax.Array], Tuple[PyTree, jax.Array]]


# --------------------------------------------------------------------------------------
# Argument checks (all on static Python values or static shapes: free at trace time).
# --------------------------------------------------------------------------------------


def _check_positive_int(name: str, value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value <= 0:
        raise ValueError(f"{name} must be a positive Python int (static), got {value!r}")


def _check_static_sizes(horizon: Any, num_candidates: Any, action_size: Any) -> None:
    _check_positive_int("horizon", horizon)
    _check_positive_int("num_candidates", num_candidates)
    _check_positive_int("action_size", action_size)


def _check_discount(discount: Any) -> None:
    # A traced discount is allowed (e.g. swept under vmap); only check concrete numbers.
    if isinstance(discount, numbers.Real) and not 0.0 < float(discount) <= 1.0:
        raise ValueError(f"discount must lie in (0, 1], got {discount!r}")
    if not isinstance(discount, numbers.Real) and jnp.shape(discount) != ():
        raise ValueError(f"discount must be a scalar, got shape {jnp.shape(discount)}")


def _is_typed_key(key: Any) -> bool:
    return hasattr(key, "dtype") and jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key)


def _check_single_key(key: Any) -> None:
    """Accept one new-style typed key (shape ``()``) or one raw uint32 key (``(2,)``)."""
    shape = jnp.shape(key)
    if _is_typed_key(key):
        if shape != ():
            raise ValueError(f"expected a single PRNG key, got a typed key array of shape {shape}")
    elif len(shape) != 1:
        raise ValueError(f"expected a single raw PRNG key of shape (2,), got shape {shape}")


def _leading_dim(tree: PyTree, what: str) -> int:
    leaves = jax.tree_util.tree_leaves(tree)
    if not leaves:
        raise ValueError(f"{what} has no array leaves")
    dims = {jnp.shape(x)[0] if jnp.ndim(x) > 0 else None for x in leaves}
    if None in dims or len(dims) != 1:
        raise ValueError(
            f"every leaf of {what} must share one leading batch axis; got leading dims {dims}"
        )
    return dims.pop()


def _cast_strong(x: Any, dtype: Any) -> jax.Array:
    """``x`` as a strongly typed array of ``dtype`` (PRNG-key leaves are left alone)."""
    if jax.dtypes.issubdtype(dtype, jax.dtypes.prng_key):
        return x
    return lax.convert_element_type(x, dtype)


def _as_carry(tree: PyTree) -> PyTree:
    """Turn every leaf into a strongly typed array, so it can be a ``lax.scan`` carry."""
    return jax.tree_util.tree_map(lambda x: _cast_strong(x, jnp.result_type(x)), tree)


def _match_carry(new: PyTree, old: PyTree) -> PyTree:
    """Cast ``new`` to the leaf dtypes of ``old`` (strong types), checking structure/shapes.

    Simulators often return Python-float or weak-typed fields (e.g. Brax's inverted
    pendulum sets ``reward = 1.0``); casting keeps the scan carry type fixed.
    """
    new_leaves, new_def = jax.tree_util.tree_flatten(new)
    old_leaves, old_def = jax.tree_util.tree_flatten(old)
    if new_def != old_def:
        raise ValueError(
            "step_fn must return a next_state with the same pytree structure as state;\n"
            f"  state:      {old_def}\n  next_state: {new_def}"
        )
    out = []
    for n, o in zip(new_leaves, old_leaves):
        if jnp.shape(n) != jnp.shape(o):
            raise ValueError(
                f"step_fn changed a state leaf's shape from {jnp.shape(o)} to {jnp.shape(n)}"
            )
        out.append(_cast_strong(n, o.dtype))
    return jax.tree_util.tree_unflatten(old_def, out)


# --------------------------------------------------------------------------------------
# Building blocks.
# --------------------------------------------------------------------------------------


def sample_action_sequences(
    key: jax.Array,
    *,
    horizon: int,
    num_candidates: int,
    action_size: int,
    dtype: Any = jnp.float32,
) -> jax.Array:
    """Uniform candidate action sequences.

    Args:
      key: a single PRNG key.
    Returns:
      actions: ``[N, H, A]``, i.i.d. uniform in ``[-1, 1]``.
    """
    _check_single_key(key)
    _check_static_sizes(horizon, num_candidates, action_size)
    return jax.random.uniform(
        key, (num_candidates, horizon, action_size), dtype=dtype, minval=-1.0, maxval=1.0
    )


def rollout_returns(
    step_fn: StepFn,
    state: PyTree,
    actions: jax.Array,
    discount: float | jax.Array = 1.0,
) -> jax.Array:
    """Discounted predicted return of every candidate sequence from one start state.

    ``return[n] = sum_t discount**t * reward_t`` with ``(s_{t+1}, reward_t) =
    step_fn(s_t, actions[n, t])``. Candidates are ``jax.vmap``-ed, the horizon is a
    ``jax.lax.scan``. Non-finite returns are passed through unchanged (see
    :func:`select_best`).

    Args:
      step_fn: ``(state, action[A]) -> (next_state, reward[])``, pure JAX.
      state: the start state, a pytree without a candidate axis.
      actions: ``[N, H, A]``.
      discount: scalar in ``(0, 1]``.
    Returns:
      returns: ``[N]``, in the dtype of ``actions``.
    """
    if jnp.ndim(actions) != 3:
        raise ValueError(f"actions must be [N, H, A], got shape {jnp.shape(actions)}")
    _check_discount(discount)
    dtype = actions.dtype
    discount = jnp.asarray(discount, dtype)
    start = _as_carry(state)

    def one_sequence(seq: jax.Array) -> jax.Array:  # seq: [H, A] -> []
        def body(carry, action):
            s, ret, weight = carry
            next_s, reward = step_fn(s, action)
            reward = jnp.asarray(reward, dtype)
            if reward.shape != ():
                raise ValueError(f"step_fn must return a scalar reward, got shape {reward.shape}")
            ret = ret + weight * reward
            return (_match_carry(next_s, s), ret, weight * discount), None

        init = (start, jnp.zeros((), dtype), jnp.ones((), dtype))
        (_, ret, _), _ = lax.scan(body, init, seq)
        return ret

    return jax.vmap(one_sequence)(actions)


def select_best(
    actions: jax.Array, returns: jax.Array
) -> Tuple[jax.Array, Dict[str, jax.Array]]:
    """First action of the best candidate, ignoring non-finite returns.

    NaN and +/-inf returns are treated as ``-inf`` and never chosen. If no return is
    finite, the action is all zeros (the centre of the action box).

    Args:
      actions: ``[N, H, A]``.
      returns: ``[N]``.
    Returns:
      action: ``[A]``.
      info: scalars ``best_return`` (``-inf`` if nothing is finite), ``mean_return``
        (mean over the finite candidates, ``-inf`` if none) and ``frac_finite``.
    """
    n, _, a = actions.shape
    if returns.shape != (n,):
        raise ValueError(f"returns must have shape ({n},), got {returns.shape}")
    finite = jnp.isfinite(returns)
    any_finite = jnp.any(finite)
    safe = jnp.where(finite, returns, -jnp.inf)
    best = jnp.argmax(safe)  # NaN-free, so argmax is well defined; index 0 if all -inf
    action = jnp.where(any_finite, actions[best, 0], jnp.zeros((a,), actions.dtype))
    num_finite = jnp.sum(finite)
    mean_finite = jnp.sum(jnp.where(finite, returns, 0.0)) / jnp.maximum(num_finite, 1)
    info = {
        "best_return": safe[best],
        "mean_return": jnp.where(any_finite, mean_finite, -jnp.inf),
        "frac_finite": num_finite.astype(returns.dtype) / n,
    }
    return action, info


def select_elite_mean(
    actions: jax.Array, returns: jax.Array, num_elites: int
) -> Tuple[jax.Array, Dict[str, jax.Array]]:
    """Mean first action of the ``num_elites`` best candidates, ignoring non-finite returns.

    Non-finite returns rank last (as ``-inf``); elites without a finite return are left out of the
    mean, and with no finite return at all the action is zeros. ``num_elites = 1`` is ``select_best``.

    Args:
      actions: ``[N, H, A]``.
      returns: ``[N]``.
      num_elites: static int, ``1 <= num_elites <= N``.
    Returns:
      action: ``[A]``; info as ``select_best``'s (``best_return`` is the best elite's).
    """
    n, _, a = actions.shape
    _check_positive_int("num_elites", num_elites)
    if num_elites > n:
        raise ValueError(f"num_elites={num_elites} is more than the {n} candidates")
    best, info = select_best(actions, returns)
    if num_elites == 1:
        return best, info
    safe = jnp.where(jnp.isfinite(returns), returns, -jnp.inf)
    top, idx = lax.top_k(safe, num_elites)
    weight = jnp.isfinite(top).astype(actions.dtype)
    total = jnp.sum(weight)
    mean = jnp.sum(actions[idx, 0] * weight[:, None], axis=0) / jnp.maximum(total, 1.0)
    return jnp.where(total > 0, mean, jnp.zeros((a,), actions.dtype)), info


# --------------------------------------------------------------------------------------
# Controllers.
# --------------------------------------------------------------------------------------


def random_shooting(
    key: jax.Array,
    step_fn: StepFn,
    state: PyTree,
    *,
    horizon: int,
    num_candidates: int,
    action_size: int,
    discount: float | jax.Array = 1.0,
    num_elites: int = 1,
) -> Tuple[jax.Array, Dict[str, jax.Array]]:
    """Random-shooting MPC for one state.

    Args:
      key: a single PRNG key (typed ``()`` or raw ``(2,)``).
      step_fn: ``(state, action[A]) -> (next_state, reward[])``, pure JAX; ``next_state``
        must have the structure and leaf shapes of ``state`` (dtypes are cast back).
      state: the current state, any pytree (no batch axis).
      horizon: ``H``, planning horizon (static int).
      num_candidates: ``N``, number of sampled action sequences (static int).
      action_size: ``A`` (static int). Actions are in ``[-1, 1]``.
      discount: scalar in ``(0, 1]`` weighting reward ``t`` by ``discount**t``.
      num_elites: static int; 1 acts with the best candidate's first action, more with the
        mean first action of that many best candidates (``select_elite_mean``).
    Returns:
      action: ``[A]``, first action of the best candidate, or the elites' mean (zeros if every
        predicted return is non-finite).
      info: dict of scalars ``best_return``, ``mean_return``, ``frac_finite``.
    """
    _check_single_key(key)
    _check_static_sizes(horizon, num_candidates, action_size)
    actions = sample_action_sequences(
        key, horizon=horizon, num_candidates=num_candidates, action_size=action_size
    )
    returns = rollout_returns(step_fn, state, actions, discount)
    return select_elite_mean(actions, returns, num_elites)


def batched_random_shooting(
    key: jax.Array,
    step_fn: StepFn,
    states: PyTree,
    *,
    horizon: int,
    num_candidates: int,
    action_size: int,
    discount: float | jax.Array = 1.0,
    num_elites: int = 1,
) -> Tuple[jax.Array, Dict[str, jax.Array]]:
    """Random-shooting MPC for a batch of states, one independent controller per env.

    ``key`` is split into ``B`` keys, ``keys[i]`` drives env ``i``; the result equals
    ``random_shooting(keys[i], step_fn, states[i], ...)`` for each ``i``.

    Args:
      key: a single PRNG key.
      step_fn: as in :func:`random_shooting`, for ONE unbatched state.
      states: pytree whose every leaf has leading batch axis ``B``.
      horizon, num_candidates, action_size, discount, num_elites: as in :func:`random_shooting`.
    Returns:
      actions: ``[B, A]``.
      info: dict of ``[B]`` arrays (``best_return``, ``mean_return``, ``frac_finite``).
    """
    _check_single_key(key)
    _check_static_sizes(horizon, num_candidates, action_size)
    batch = _leading_dim(states, "states")
    keys = jax.random.split(key, batch)

    def one_env(k, s):
        return random_shooting(
            k,
            step_fn,
            s,
            horizon=horizon,
            num_candidates=num_candidates,
            action_size=action_size,
            discount=discount,
            num_elites=num_elites,
        )

    return jax.vmap(one_env)(keys, states)
