"""Orbax checkpoints of an arm's state: what a resume needs, each value once.

One `orbax.checkpoint.CheckpointManager` per arm, step = updates done, items `state` ({leaf name: array})
and `progress` (JSON: counters, wall clock, and the layout of `state`). Left out of `state`:

- leaves the trainer marks as not needed (`Trainer.saved_leaves`, e.g. the derived MJX physics data that
  every step recomputes, cdjax.envs.resume): a restore takes them from `like`, a fresh `init` of the runs;
- leaves that are all zero bits (listed in the layout), and a leaf equal bit for bit to an earlier one
  (listed with that one's name: Brax keeps q and qpos, qd and qvel);
- empty arrays (orbax refuses them; MJX state has some).

Checkpoints are atomic (orbax writes a temporary directory and renames it when complete); a checkpoint
that cannot be read is skipped in favour of the previous one with a `CheckpointWarning`. A save that
fails (a full disk) raises `WriteError` naming it; the previous checkpoints stay as they were.
"""

from __future__ import annotations

import pathlib
import re
import shutil
import warnings
from typing import Any

import jax
import numpy as np

from cdjax.io import WriteError, reason

MAX_TO_KEEP = 2


class CheckpointWarning(UserWarning):
    """A checkpoint could not be restored and an older one is used instead."""


def _is_key(x) -> bool:
    return hasattr(x, "dtype") and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def leaf_name(path) -> str:
    """`.params['policy']['params']['Dense_0']['kernel']` -> `params.policy.params.Dense_0.kernel`."""
    return re.sub(r"[^\w]+", ".", jax.tree_util.keystr(path)).strip(".")


def named_leaves(tree) -> list[tuple[str, Any]]:
    out = [(leaf_name(path), x) for path, x in jax.tree_util.tree_flatten_with_path(tree)[0]]
    names = [name for name, _ in out]
    assert len(set(names)) == len(names), "two leaves with one name"
    return out


def compact(tree, keep=None) -> tuple[dict[str, Any], dict]:
    """(arrays to store, layout) of a state: see the module docstring. `keep`: pytree of bool like `tree`."""
    flags = jax.tree.leaves(keep) if keep is not None else None
    layout: dict = {"zeros": [], "same": {}}
    stored: dict[str, Any] = {}
    seen: dict[tuple, list[str]] = {}
    for i, (name, x) in enumerate(named_leaves(tree)):
        if (flags is not None and not flags[i]) or x.size == 0:
            continue
        x = jax.random.key_data(x) if _is_key(x) else x
        if jax.process_count() > 1:  # a global array is not readable from one process: store it as it is
            stored[name] = x
            continue
        value = np.asarray(jax.device_get(x))
        raw = np.ascontiguousarray(value).view(np.uint8)
        if not raw.any():
            layout["zeros"].append(name)
            continue
        twins = seen.setdefault((value.shape, value.dtype.str, hash(raw.tobytes())), [])
        twin = next((t for t in twins if np.array_equal(np.ascontiguousarray(stored[t]).view(np.uint8), raw)), None)
        if twin is not None:
            layout["same"][name] = twin
            continue
        twins.append(name)
        stored[name] = value
    layout["stored"] = sorted(stored)
    return stored, layout


def expand(stored: dict[str, Any], layout: dict | None, like):
    """Inverse of `compact`: the tree of `like` (concrete, with shardings) with the stored leaves put back."""
    leaves, treedef = jax.tree.flatten(like)
    out = []
    for (name, target), leaf in zip(named_leaves(like), leaves):
        if leaf.size == 0:
            out.append(leaf)
            continue
        data_like = jax.eval_shape(jax.random.key_data, target) if _is_key(target) else target
        if name in stored:
            value = stored[name]
        elif layout is not None and name in layout["zeros"]:
            value = np.zeros(data_like.shape, data_like.dtype)
        elif layout is not None and name in layout["same"]:
            value = np.asarray(stored[layout["same"][name]])  # its own buffer: a state may be donated
        else:
            out.append(leaf)  # not stored: no later update reads it, or init gives it again
            continue
        if tuple(value.shape) != tuple(data_like.shape) or value.dtype != data_like.dtype:
            raise ValueError(f"leaf {name} is {value.shape} {value.dtype} where {data_like.shape} {data_like.dtype} "
                             "was expected")
        value = jax.device_put(value, leaf.sharding)
        out.append(jax.random.wrap_key_data(value, impl=jax.random.key_impl(leaf)) if _is_key(leaf) else value)
    return jax.tree.unflatten(treedef, out)


def leading_runs(tree) -> int | None:
    """The leading (run) axis length shared by every non-scalar leaf of a sweep state; None if there is none."""
    lengths = {x.shape[0] for x in jax.tree.leaves(tree) if getattr(x, "ndim", 0) > 0}
    return lengths.pop() if len(lengths) == 1 else None


def repad_runs(value: np.ndarray, runs: int) -> np.ndarray:
    """A stored [R_saved, ...] leaf for a sweep padded to `runs`. The padding runs of `cdjax.sweep.Sweep.grid`
    repeat the last real run (same key and hyper-parameters, so the same state), and both run counts are at
    least the real one: cutting keeps every real run, and extending repeats a real run or a copy of one."""
    if value.shape[0] >= runs:
        return value[:runs]
    return np.concatenate([value, np.repeat(value[-1:], runs - value.shape[0], axis=0)])


def step_dirs(directory: pathlib.Path) -> list[int]:
    """The steps of the complete checkpoints in `directory`, from the directory names alone."""
    return sorted(int(p.name) for p in directory.iterdir() if p.name.isdigit()) if directory.is_dir() else []


class Checkpoints:
    """The checkpoints of one arm: save(step, state, progress), restore(like), latest complete step."""

    def __init__(self, directory: pathlib.Path):
        import orbax.checkpoint as ocp

        self._ocp = ocp
        self.directory = directory
        try:
            directory.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise WriteError(f"cannot write {directory}: {reason(err)}") from None
        self.manager = ocp.CheckpointManager(
            directory.resolve(), options=ocp.CheckpointManagerOptions(max_to_keep=MAX_TO_KEEP, create=True),
            item_names=("state", "progress"))
        self._pending: int | None = None

    def steps(self) -> list[int]:
        return sorted(self.manager.all_steps())

    def latest(self) -> int | None:
        """The newest complete checkpoint on disk (None: none yet); also after `close`."""
        steps = [s for s in step_dirs(self.directory) if s != self._pending]
        return max(steps) if steps else None

    def save(self, step: int, state, progress: dict, keep=None) -> None:
        """Start an (asynchronous, atomic) save; `wait` for it. `keep`: Trainer.saved_leaves() or None."""
        ocp = self._ocp
        stored, layout = compact(state, keep)
        runs = leading_runs(state)
        if runs is not None:
            layout["runs"] = runs  # the (padded) run count: a restore on another device count re-pads to its own
        self._pending = step
        try:
            self.manager.save(step, args=ocp.args.Composite(
                state=ocp.args.StandardSave(stored or {"empty": np.zeros(1)}),
                progress=ocp.args.JsonSave({**progress, "layout": layout})), force=True)
        except Exception as err:  # noqa: BLE001 - a failed write, whatever orbax wraps it in
            self._failed(step, err)

    def wait(self) -> None:
        """Block until the last save is complete; WriteError (naming it) if it failed."""
        try:
            self.manager.wait_until_finished()
        except Exception as err:  # noqa: BLE001
            self._failed(self._pending, err)
        self._pending = None

    def _failed(self, step: int | None, err: Exception):
        for tmp in self.directory.glob(f"{step}.orbax-checkpoint-tmp*"):  # free what the failed save took
            shutil.rmtree(tmp, ignore_errors=True)
        self._pending = None
        raise WriteError(f"cannot write the checkpoint {self.directory / str(step)}: {reason(err)}") from None

    def restore(self, like, delete_bad: bool = True) -> tuple[Any, dict] | None:
        """(state, progress) of the newest checkpoint that can be read, or None if there is none.

        `like`: a concrete state of the same runs (a fresh init): shapes, dtypes, shardings and the leaves
        the checkpoint does not hold. A checkpoint that fails to restore is reported with a
        CheckpointWarning (and deleted, with `delete_bad`: a resumed run writes that step again), and the
        previous one is tried.
        """
        ocp = self._ocp
        for step in reversed(self.steps()):
            try:
                progress = dict(self.manager.restore(step, args=ocp.args.Composite(
                    progress=ocp.args.JsonRestore()))["progress"])
                layout = progress.pop("layout", None)
                names = dict(named_leaves(like))
                wanted = layout["stored"] if layout is not None else [n for n, x in names.items() if x.size]
                saved_runs, runs = (layout or {}).get("runs"), leading_runs(like)
                repad = saved_runs is not None and runs is not None and saved_runs != runs
                target = {}
                for name in wanted:
                    x = names[name]
                    data = jax.eval_shape(jax.random.key_data, x) if _is_key(x) else x
                    if repad:  # saved on another device count: read whole on one device, re-padded below
                        target[name] = jax.ShapeDtypeStruct((saved_runs, *data.shape[1:]), data.dtype,
                                                            sharding=jax.sharding.SingleDeviceSharding(
                                                                next(iter(x.sharding.device_set))))
                    else:
                        target[name] = jax.ShapeDtypeStruct(data.shape, data.dtype, sharding=x.sharding)
                stored = dict(self.manager.restore(step, args=ocp.args.Composite(
                    state=ocp.args.StandardRestore(target)))["state"]) if target else {}
                if repad:
                    stored = {name: repad_runs(np.asarray(v), runs) for name, v in stored.items()}
                state = expand(stored, layout, like)
                if progress.get("updates") != step:
                    raise ValueError(f"progress says {progress.get('updates')} updates")
            except Exception as err:  # noqa: BLE001 - any failure to read means: use the previous one
                warnings.warn(f"Checkpoint {self.directory}/{step} cannot be restored ({type(err).__name__}: "
                              f"{str(err).splitlines()[0][:200] if str(err) else ''}); falling back to the "
                              "previous one.", CheckpointWarning, stacklevel=2)
                if delete_bad:
                    self.manager.delete(step)
                continue
            return state, progress
        return None

    def delete_all(self) -> None:
        for step in self.steps():
            self.manager.delete(step)

    def close(self) -> None:
        """Wait for a save in flight and release the manager (a failed save was reported by `wait`)."""
        try:
            self.manager.wait_until_finished()
        except Exception:  # noqa: BLE001
            pass
        self.manager.close()
