"""Several processes sharing one sweep (one per host, or one per GPU): JAX's distributed runtime, seen from the
host side.

    cdjax sweep --distributed ...       # SLURM, Open MPI, Cloud TPU: JAX finds the coordinator, the count and the id
    cdjax sweep --distributed --coordinator HOST0:1234 --num-processes 2 --process-id I ...   # anywhere else

Every process runs the same command: the same programs, called in the same order, on one mesh over every process's
devices (`cdjax.sweep.runs_mesh()`), each process computing the runs on its own devices. Process 0 is the writer:
it alone writes run.json, the logs, TensorBoard, the evaluations and the plots, and holds the run directory's lock;
orbax writes each process's part of a checkpoint (the run directory must be on a file system every process sees).

What one process decides alone (a refusal, a failed write, a Ctrl-C or SIGTERM, its --time-limit) is exchanged at
fixed points (`exchange`, `together`), so that every process refuses, stops after the same chunk or fails with the
same sentence. A process that dies is noticed by the others at their next exchange (at once: its connections close),
or wherever they wait (a checkpoint's barrier, a compilation, a long chunk) by the watch over the connections of the
join (`cdjax.multihost.watch`: at once when its connection closes, after --heartbeat-timeout when it falls silent);
they end with one sentence (`PeerLost`, exit 69), before JAX's runtime would abort them. The run directory stays
resumable either way: a checkpoint is complete only once every process has written its part.

In one process (no --distributed) every function here is the identity, or does what one process would.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import re
import signal
import sys
import threading

import jax
import numpy as np

from cdjax.errors import CheckpointMismatch, PeerLost, Refused, RunDirError, WriteError
from cdjax.multihost import watch
from cdjax.multihost.join import rendezvous
from cdjax.multihost.watch import PEER_LOST_STATUS, ending, tail  # noqa: F401  (cdjax.multihost.ending, ...)
from cdjax.protocol import ConfigError

DEFAULT_HEARTBEAT_S = 100  # jax.distributed.initialize's own default: a silent process is declared lost after this
DEFAULT_JOIN_S = 300  # how long the processes wait for one another to join (and JAX's start-up), by default
_MESSAGE_BYTES = 2048  # what one process can say in an exchange (a sentence; longer ones are cut)

# Set once a peer was lost: from then on nothing waits for the others (checkpoint managers are not closed, since
# closing waits at a barrier that the dead process will never reach).
LOST = threading.Event()


def count() -> int:
    """Processes in this sweep (1 without --distributed)."""
    return jax.process_count()


def index() -> int:
    """This process's number (0 is the writer)."""
    return jax.process_index()


def is_writer() -> bool:
    """Whether this process writes the run directory (process 0; the only process without --distributed)."""
    return jax.process_index() == 0


def _check_coordinator(coordinator: str) -> None:
    host, _, port = coordinator.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ConfigError(f"--coordinator must be HOST:PORT (e.g. node001:1234, the address of process 0 and a free "
                          f"port), got {coordinator!r}.")


def initialize(coordinator: str | None = None, num_processes: int | None = None, process_id: int | None = None,
               heartbeat_s: int | None = None, arguments: dict | None = None, join_s: float = DEFAULT_JOIN_S,
               say=None) -> None:
    """Join the other processes of the sweep (`jax.distributed.initialize`), before anything runs in JAX.

    Arguments left None are found by JAX in SLURM, Open MPI and Cloud TPU environments. On the CPU, the processes'
    collectives go over gloo. First the processes join over a channel of their own on the coordinator's port
    (`rendezvous`): `arguments` (what must match: out, arms, seeds, steps, config, grid) are
    compared and a duplicate process id refused, every process with the same sentence, before JAX starts; every wait
    is bounded by `join_s` and says what it waits for (`say`); then the processes watch one another over the
    connections they joined on (`watch`: a process lost from then on ends this one with exit 69 and one sentence,
    within `heartbeat_s` where it went silent). ConfigError (one sentence) when the arguments cannot work, differ
    between processes or JAX has already started; PeerLost when the others do not join in time or one is lost during
    the start-up."""
    from jax._src import xla_bridge

    if coordinator is not None:
        _check_coordinator(coordinator)
    if num_processes is not None and num_processes < 1:
        raise ConfigError(f"--num-processes must be at least 1, got {num_processes}.")
    if process_id is not None and (process_id < 0 or (num_processes is not None and process_id >= num_processes)):
        raise ConfigError(f"--process-id must be from 0 to --num-processes - 1, got {process_id}"
                          + (f" of {num_processes}." if num_processes is not None else "."))
    if xla_bridge.backends_are_initialized():
        raise ConfigError("--distributed must join the other processes before JAX starts, and JAX has already "
                          "started in this process; call cdjax.multihost.initialize first.")
    with contextlib.suppress(AttributeError, ValueError):  # CPU collectives (the default in jax 0.10, set for others)
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
    coordinator, num_processes, process_id = _found(coordinator, num_processes, process_id)
    heartbeat_s = heartbeat_s or DEFAULT_HEARTBEAT_S
    if None not in (coordinator, num_processes, process_id) and num_processes > 1:
        conns = rendezvous(coordinator, num_processes, process_id, arguments or {}, join_s, say or _stderr)
        watch.start(conns, process_id, num_processes, heartbeat_s)
        watch.tail(lambda: " during JAX's start-up; nothing was started, run the command again.")
    # Inside JAX's start-up nothing Python runs in this thread until it returns: SIGTERM ends the process as the
    # system does (the watch's thread still ends it with its sentence when a peer is lost meanwhile).
    previous = signal.signal(signal.SIGTERM, signal.SIG_DFL) if threading.current_thread() is threading.main_thread() \
        else None
    try:
        jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes,
                                   process_id=process_id, initialization_timeout=max(1, math.ceil(join_s)),
                                   heartbeat_timeout_seconds=watch.JAX_HEARTBEAT_FACTOR * heartbeat_s)
    except (ValueError, TypeError) as err:  # what JAX could not find (no SLURM, Open MPI or TPU environment)
        missing = {"coordinator": "the coordinator's address", "number of processes": "the number of processes",
                   "process id": "this process's number"}
        what = next((words for key, words in missing.items() if key in str(err).lower()), _first_line(err))
        raise ConfigError(f"--distributed could not find {what} (no SLURM, Open MPI or Cloud TPU environment says "
                          "it); give --coordinator HOST:PORT --num-processes N --process-id I.") from None
    except RuntimeError as err:
        if num_processes is not None and num_processes > 1 and coordinator is not None:  # they had joined: one left
            raise PeerLost(f"Process {process_id} of {num_processes} stopped: another process stopped during JAX's "
                           f"start-up ({_first_line(err)[:160]}); nothing was started, run the sweep again.", True
                           ) from None
        raise ConfigError(f"--distributed could not join the other processes ({_first_line(err)}); check that every "
                          "process was started with the same --coordinator and --num-processes and that the "
                          "coordinator's port is free and reachable.") from None
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    with _quiet_stdout():  # gloo says on stdout that it connected, at the first collective: here, not in the output
        exchange("")
    # JAX has started; until the command says where its run stands (its own tail), nothing has been written
    watch.tail(lambda: " after JAX's start-up, before the command began; nothing was written, run the command again.")


def _stderr(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def _found(coordinator, num_processes, process_id):
    """The coordinator, number of processes and process id, those not given found as JAX finds them (SLURM, Open
    MPI, Cloud TPU); what cannot be found stays None (JAX's initialize then says so)."""
    if None not in (coordinator, num_processes, process_id):
        return coordinator, num_processes, process_id
    try:
        from jax._src import clusters

        return clusters.ClusterEnv.auto_detect_unset_distributed_params(coordinator, num_processes, process_id, None,
                                                                        None, None)[:3]
    except Exception:  # noqa: BLE001 - nothing found, or a JAX without this function: JAX's initialize says it
        return coordinator, num_processes, process_id


@contextlib.contextmanager
def _quiet_stdout():
    """File descriptor 1 sent to /dev/null inside (what libraries print from C++ as well as from Python)."""
    sys.stdout.flush()
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


def _first_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
    return text[:300]


# Words of the errors a lost peer causes: gloo's broken connections, the coordination service's barriers and
# heartbeats, and the RPCs to a coordinator that is gone.
_LOST_WORDS = re.compile(r"gloo|heartbeat|barrier|unavailable|coordination service|connection reset|connection closed|"
                         r"connection refused|socket closed|deadline_exceeded|peer", re.IGNORECASE)


def is_peer_error(err: BaseException) -> bool:
    """Whether `err` (raised by a collective, an exchange or a checkpoint's barrier) says another process is gone."""
    return count() > 1 and not isinstance(err, KeyboardInterrupt) and bool(_LOST_WORDS.search(str(err)))


def lost(err: BaseException) -> PeerLost:
    """The PeerLost that `err` says (sets LOST); the runtime's own words go to the library log. This process's end is
    claimed from the watch first (`ending`: the peers are told), so that only one sentence is said: where the watch has
    already begun to end the process, this blocks until it has."""
    ending(PEER_LOST_STATUS)
    LOST.set()
    logging.getLogger(__name__).warning("process %d of %d lost another process: %s", index(), count(), err)
    text = str(err).lower()
    how = ("its heartbeats stopped" if "heartbeat" in text else "its connection closed" if "connection" in text
           else "the coordinator cannot be reached" if "coordination" in text or "unavailable" in text
           else _first_line(err)[:120])
    return PeerLost(f"Process {index()} of {count()} stopped: another process of the sweep stopped answering "
                    f"(killed, or its host failed: {how})")


def _gather(array: np.ndarray) -> np.ndarray:
    """[P, ...]: every process's `array` (a collective)."""
    from jax.experimental import multihost_utils

    try:
        return np.asarray(multihost_utils.process_allgather(array))
    except KeyboardInterrupt:
        raise
    except Exception as err:  # noqa: BLE001 - whatever the runtime raises when a peer is gone
        if is_peer_error(err):
            raise lost(err) from None
        raise


def exchange(text: str) -> list[str]:
    """Every process's `text`, in process order, on every process (a collective: every process calls it at the same
    point of the same command). In one process: [text]."""
    if count() == 1:
        return [text]
    data = text.encode("utf-8")[:_MESSAGE_BYTES]
    buffer = np.zeros(_MESSAGE_BYTES + 4, np.uint8)
    buffer[:4] = np.frombuffer(np.uint32(len(data)).tobytes(), np.uint8)
    buffer[4:4 + len(data)] = np.frombuffer(data, np.uint8)
    rows = _gather(buffer)
    return [bytes(row[4:4 + int(np.frombuffer(row[:4].tobytes(), np.uint32)[0])]).decode("utf-8", "replace")
            for row in rows]


def from_writer(text: str) -> str:
    """Process 0's `text`, on every process (a collective)."""
    return exchange(text if is_writer() else "")[0]


# What a process refused or failed at, as one letter in an exchange: the same class is raised on every process.
def _kinds():
    return {"W": WriteError, "M": CheckpointMismatch, "D": RunDirError, "C": ConfigError}


def _encode(err: BaseException | None) -> str:
    if err is None:
        return ""
    letter = next((k for k, cls in _kinds().items() if isinstance(err, cls)), "D")
    return letter + str(err)


def settle(err: BaseException | None) -> None:
    """Exchange what each process refused or failed at (None: nothing) and raise, on every process, the first one
    (a process raises its own; the others the same sentence, of the same class). In one process: raise `err`."""
    if count() == 1:
        if err is not None:
            raise err
        return
    said = exchange(_encode(err))
    first = next((text for text in said if text), None)
    if first is None:
        return
    if err is not None:
        raise err
    cls = _kinds().get(first[0], Refused)
    raise cls(first[1:])


@contextlib.contextmanager
def together():
    """Run the block on every process; then every process raises the first one-sentence refusal any process met
    inside it (ConfigError, RunDirError and its kinds), or goes on. Other exceptions (a KeyboardInterrupt, a bug)
    leave at once: the others then see this process gone. In one process, the block as it is."""
    if count() == 1:
        yield
        return
    try:
        yield
    except (ConfigError, RunDirError) as err:
        settle(err)
    else:
        settle(None)


def fetch(tree):
    """Device arrays -> numpy, whole, on every process (a collective in several processes: every process calls it
    with the same arrays)."""
    if count() == 1:
        return jax.tree.map(np.asarray, jax.device_get(tree))
    from jax.experimental import multihost_utils

    try:
        return jax.tree.map(np.asarray, multihost_utils.process_allgather(tree, tiled=True))
    except KeyboardInterrupt:
        raise
    except Exception as err:  # noqa: BLE001
        if is_peer_error(err):
            raise lost(err) from None
        raise


def _is_key(x) -> bool:
    return hasattr(x, "dtype") and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def put(tree, sharding):
    """Every leaf (the same values on every process) placed with `sharding`, which may span every process's devices.
    In one process: jax.device_put."""
    if count() == 1:
        return jax.device_put(tree, sharding)

    def one(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:  # already global
            return x if x.sharding == sharding else jax.jit(lambda a: a, out_shardings=sharding)(x)
        if _is_key(x):
            return jax.random.wrap_key_data(one(jax.random.key_data(x)), impl=jax.random.key_impl(x))
        return jax.device_put(np.asarray(x), sharding)

    return jax.tree.map(one, tree)


def resume_flags() -> str:
    """What a resume command adds to `cdjax sweep --out DIR --resume` for this sweep's processes."""
    return " --distributed" if count() > 1 else ""
