"""How the processes of one sweep join, before JAX starts: a channel of their own on the coordinator's port.

Process 0 listens on the coordinator's port; every other process connects to it (again and again until it answers)
and sends its process id, the number of processes and the arguments that must match (`arguments`: out, arms,
seeds, steps, config, grid). Process 0 waits until every other process has joined, compares, and answers each one
"go" or the one sentence that refuses the sweep (arguments that differ, a process id given twice, another number
of processes), which every process then raises. Then process 0 stops listening and JAX's coordination service takes
the port; the connections stay open, for the processes to watch one another (cdjax.multihost.watch). Every wait is
bounded by the join timeout and says first what it waits for; a process that does not join in time, or a process 0
that goes away, ends the others with `PeerLost` (exit 69). SIGTERM raised in Python (the `cdjax` command's handler)
ends a waiting process, since every wait here is a short socket timeout in a loop.

Two processes given --process-id 0: the second cannot listen on the port the first holds, so it joins as a client
and is refused with the first, by the first. A process that comes once its sweep has started (JAX's coordination
service holds the port; a duplicate process id, or a command run twice) or to a port another program holds is
answered in another protocol than this one, and refused alone: the sweep that holds the port goes on.
"""

from __future__ import annotations

import json
import socket
import time
from typing import Callable

from cdjax.errors import PeerLost
from cdjax.protocol import ConfigError

_POLL_S = 0.5  # how often a wait looks again (and lets a signal's handler run)
_LINE_BYTES = 1 << 16  # the most one message may hold
FOREIGN = "foreign"  # what `_receive` gives for an answer in another protocol (JAX's coordination service, a web server)


def _address(coordinator: str) -> tuple[str, int]:
    host, _, port = coordinator.rpartition(":")
    return host.strip("[]"), int(port)


def _send(conn: socket.socket, message: dict) -> None:
    conn.sendall(json.dumps(message).encode() + b"\n")


def _receive(conn: socket.socket, deadline: float) -> dict | str | None:
    """One message; None when the other end closed or the deadline passed first, having said nothing; FOREIGN when
    it said something that is not a message of this protocol."""
    data = b""
    while not data.endswith(b"\n") and len(data) < _LINE_BYTES:
        conn.settimeout(max(0.01, min(_POLL_S, deadline - time.monotonic())))
        try:
            chunk = conn.recv(4096)
        except socket.timeout:
            if time.monotonic() >= deadline:
                return None
            continue
        except OSError:
            chunk = b""
        if not chunk:
            return FOREIGN if data else None
        data += chunk
    try:
        message = json.loads(data.decode("utf-8", "replace"))
    except json.JSONDecodeError:
        return FOREIGN
    return message if isinstance(message, dict) else FOREIGN


def difference(mine: dict, theirs: dict, process: int) -> str | None:
    """The sentence refusing a sweep whose process `process` was given `theirs` where process 0 has `mine`."""
    for key in sorted(set(mine) | set(theirs)):
        if mine.get(key) != theirs.get(key):
            return (f"the processes of this sweep were given different arguments: process {process}'s {key} is "
                    f"{theirs.get(key, '(not given)')} where process 0's is {mine.get(key, '(not given)')}; every "
                    "process runs the same command (only --process-id differs), so none was started.")
    return None


def rendezvous(coordinator: str, num_processes: int, process_id: int, arguments: dict, timeout_s: float,
               say: Callable[[str], None]) -> dict[int, socket.socket]:
    """Join the other processes (see the module's docstring); returns once every process has joined and agreed, with
    the connections kept open (process id -> connection: process 0 holds one to each other process, the others
    one to process 0). ConfigError for arguments that differ or a process id given twice (the same sentence on every
    process), or a port that answers in another protocol; PeerLost when the others do not join within `timeout_s`
    or process 0 goes away."""
    host, port = _address(coordinator)
    deadline = time.monotonic() + timeout_s
    server = None
    if process_id == 0:
        try:
            server = socket.create_server(("", port), family=socket.AF_INET6, dualstack_ipv6=True) \
                if socket.has_dualstack_ipv6() else socket.create_server(("", port))
        except OSError:
            server = None  # the port is held: by another process 0 (refused as a duplicate by it), or not ours
    if server is not None:
        with server:
            return _serve(server, host, port, num_processes, arguments, deadline, timeout_s, say)
    return {0: _join(host, port, num_processes, process_id, arguments, deadline, timeout_s, say)}


def _serve(server: socket.socket, host: str, port: int, num_processes: int, arguments: dict, deadline: float,
           timeout_s: float, say: Callable[[str], None]) -> dict[int, socket.socket]:
    others = set(range(1, num_processes))
    say(f"Process 0 of {num_processes}: waiting up to {timeout_s:g} s (--join-timeout) for process(es) "
        f"{', '.join(map(str, sorted(others)))} to join at {host}:{port}.")
    joined: dict[int, socket.socket] = {}
    conns: list[socket.socket] = []  # every process that joined, duplicates included: each gets the answer
    kept: dict[int, socket.socket] = {}
    refusal = None
    server.settimeout(_POLL_S)
    try:
        while set(joined) != others and refusal is None:
            if time.monotonic() >= deadline:
                missing = ", ".join(map(str, sorted(others - set(joined))))
                for conn in conns:
                    _send_quietly(conn, {"lost": f"process(es) {missing} did not join within {timeout_s:g} s"})
                raise PeerLost(f"Process 0 of {num_processes} stopped: process(es) {missing} did not join within "
                               f"{timeout_s:g} s (--join-timeout); start every process with the same --coordinator "
                               f"{host}:{port} and --num-processes {num_processes}; nothing was started.", True)
            try:
                conn, _ = server.accept()
            except socket.timeout:
                continue
            message = _receive(conn, min(deadline, time.monotonic() + 10))
            message = message if isinstance(message, dict) else {}
            process, count = message.get("id"), message.get("n")
            if not isinstance(process, int):
                conn.close()  # not one of ours (a port scan, a stray connection): ignored
                continue
            conns.append(conn)
            if count != num_processes:
                refusal = (f"the processes of this sweep were given different --num-processes: process {process} "
                           f"has {count} where process 0 has {num_processes}; none was started.")
            elif process == 0 or process in joined:
                refusal = (f"two processes of this sweep were given --process-id {process}; give each process its "
                           f"own number from 0 to {num_processes - 1}; none was started.")
            else:
                refusal = difference(arguments, message.get("args", {}), process)
                joined[process] = conn
        if refusal is None:  # a duplicate that connected with the last one, still queued, is refused with it
            refusal = _queued_duplicate(server, conns, num_processes)
        for conn in conns:
            _send_quietly(conn, {"refuse": refusal} if refusal is not None else {"go": True})
        if refusal is None:
            kept = joined  # open beside JAX's service on the port, until the process ends
            return joined
        for conn in conns:  # refused: each process closes first, having read the refusal
            _receive(conn, time.monotonic() + 5)
    finally:
        for conn in conns:
            if conn not in kept.values():
                conn.close()
    raise ConfigError(refusal)


def _queued_duplicate(server: socket.socket, conns: list, num_processes: int) -> str | None:
    """The refusal for a process that connected after every process had joined (so given a number already taken),
    found among the connections still queued; None when there is none."""
    server.settimeout(0.2)
    try:
        conn, _ = server.accept()
    except OSError:
        return None
    message = _receive(conn, time.monotonic() + 5)
    if not isinstance(message, dict) or not isinstance(message.get("id"), int):
        conn.close()
        return None
    conns.append(conn)
    return (f"two processes of this sweep were given --process-id {message['id']}; give each process its own number "
            f"from 0 to {num_processes - 1}; none was started.")


def _send_quietly(conn: socket.socket, message: dict) -> None:
    try:
        _send(conn, message)
    except OSError:
        pass  # that process is gone: it has its own end


def _join(host: str, port: int, num_processes: int, process_id: int, arguments: dict, deadline: float,
          timeout_s: float, say: Callable[[str], None]) -> socket.socket:
    said = False
    while True:
        if time.monotonic() >= deadline:
            raise PeerLost(f"Process {process_id} of {num_processes} stopped: process 0 did not answer at {host}:"
                           f"{port} within {timeout_s:g} s (--join-timeout); start it with the same --coordinator, "
                           "or check that the address and port are right; nothing was started.", True)
        try:
            conn = socket.create_connection((host, port), timeout=max(0.1, min(2.0, deadline - time.monotonic())))
        except OSError:
            if not said:
                say(f"Process {process_id} of {num_processes}: waiting up to {timeout_s:g} s (--join-timeout) for "
                    f"process 0 at {host}:{port}.")
                said = True
            time.sleep(_POLL_S)
            continue
        break
    try:
        _send(conn, {"id": process_id, "n": num_processes, "args": arguments})
        answer = _receive(conn, deadline)
    except BaseException:
        conn.close()
        raise
    if isinstance(answer, dict) and "go" in answer:
        return conn  # kept open: the processes watch one another over it
    conn.close()
    if answer == FOREIGN:
        raise ConfigError(f"the coordinator's port {host}:{port} answers, but not as process 0 of a cdjax sweep "
                          f"waiting for its processes: a sweep given this --coordinator has already started (JAX's "
                          f"service holds the port, and --process-id {process_id} of it is taken), or another "
                          "program holds the port; give every process of this sweep a free port; nothing was started.")
    if answer is None:
        raise PeerLost(f"Process {process_id} of {num_processes} stopped: process 0 went away before every process "
                       f"had joined (or did not answer within {timeout_s:g} s, --join-timeout); nothing was started.",
                       True)
    if "refuse" in answer:
        raise ConfigError(str(answer["refuse"]))
    if "lost" in answer:
        raise PeerLost(f"Process {process_id} of {num_processes} stopped: {answer['lost']} (--join-timeout); nothing "
                       "was started.", True)
