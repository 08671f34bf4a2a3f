"""Orbax checkpoints of an arm's state: what a resume needs, each value once.

One `orbax.checkpoint.CheckpointManager` per arm, step = updates done, items `state` ({leaf name: array})
and `progress` (JSON: counters, wall clock, and the layout of `state`). Left out of `state`:

- leaves the trainer marks as not needed (`Trainer.saved_leaves`, e.g. the derived MJX physics data that
  every step recomputes, cdjax.envs.resume): a restore takes them from `like`, a fresh `init` of the runs;
- leaves that are all zero bits (listed in the layout), and a leaf equal bit for bit to an earlier one
  (listed with that one's name: Brax keeps q and qpos, qd and qvel);
- empty arrays (orbax refuses them; MJX state has some).

Checkpoints are evidence: a read never deletes one. Before any array is read, a checkpoint is checked against
the run asked for: the run it records (`progress["run"]`, compared by the caller's `expect`: setting, arm,
config, seeds and grid) and the name, shape and dtype of every leaf (`layout["shapes"]`, or orbax's metadata for
checkpoints written before it was recorded). A difference raises `CheckpointMismatch` (one sentence naming it;
nothing is changed). Only a checkpoint that cannot be read as files (a truncated or damaged file) is skipped in
favour of the previous one, with a `CheckpointWarning`, and moved aside (renamed `<step>.unreadable`, kept).
The run axis is re-padded only for another device count: the real runs recorded must be the same.

Checkpoints are atomic (orbax writes a temporary directory and renames it when complete). A save that fails (a
full disk) raises `WriteError` naming it; the previous checkpoints stay as they were.

Several processes (cdjax.multihost): the state's leaves are global arrays; every process calls save, restore and
close in the same order, orbax writes each process's shards and process 0 the records and the final rename (a
checkpoint is complete once every process has written its part). Whether a checkpoint can be read is agreed (one
process that cannot read its shards makes it unreadable for all), only process 0 moves one aside, and an error that
says another process is gone raises `multihost.PeerLost` instead of a WriteError.
"""

from __future__ import annotations

import os
import pathlib
import re
import shutil
import warnings
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from cdjax import multihost
from cdjax.errors import CheckpointMismatch, CheckpointWarning, WriteError, reason

MAX_TO_KEEP = 2


class _Unreadable(Exception):
    """A checkpoint that cannot be read as files."""


def _data_shape(x) -> tuple[tuple[int, ...], str]:
    """(shape, dtype name) of a leaf as stored: a PRNG key as its key data."""
    data = jax.eval_shape(jax.random.key_data, x) if _is_key(x) else x
    return tuple(int(d) for d in data.shape), np.dtype(data.dtype).name


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
    layout: dict = {"zeros": [], "same": {}, "shapes": {}}
    stored: dict[str, Any] = {}
    seen: dict[tuple, list[str]] = {}
    for i, (name, x) in enumerate(named_leaves(tree)):
        shape, dtype = _data_shape(x)
        layout["shapes"][name] = [list(shape), dtype]  # every leaf, stored or not: what a restore checks
        if (flags is not None and not flags[i]) or x.size == 0:
            continue
        x = jax.random.key_data(x) if _is_key(x) else x
        if jax.process_count() > 1:  # a global array is not readable from one process: store it as it is
            stored[name] = x
            continue
        value = np.asarray(jax.device_get(x))
        if isinstance(x, jax.Array) and any(d.platform == "cpu" for d in x.devices()):
            value = value.copy()  # XLA:CPU may lend its own buffer, which the next chunk donates while this is written
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


@jax.jit
def _copies(leaves: list) -> list:
    """Fresh device buffers holding `leaves` (arrays, typed keys too): one program per list of shapes. Copying leaf
    by leaf would compile one program per shape, and the first checkpoint of a chunked sweep (the second round's
    start) would wait on all of those compiles."""
    return [jnp.copy(x) for x in leaves]


def snapshot(tree, keep=None):
    """A copy on the devices of the leaves a save stores (`keep`: pytree of bool like `tree`; the others become
    ShapeDtypeStructs, whose shapes are all a save records of them): what `save` reads once the next chunk has
    donated the state's own buffers, so the chunk can start before the copy to the host."""
    flags = jax.tree.leaves(keep) if keep is not None else None
    leaves, treedef = jax.tree.flatten(tree)
    out, copied = list(leaves), []
    for i, x in enumerate(leaves):
        if not isinstance(x, jax.Array):
            continue
        if (flags is not None and not flags[i]) or x.size == 0:
            out[i] = jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=x.sharding)
        else:
            copied.append(i)
    for i, x in zip(copied, _copies([leaves[i] for i in copied])):
        out[i] = x
    return jax.tree.unflatten(treedef, out)


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
            twin = stored[layout["same"][name]]  # a copy, its own buffer: a state may be donated
            if isinstance(twin, jax.Array) and not twin.is_fully_addressable:  # (several processes, one's checkpoint)
                value = jnp.array(twin, copy=True)
            else:
                value = np.asarray(twin)
        else:
            out.append(leaf)  # not stored: no later update reads it, or init gives it again
            continue
        if tuple(value.shape) != tuple(data_like.shape) or value.dtype != data_like.dtype:
            raise ValueError(f"leaf {name} is {value.shape} {value.dtype} where {data_like.shape} {data_like.dtype} "
                             "was expected")
        value = multihost.put(value, leaf.sharding)
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


def _why(err: BaseException) -> str:
    text = str(err).splitlines()[0][:200] if str(err) else ""
    return f"{type(err).__name__}: {text}" if text else type(err).__name__


def _short(value, limit: int = 80) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[:limit] + "..."


def _leaf_difference(saved: dict, layout: dict | None, like, run: dict | None) -> str | None:
    """How the checkpoint's leaves differ from those of `like` (None: they agree). The run axis may differ only
    in its padding (another device count), and only when the checkpoint records its real runs and each padding
    holds them all."""
    want = {name: _data_shape(x) for name, x in named_leaves(like)}
    runs = leading_runs(like)
    saved_runs = (layout or {}).get("runs")
    if saved_runs is None:  # an older checkpoint: the run axis of its stored leaves
        lengths = {shape[0] for shape, _ in saved.values() if shape}
        saved_runs = lengths.pop() if len(lengths) == 1 else None
    batched = runs is not None and saved_runs is not None
    for name, (shape, dtype) in sorted(saved.items(), key=lambda item: (not item[0].startswith("params"), item[0])):
        if name not in want:  # (parameters first: the difference a user recognises)
            return f"it holds a leaf {name} that this run's state has not"
        mine, mine_dtype = want[name]
        same = (shape[1:] == mine[1:] and shape[:1] == (saved_runs,) and mine[:1] == (runs,)) if batched and shape \
            else shape == mine
        if not same or dtype != mine_dtype:
            return f"its leaf {name} is {list(shape)} {dtype} where this run's state has {list(mine)} {mine_dtype}"
    if layout is not None and isinstance(layout.get("shapes"), dict):  # every leaf recorded: none may be missing
        missing = sorted(set(want) - set(saved))
        if missing:
            return f"this run's state has a leaf {missing[0]} that it does not hold"
    if batched and saved_runs != runs:
        real = run.get("num_runs") if isinstance(run, dict) else None
        if not (isinstance(real, int) and real <= min(saved_runs, runs)):
            return f"it holds {saved_runs} runs where this run has {runs}"
    return None


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
        # Orbax names its barriers by step alone: with several processes, two arms saving the same step at once
        # would meet in one barrier ("already ongoing") unless each arm's names are its own.
        sync = ocp.options.MultiprocessingOptions(barrier_sync_key_prefix=f"cdjax.{directory.name}")
        self.manager = ocp.CheckpointManager(
            directory.resolve(), options=ocp.CheckpointManagerOptions(max_to_keep=MAX_TO_KEEP, create=True,
                                                                      multiprocessing_options=sync),
            item_names=("state", "progress"))
        self._pending: int | None = None
        self._reads_device = False

    def steps(self) -> list[int]:
        return sorted(self.manager.all_steps())

    def latest(self) -> int | None:
        """The newest complete checkpoint on disk (None: none yet); also after `close`."""
        steps = [s for s in step_dirs(self.directory) if s != self._pending]
        return max(steps) if steps else None

    def save(self, step: int, state, progress: dict, keep=None) -> None:
        """Start an (asynchronous, atomic) save; `wait` for it. `keep`: Trainer.saved_leaves() or None."""
        ocp = self._ocp
        if self._pending is not None:  # the last save's write may still run (`release`): finish it, naming its step
            self.wait()
        stored, layout = compact(state, keep)
        # Several processes store global arrays as they are (the write reads the devices' buffers); one process
        # stores host copies, made above, so its write no longer needs the state (`release`).
        self._reads_device = any(isinstance(v, jax.Array) for v in stored.values())
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

    def release(self) -> None:
        """Make the saved state's device buffers free for the next chunk to donate: wait for the save only where its
        write still reads them (several processes); otherwise it goes on behind the next chunk, and the next `save`,
        `wait` or `close` waits for it (a failed write is then reported by the next save or wait)."""
        if self._pending is not None and self._reads_device:
            self.wait()

    def wait(self) -> None:
        """Block until the last save is complete; WriteError (naming it) if it failed."""
        try:
            self.manager.wait_until_finished()
        except Exception as err:  # noqa: BLE001
            self._failed(self._pending, err)
        self._pending = None

    def _failed(self, step: int | None, err: Exception):
        self._pending = None
        if multihost.is_peer_error(err):  # a barrier of the save failed: another process is gone
            raise multihost.lost(err) from None
        self._remove_partial(step)
        raise WriteError(f"cannot write the checkpoint {self.directory / str(step)}: {reason(err)}") from None

    def _progress(self, step: int) -> dict:
        try:
            progress = self.manager.restore(step, args=self._ocp.args.Composite(
                progress=self._ocp.args.JsonRestore()))["progress"]
        except Exception as err:  # noqa: BLE001 - any failure to read the files
            raise _Unreadable(_why(err)) from None
        if not isinstance(progress, dict) or progress.get("updates") != step:
            raise _Unreadable(f"its progress record says {_short(progress)}")
        layout = progress.get("layout")
        if layout is not None and not (
                isinstance(layout, dict) and isinstance(layout.get("stored"), list)
                and all(isinstance(n, str) for n in layout["stored"]) and isinstance(layout.get("zeros", []), list)
                and isinstance(layout.get("same", {}), dict) and isinstance(layout.get("runs", 0), (int, type(None)))):
            raise _Unreadable("its layout record is damaged")
        return dict(progress)

    def _shapes(self, step: int, layout: dict | None) -> dict[str, tuple[tuple[int, ...], str]]:
        """{leaf: (shape, dtype)} of the checkpoint: its layout's record, else orbax's metadata (older ones)."""
        if layout is not None and isinstance(layout.get("shapes"), dict):
            try:
                return {name: (tuple(int(d) for d in shape), str(dtype))
                        for name, (shape, dtype) in layout["shapes"].items()}
            except (TypeError, ValueError):
                raise _Unreadable("its layout record is damaged") from None
        try:
            tree = self._ocp.StandardCheckpointHandler().metadata((self.directory / str(step) / "state").resolve())
            tree = getattr(tree, "tree", tree)
            return {name: (tuple(int(d) for d in m.shape), np.dtype(m.dtype).name) for name, m in tree.items()}
        except Exception as err:  # noqa: BLE001
            raise _Unreadable(_why(err)) from None

    def check(self, step: int, like, expect: Callable[[dict | None], str | None] | None = None) -> dict:
        """The progress record of checkpoint `step` once it is known to belong to the run of `like` (a state of
        the same runs: arrays or ShapeDtypeStructs): CheckpointMismatch (one sentence) when `expect(recorded
        run)` names a difference or a leaf's name, shape or dtype differs; _Unreadable when its files cannot be
        read. Reads no array."""
        where = self.directory / str(step)
        progress = self._progress(step)
        layout = progress.get("layout")
        difference = expect(progress.get("run")) if expect is not None else None
        if difference is None:
            difference = _leaf_difference(self._shapes(step, layout), layout, like, progress.get("run"))
        if difference is not None:
            raise CheckpointMismatch(f"checkpoint {where} does not belong to the run asked for: {difference}; "
                                     "nothing was changed (put run.json back as it was, or train these settings in "
                                     "another --out).")
        return progress

    def inspect(self, like, expect=None) -> tuple[int | None, list[tuple[int, str]]]:
        """(the newest checkpoint that belongs to the run of `like` and whose records can be read, or None; the
        newer ones that cannot be read, with why). CheckpointMismatch as `check`; reads no array, moves nothing."""
        unreadable = []
        for step in reversed(self.steps()):
            try:
                self.check(step, like, expect)
            except _Unreadable as err:
                unreadable.append((step, str(err)))
                continue
            return step, unreadable
        return None, unreadable

    def restore(self, like, expect=None, set_aside: bool = True) -> tuple[Any, dict] | None:
        """(state, progress) of the newest checkpoint that can be read, or None if there is none.

        `like`: a concrete state of the same runs (a fresh init): shapes, dtypes, shardings and the leaves the
        checkpoint does not hold. Each checkpoint is first checked (`check`, with `expect`): one of another run
        raises CheckpointMismatch and nothing is changed. One that cannot be read as files is reported with a
        CheckpointWarning and, with `set_aside`, renamed `<step>.unreadable` (kept: a resumed run writes that
        step again), and the previous one is tried. `self.unreadable` lists the steps passed over.
        """
        self.unreadable: list[tuple[int, str]] = []
        for step in reversed(self.steps()):
            why = None
            try:
                restored = self._restore(step, like, expect)
            except _Unreadable as err:
                why = str(err)
            if multihost.count() > 1:  # unreadable for one process (its shards), unreadable for all
                why = next((text for text in multihost.exchange(why or "") if text), None)
            if why is not None:
                self.unreadable.append((step, why))
                aside = self.set_aside(step) if set_aside else None
                warnings.warn(f"Checkpoint {self.directory}/{step} cannot be restored ({why}); "
                              + (f"moved aside to {aside.name} (kept), " if aside is not None else "")
                              + "falling back to the previous one.", CheckpointWarning, stacklevel=2)
                continue
            return restored
        return None

    def _restore(self, step: int, like, expect) -> tuple[Any, dict]:
        """(state, progress) of checkpoint `step`, checked first (`check`); _Unreadable when its files cannot be
        read or its records do not fit what is stored."""
        ocp = self._ocp
        progress = self.check(step, like, expect)
        layout = progress.pop("layout", None)
        progress.pop("run", None)
        names = dict(named_leaves(like))
        wanted = layout["stored"] if layout is not None else [n for n, x in names.items() if x.size]
        if any(name not in names for name in wanted):
            raise _Unreadable("its layout names a leaf it does not describe")
        saved_runs, runs = (layout or {}).get("runs"), leading_runs(like)
        repad = saved_runs is not None and runs is not None and saved_runs != runs
        target = {}
        for name in wanted:
            x = names[name]
            data = jax.eval_shape(jax.random.key_data, x) if _is_key(x) else x
            if repad:  # saved on another device count: read whole on one device, re-padded below
                target[name] = jax.ShapeDtypeStruct((saved_runs, *data.shape[1:]), data.dtype,
                                                    sharding=jax.sharding.SingleDeviceSharding(
                                                        next(iter(x.sharding.addressable_devices))))
            else:
                target[name] = jax.ShapeDtypeStruct(data.shape, data.dtype, sharding=x.sharding)
        try:
            stored = dict(self.manager.restore(step, args=ocp.args.Composite(
                state=ocp.args.StandardRestore(target)))["state"]) if target else {}
        except Exception as err:  # noqa: BLE001 - the records were right: the array files are not
            if multihost.is_peer_error(err):
                raise multihost.lost(err) from None
            raise _Unreadable(_why(err)) from None
        if repad:
            stored = {name: repad_runs(np.asarray(v), runs) for name, v in stored.items()}
        try:
            state = expand(stored, layout, like)
        except (KeyError, TypeError, ValueError) as err:  # a layout record that does not fit what is stored
            raise _Unreadable(_why(err)) from None
        return state, progress

    def set_aside(self, step: int, why: str = "unreadable") -> pathlib.Path:
        """Rename checkpoint `step` to `<step>.<why>` (`<step>.<why>-2`, ... if taken): kept on disk, no longer one
        of the arm's checkpoints. Returns the new path."""
        source = self.directory / str(step)
        target = self.directory / f"{step}.{why}"
        n = 2
        while target.exists():
            target, n = self.directory / f"{step}.{why}-{n}", n + 1
        with multihost.together():  # process 0 renames it; every process then sees it gone
            if multihost.is_writer():
                try:
                    os.rename(source, target)
                except OSError as err:
                    raise WriteError(f"cannot move {source} aside to {target.name}: {reason(err)}") from None
        target = pathlib.Path(multihost.from_writer(str(target)))
        self.manager.reload()
        return target

    def set_aside_all(self, why: str) -> list[pathlib.Path]:
        """Every checkpoint of the arm moved aside (`set_aside`), newest first."""
        return [self.set_aside(step, why) for step in reversed(self.steps())]

    def _remove_partial(self, step: int | None) -> None:
        """Free what a failed save of `step` took on disk (orbax's temporary directory; process 0 writes it)."""
        if multihost.is_writer():
            for tmp in self.directory.glob(f"{step}.orbax-checkpoint-tmp*"):
                shutil.rmtree(tmp, ignore_errors=True)

    def close(self) -> None:
        """Wait for a save in flight and release the manager. A failed save was reported by `wait`, which follows
        every save but those written behind the next chunk (`release`); one of those that fails here (the run stopped
        by an error or Ctrl-C meanwhile) is not reported: its partial files are removed and `latest` names the
        checkpoint before it. orbax raises the same failure again while closing, dropped here. Nothing is waited
        for once another process was lost (its barriers would never pass)."""
        if multihost.LOST.is_set():
            return
        pending, self._pending = self._pending, None
        try:
            self.manager.wait_until_finished()
        except Exception:  # noqa: BLE001
            if pending is not None:
                self._remove_partial(pending)
        try:
            self.manager.close()
        except Exception:  # noqa: BLE001
            pass
