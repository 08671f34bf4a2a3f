"""Which leaves of a `BatchedEnv`'s state a resumed run needs, found from the traced step itself.

An MJX environment state is mostly derived data (mass matrix, contacts, constraint Jacobians, ...) that
every physics step recomputes from a few fields (qpos, qvel, the solver's warm start, ...) before reading
it. `needed_leaves(env)` traces one batched step and follows, leaf by leaf, which inputs each output
depends on (through scans, while loops and conds); a leaf is needed when something observable (the
step's outputs, the observation the policy acts on, the restart observation) depends on it now or
after any number of steps. A checkpoint keeps the needed leaves and drops the others: whatever value
they take on restore, no later step reads them, so a resumed run is bit for bit the same.

On Brax's ant this keeps 1.6 kB of the 24 kB of state per environment (the tests check the point
mass and the MJX pendulum: restoring only these leaves continues the episode exactly).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.extend import core as jax_core

from cdjax.envs import BatchedEnv


def leaf_dependencies(fn, *args) -> list[int]:
    """For each flat output leaf of fn(*args), a bit mask of the flat input leaves it depends on.

    `args` may be abstract (jax.ShapeDtypeStruct). The analysis is conservative: inside one primitive
    every output depends on every input, except that calls are followed into and scans, while loops
    and conds are followed per carry (to a fixed point).
    """
    closed = jax.make_jaxpr(fn)(*args)
    inputs = [1 << i for i in range(len(closed.jaxpr.invars))]
    return _walk(closed.jaxpr, inputs)


def _walk(jaxpr, inputs: list[int]) -> list[int]:
    deps: dict = dict(zip(jaxpr.invars, inputs))

    def read(var) -> int:
        return 0 if isinstance(var, jax_core.Literal) else deps.get(var, 0)

    for eqn in jaxpr.eqns:
        outs = _primitive(eqn, [read(v) for v in eqn.invars])
        deps.update(zip(eqn.outvars, outs))
    return [read(v) for v in jaxpr.outvars]


def _inner(closed, inputs: list[int]) -> list[int]:
    jaxpr = getattr(closed, "jaxpr", closed)
    return _walk(jaxpr, inputs)


def scan_split(eqn) -> tuple[int, int]:
    """(number of consts, number of carries) of a scan equation.

    Read from the parameters when they are there; otherwise (their names have changed between JAX
    releases) from the shapes, which every release keeps: a carry has the same shape outside and inside
    the body, a scanned input or output has the trip count in front of the body's shape. So the carries
    are the leading outputs whose shape the body keeps, and the scanned inputs the trailing inputs that
    lose their leading axis in the body; the consts are the rest.
    """
    params = eqn.params
    body = getattr(params["jaxpr"], "jaxpr", params["jaxpr"])
    n_carry = params.get("num_carry")
    if n_carry is None:
        n_carry = 0
        for outer, inner in zip(eqn.outvars, body.outvars):
            if outer.aval.shape != inner.aval.shape:
                break
            n_carry += 1
    n_consts = params.get("num_consts")
    if n_consts is None:
        n_xs = 0
        for outer, inner in zip(reversed(eqn.invars), reversed(body.invars)):
            if outer.aval.shape[1:] != inner.aval.shape or outer.aval.ndim != inner.aval.ndim + 1:
                break
            n_xs += 1
        n_consts = len(eqn.invars) - n_carry - n_xs
    return n_consts, n_carry


def _primitive(eqn, ins: list[int]) -> list[int]:
    """Output masks of one equation from its input masks."""
    params, n_out = eqn.params, len(eqn.outvars)
    if eqn.primitive.name == "scan":
        consts, n_carry = scan_split(eqn)
        carry, xs = ins[consts:consts + n_carry], ins[consts + n_carry:]
        while True:
            outs = _inner(params["jaxpr"], ins[:consts] + carry + xs)
            grown = [a | b for a, b in zip(carry, outs[:n_carry])]
            if grown == carry:
                return carry + outs[n_carry:]
            carry = grown
    if eqn.primitive.name == "while":
        # cond_jaxpr takes (cond consts, carry), body_jaxpr (body consts, carry); the carry is the output.
        cond_jaxpr, body_jaxpr = (getattr(params[k], "jaxpr", params[k]) for k in ("cond_jaxpr", "body_jaxpr"))
        n_cond, n_body = len(cond_jaxpr.invars) - n_out, len(body_jaxpr.invars) - n_out
        cond, body, carry = ins[:n_cond], ins[n_cond:n_cond + n_body], ins[n_cond + n_body:]
        while True:
            stop = _inner(cond_jaxpr, cond + carry)[0]  # the trip count touches every output
            grown = [a | b | stop for a, b in zip(carry, _inner(body_jaxpr, body + carry))]
            if grown == carry:
                return carry
            carry = grown
    if eqn.primitive.name == "cond":
        outs = [ins[0]] * n_out
        for branch in params["branches"]:
            outs = [a | b for a, b in zip(outs, _inner(branch, ins[1:]))]
        return outs
    for value in params.values():  # a call (pjit, custom_jvp, remat, ...): follow it when it maps 1:1
        jaxpr = getattr(value, "jaxpr", value)
        if hasattr(jaxpr, "eqns") and len(jaxpr.invars) == len(ins) and len(jaxpr.outvars) == n_out:
            return _inner(jaxpr, ins)
    union = functools.reduce(lambda a, b: a | b, ins, 0)
    return [union] * n_out


# (physics env object, batched env's settings) -> (the env object, held so that its id stays its own; needed_leaves)
_NEEDED: dict = {}


def needed_leaves(env: BatchedEnv):
    """An EnvState of bools: True for the leaves a resumed run must restore exactly. Analysed once per env object and
    settings in this process (seconds for an MJX task): the arms of a sweep act in the same environments."""
    key = (id(env.env), env.num_envs, env.episode_length, env.action_repeat, env.reset_mode, env.stagger)
    if key not in _NEEDED:
        _NEEDED[key] = (env.env, _needed_leaves(env))
    return _NEEDED[key][1]


def _needed_leaves(env: BatchedEnv):
    state = jax.eval_shape(env.reset, jax.random.key(0))
    action = jax.ShapeDtypeStruct((env.num_envs, env.action_size), jnp.float32)

    def observed(s, a):
        new, out = env.step(s, a)
        restart = env.restart_obs(s)
        return new, (out, s.obs, () if restart is None else restart)

    deps = leaf_dependencies(observed, state, action)
    leaves, treedef = jax.tree.flatten(state)
    n = len(leaves)
    needed = functools.reduce(lambda a, b: a | b, deps[n:], 0)
    while True:  # a leaf that a needed leaf of the next state depends on is needed as well
        grown = functools.reduce(lambda a, i: a | deps[i], (i for i in range(n) if needed >> i & 1), needed)
        if grown == needed:
            break
        needed = grown
    return jax.tree.unflatten(treedef, [bool(needed >> i & 1) for i in range(n)])
