"""Run by test_multihost.py as one process of a sweep: the `cdjax` command (argv as given), which kills itself
(SIGKILL) right after its second round of chunks (in a sweep that starts at update 0), logged and checkpointed, with
the third round's chunks dispatched. Its checkpoint of that round is complete (a round of several processes waits
for its checkpoint's write), so the other processes are not inside a checkpoint's barrier: the next thing they do
with it is an exchange (fetching the third round's metrics), where they find it gone."""

import os
import signal

from cdjax.runner import loop

_round = loop.Loop.round
_calls = []


def round_(self):
    done = _round(self)
    _calls.append(self.rounds)
    if len(_calls) == 2:
        os.kill(os.getpid(), signal.SIGKILL)
    return done


loop.Loop.round = round_

if __name__ == "__main__":
    from cdjax.cli import main

    main()
