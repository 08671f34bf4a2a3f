"""Run by test_multihost.py as one process of a sweep: the `cdjax` command (argv as given), which kills itself
(SIGKILL) right after its second round of chunks (in a sweep that starts at update 0), logged and checkpointed, with
the third round's chunks dispatched. Its checkpoint of that round is complete (a round of several processes waits
for its checkpoint's write), so the other processes are not inside a checkpoint's barrier: the next thing they do
with it is an exchange (fetching the third round's metrics), where they find it gone.

With $CDJAX_TEST_STOP_AFTER_JOIN set, it stops itself instead (SIGSTOP) as soon as it has joined the others and JAX
has started: a process that falls silent with its connections open, as a hung host does.

Before it kills itself it checks that every chunk ran from the main thread (several processes must issue their
collectives in one order, so the loop launches no chunk from a thread of its own there): if one did not, it exits
with status 3 instead, and the test that expects the SIGKILL fails."""

import os
import signal
import sys
import threading

from cdjax.runner import arms, loop

_round = loop.Loop.round
_chunk_program = arms.Arm.chunk_program
_calls = []
_threads = set()


def round_(self):
    done = _round(self)
    _calls.append(self.rounds)
    if len(_calls) == 2:
        if _threads != {threading.main_thread().name}:
            print(f"chunks ran in threads {sorted(_threads)}", file=sys.stderr)
            os._exit(3)
        os.kill(os.getpid(), signal.SIGKILL)
    return done


def chunk_program(self):
    program = _chunk_program(self)

    def called(*args):
        _threads.add(threading.current_thread().name)
        return program(*args)

    return called


loop.Loop.round = round_
arms.Arm.chunk_program = chunk_program

if __name__ == "__main__":
    import cdjax.cli
    from cdjax.cli import main

    if os.environ.get("CDJAX_TEST_STOP_AFTER_JOIN"):
        _join = cdjax.cli._join

        def join_then_stop(args):
            _join(args)
            os.kill(os.getpid(), signal.SIGSTOP)

        cdjax.cli._join = join_then_stop
    main()
