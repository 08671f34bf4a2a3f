"""Run by test_multihost.py as one process of a sweep: the `cdjax` command (argv as given), which kills itself
(SIGKILL) right after the exchange that follows its second round of chunks (in a sweep that starts at update 0). Its
checkpoint of that round is complete, so the other processes are not inside a checkpoint's barrier: the next thing
they do with it is an exchange (fetching the third round's metrics), where they find it gone."""

import os
import signal

from cdjax.runner import loop

_stop_asked = loop.Loop.stop_asked
_calls = []


def stop_asked(self):
    asked = _stop_asked(self)  # an exchange with the other processes (the first is before the first round)
    _calls.append(self.rounds)
    if len(_calls) == 3:
        os.kill(os.getpid(), signal.SIGKILL)
    return asked


loop.Loop.stop_asked = stop_asked

if __name__ == "__main__":
    from cdjax.cli import main

    main()
