"""The processes of one sweep watching one another over the connections they joined on (cdjax.multihost.join).

JAX's runtime notices a lost process through its coordination service's heartbeats, and then ends every other process
itself with a native abort (exit 134, its own log); the callback it offers for that cannot be given from Python in
jax 0.10 (the status it passes has no Python form). So cdjax keeps the connections of the join open for the whole
command: process 0 holds one to every other process, each other process one to process 0, and a thread of each
process sends a heartbeat on them every second and reads what comes back. A peer whose connection closes without a
word (killed, out of memory, its host gone) is noticed at once; a peer silent for `silent_s` (`--heartbeat-timeout`:
stopped, or its network gone) then. Either way this process ends with cdjax's one sentence and exit status 69, before
JAX's runtime (given a longer timeout: `JAX_HEARTBEAT_FACTOR`) would abort it, and wherever its main thread waits: a
collective, a checkpoint's barrier, a compilation, a long chunk.

A process that ends on its own (`ending`: its command's last sentence, any exit status) first tells its peers; they
stand down for it when it finished (status 0: the others finish too), and otherwise allow it `END_GRACE_S` to end
alike (every process of a sweep ends a refusal, a stop or a time limit at the same point) before they end with 69.
Whichever of the main thread and the watch ends the process first says the one sentence; the other stays silent.
"""

from __future__ import annotations

import atexit
import os
import selectors
import socket
import sys
import threading
import time
from typing import Callable

PEER_LOST_STATUS = 69  # EX_UNAVAILABLE: a process of the sweep was lost; the run directory can be resumed
JAX_HEARTBEAT_FACTOR = 2  # JAX's own heartbeat timeout, in units of the watch's: its abort comes only if ours cannot
END_GRACE_S = 30.0  # how long a process that ended with a non-zero status is given for the others to end alike
_BEAT_S = 1.0  # how often each process says it is alive (at most; a quarter of a shorter timeout)

_lock = threading.Lock()  # taken by whichever ends the process first: the main thread (`ending`) or the watch
_current: "_Watch | None" = None


def start(conns: dict[int, socket.socket], me: int, count: int, silent_s: float,
          end: Callable[[str], None] | None = None) -> None:
    """Watch `conns` (peer's process id -> the connection of the join) from a daemon thread until `ending`. `end`
    says the sentence and ends the process (default: stderr, exit 69); tests give their own."""
    global _current
    if not conns:
        return
    _current = _Watch(conns, me, count, silent_s, end or _end_process)
    _current.thread.start()
    if end is None:  # a program that never calls `ending` (a library user's script) tells its peers as it exits
        atexit.register(ending, 0)


def tail(describe: Callable[[], str]) -> Callable[[], str] | None:
    """Set what the sentence of a lost peer adds (where the run stands: "; the previous checkpoints are intact ...");
    returns the one set before. Without a watch: nothing."""
    if _current is None:
        return None
    previous, _current.tail = _current.tail, describe
    return previous


def ending(status: int) -> None:
    """This process ends on its own with `status`: the watch stands down and the peers are told. Blocks for ever where
    the watch has already begun to end the process (its sentence is the one said). Without a watch: nothing."""
    global _current
    watch = _current
    if watch is None:
        return
    with _lock:  # waits for ever where the watch is ending the process
        _current = None
        watch.stop.set()
    for conn in watch.conns.values():
        _send(conn, f"end {status}\n".encode())


def _send(conn: socket.socket, data: bytes) -> None:
    try:
        conn.send(data, socket.MSG_DONTWAIT)
    except OSError:
        pass  # that process is gone, or its buffer is full (it is stopped): its silence says it


def _end_process(sentence: str) -> None:
    """Say `sentence` as the process's last line and end it at once (the main thread may be inside XLA)."""
    try:
        sys.stdout.flush()
    except Exception:  # noqa: BLE001 - best effort: the sentence matters, not the buffered progress
        pass
    os.write(2, f"cdjax: {sentence}\n".encode())
    os._exit(PEER_LOST_STATUS)


class _Watch:
    def __init__(self, conns, me, count, silent_s, end):
        self.conns, self.me, self.count, self.silent_s, self.end = dict(conns), me, count, silent_s, end
        self.tail: Callable[[], str] = lambda: ""
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name="cdjax-peer-watch", daemon=True)

    def _run(self) -> None:
        beat = max(0.05, min(_BEAT_S, self.silent_s / 4))
        self.selector = selectors.DefaultSelector()
        now = time.monotonic()
        self.heard = {peer: now for peer in self.conns}
        self.ended: dict[int, tuple[int, float]] = {}  # peer -> (its exit status, when it said so)
        self.unread = {peer: b"" for peer in self.conns}
        for peer, conn in self.conns.items():
            conn.setblocking(False)
            self.selector.register(conn, selectors.EVENT_READ, peer)
        next_beat = now
        while not self.stop.is_set():
            if (closed := self._read(beat / 2)) is not None:
                return self._lost(closed, "its connection closed")
            now = time.monotonic()
            silent = [peer for peer in self.conns if peer not in self.ended and now - self.heard[peer] > self.silent_s]
            if silent and (closed := self._read(0)) is not None:  # what came while this process itself was held
                return self._lost(closed, "its connection closed")
            for peer in self.conns:
                status, when = self.ended.get(peer, (None, 0.0))
                if status is None and now - self.heard[peer] > self.silent_s:
                    return self._lost(peer, f"it was silent for {self.silent_s:g} s, --heartbeat-timeout")
                if status not in (None, 0) and now - when > END_GRACE_S:
                    return self._lost(peer, f"it ended with exit status {status} and this process did not within "
                                            f"{END_GRACE_S:g} s")
            if all(self.ended.get(peer, (None,))[0] == 0 for peer in self.conns):
                return  # every peer finished: nothing is left to watch
            if now >= next_beat:
                for peer, conn in self.conns.items():
                    if peer not in self.ended:
                        _send(conn, b".\n")
                next_beat = now + beat

    def _read(self, timeout: float) -> int | None:
        """Read what the peers sent within `timeout`: heartbeats and their ends; the peer whose connection closed
        without a word, if any."""
        for key, _ in self.selector.select(timeout=timeout):
            peer = key.data
            try:
                data = key.fileobj.recv(4096)
            except BlockingIOError:
                continue
            except OSError:
                data = b""
            now = time.monotonic()
            if not data:
                self.selector.unregister(key.fileobj)
                if peer not in self.ended:
                    return peer
                continue
            self.heard[peer] = now
            *lines, self.unread[peer] = (self.unread[peer] + data).split(b"\n")
            for line in lines:
                if line.startswith(b"end "):
                    word = line[4:].strip()
                    self.ended[peer] = (int(word) if word.lstrip(b"-").isdigit() else 1, now)
        return None

    def _lost(self, peer: int, how: str) -> None:
        if not _lock.acquire(blocking=False):
            return  # the main thread is ending the process with its own sentence
        if self.stop.is_set():
            _lock.release()
            return
        try:
            where = self.tail()
        except Exception:  # noqa: BLE001 - the sentence is said even when the run's state cannot be described
            where = ""
        try:
            # the words of `cdjax.multihost.lost` (the same end noticed in an exchange), the peer unnamed: with more
            # than two processes the one lost may be another than the one this process is connected to
            self.end(f"Process {self.me} of {self.count} stopped: another process of the sweep stopped answering "
                     f"(killed, or its host failed: {how}){where}")
        finally:  # reached only where `end` returns (a test's): the watch is over
            _forget(self)
            _lock.release()


def _forget(watch: _Watch) -> None:
    global _current
    if _current is watch:
        _current = None
