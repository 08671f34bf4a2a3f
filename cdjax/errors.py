"""The errors that more than one layer of cdjax raises, each one sentence meant for the user.

They live here, below every module that raises or catches them, so that the run directory (`cdjax.io`), its
checkpoints (`cdjax.io.checkpoints`) and the processes of a sweep (`cdjax.multihost`) share them without importing
one another in a circle. Their old homes re-export them: `from cdjax.io import RunDirError` and
`from cdjax.multihost import PeerLost` keep working. `cdjax.protocol.ConfigError` (input that cannot run) stays in
the protocol.
"""

from __future__ import annotations

import contextlib
import os
import re
import threading

# Set once any write failed in this process. After a failed checkpoint write, tensorstore's own threads go on
# completing orbax's abandoned writes and print "Event loop is closed" tracebacks; the `cdjax` command drops
# what threads created outside Python write to stderr from then on (cdjax.cli).
WRITE_FAILED = threading.Event()


class RunDirError(ValueError):
    """A run directory that cannot be used as asked; the message is one sentence meant for the user."""


class WriteError(RunDirError):
    """Writing into the run directory failed (disk full, no permission); one sentence."""

    def __init__(self, *args):
        super().__init__(*args)
        WRITE_FAILED.set()


class CheckpointMismatch(RunDirError):
    """A readable checkpoint of another run than the one asked for (one sentence; nothing was changed)."""


class CheckpointWarning(UserWarning):
    """A checkpoint could not be restored and an older one is used instead."""


class PeerLost(RuntimeError):
    """Another process of the sweep stopped answering (killed, or its host failed); one sentence. `complete`: the
    sentence already says what is intact and how to go on."""

    def __init__(self, sentence: str, complete: bool = False):
        super().__init__(sentence)
        self.complete = complete


class Refused(ValueError):
    """What another process refused or failed at, said by this one (the same sentence)."""


def reason(err: BaseException) -> str:
    """What an OS-level failure was, in words: "No space left on device" also from orbax's wrapped errors."""
    if isinstance(err, OSError) and err.strerror:
        return err.strerror
    code = re.search(r"os_error_code='?(\d+)", str(err))
    if code:
        return os.strerror(int(code.group(1)))
    text = str(err).splitlines()[0] if str(err) else type(err).__name__
    return text[:200]


@contextlib.contextmanager
def writing(path: str | os.PathLike):
    """Turn an OSError raised inside into a WriteError naming `path`."""
    try:
        yield
    except OSError as err:
        raise WriteError(f"cannot write {path}: {reason(err)}") from None
