"""What the user sees during a sweep, and what they do not: progress, the training clock, Ctrl-C, and the
libraries' own messages (diverted into the run directory's cdjax.log)."""

from __future__ import annotations

import contextlib
import logging
import math
import pathlib
import signal
import sys
import threading
import time
import traceback
import warnings
from typing import Callable

LINE_EVERY_S = 5.0  # without a terminal, a progress line at most this often (and at the end)


class Clock:
    """Training wall-clock: the chunks with their logging and checkpoints; not setup, compilation, evaluation."""

    def __init__(self):
        self.total = 0.0
        self._start = None

    @contextlib.contextmanager
    def running(self):
        self._start = time.perf_counter()
        try:
            yield
        finally:
            self.total += time.perf_counter() - self._start
            self._start = None

    def now(self) -> float:
        return self.total + (time.perf_counter() - self._start if self._start is not None else 0.0)


class Terminated(KeyboardInterrupt):
    """SIGTERM (what SLURM, Kubernetes and `timeout` send) outside the chunk loop, raised by `raise_on_sigterm`."""


class Stopped(KeyboardInterrupt):
    """A command stopped by the user (Ctrl-C or SIGTERM); `sentence` says what is true for what was interrupted."""

    def __init__(self, sentence: str, terminated: bool = False):
        super().__init__(sentence)
        self.sentence = sentence
        self.terminated = terminated  # SIGTERM (exit status 143) rather than Ctrl-C (130)


def stopped(err: KeyboardInterrupt, sentence: str) -> Stopped:
    """`err` as a Stopped saying `sentence` (an inner Stopped says what is true more precisely and is kept)."""
    if isinstance(err, Stopped):
        return err
    return Stopped(sentence, terminated=isinstance(err, Terminated) or getattr(err, "signum", None) == signal.SIGTERM)


@contextlib.contextmanager
def raise_on_sigterm():
    """While inside (in the main thread), SIGTERM raises `Terminated` as Ctrl-C raises KeyboardInterrupt, so that a
    command ends with its one sentence and its locks released; the chunk loop's StopFlag treats it as the first
    Ctrl-C instead."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handle(signum, frame):
        raise Terminated

    previous = signal.signal(signal.SIGTERM, handle)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


class StopFlag:
    """SIGINT or SIGTERM sets a flag (the loop stops after the chunk in flight, checkpointed); a second SIGINT
    raises at once. SIGTERM never stops at once: the grace period a scheduler gives before SIGKILL is for the
    checkpoint. `signum` is the signal that asked first."""

    def __init__(self, say: Callable[[str], None]):
        self.requested = False
        self.forced = False
        self.signum: int | None = None
        self.say = say
        self._previous: dict[int, object] = {}

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for signum in (signal.SIGINT, signal.SIGTERM):
                self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def _handle(self, signum, frame):
        if self.requested and signum == signal.SIGINT:
            self.forced = True
            signal.signal(signal.SIGINT, self._previous.get(signal.SIGINT) or signal.default_int_handler)
            raise KeyboardInterrupt
        if self.requested:
            return
        self.requested, self.signum = True, signum
        again = "Ctrl-C again to stop now" if signum == signal.SIGINT else "SIGTERM; Ctrl-C twice stops now"
        self.say(f"Stopping after the chunk in flight and saving a checkpoint ({again}).")

    def __exit__(self, *exc):
        for signum, previous in self._previous.items():
            signal.signal(signum, previous if previous is not None else signal.SIG_DFL)
        self._previous = {}
        return False


def si(x: float) -> str:
    """1234567 -> "1.23M"."""
    for unit, size in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if abs(x) >= size:
            return f"{x / size:.3g}{unit}"
    return f"{x:.0f}"


class Progress:
    """A live bar on a terminal, else a line every LINE_EVERY_S; `say` prints a sentence above it. `quiet`: neither
    (the processes of a sweep other than its writer, cdjax.multihost)."""

    def __init__(self, enabled: bool, total_steps: int, quiet: bool = False):
        from rich.console import Console

        self.console = Console(stderr=True, highlight=False)
        self.quiet = quiet
        self.enabled = enabled and not quiet
        self.total = total_steps
        self.bar = None
        self.last_line = -float("inf")
        if enabled and self.console.is_terminal:
            from rich.progress import BarColumn, TextColumn
            from rich.progress import Progress as Bar

            self.bar = Bar(BarColumn(bar_width=12), TextColumn("{task.fields[steps]}"),
                           TextColumn("{task.fields[rate]}"), TextColumn("{task.fields[eta]}"),
                           TextColumn("{task.fields[returns]}"), console=self.console)
            self.task = self.bar.add_task("training", total=total_steps, steps="", rate="", eta="", returns="")

    def say(self, text: str) -> None:
        if self.quiet:
            return
        if self.bar is not None:
            self.bar.console.print(text)
        else:
            print(text, file=sys.stderr, flush=True)

    def __enter__(self):
        if self.bar is not None:
            self.bar.start()
        return self

    def __exit__(self, *exc):
        if self.bar is not None:
            self.bar.stop()
        return False

    def update(self, steps_done: int, rate: float, returns: dict[str, float], eta_s: float, note: str = "") -> None:
        """`note`: appended to the returns (e.g. the runs that skipped non-finite steps)."""
        if not self.enabled:
            return
        eta = f"eta {int(eta_s) // 60}:{int(eta_s) % 60:02d}" if math.isfinite(eta_s) else ""
        ret = "  ".join(f"{arm} {value:.1f}" for arm, value in returns.items()) + (f"  {note}" if note else "")
        if self.bar is not None:
            self.bar.update(self.task, completed=steps_done, steps=f"{si(steps_done)}/{si(self.total)} steps",
                            rate=f"{si(rate)} steps/s", eta=eta, returns=f"return {ret}")
        elif time.perf_counter() - self.last_line >= LINE_EVERY_S or steps_done >= self.total:
            self.last_line = time.perf_counter()
            pct = 100.0 * steps_done / max(self.total, 1)
            self.say(f"{steps_done:,}/{self.total:,} env steps per run ({pct:.0f}%)  {rate:,.0f} steps/s  {eta}  "
                     f"return: {ret}")


class _QuietFileHandler(logging.FileHandler):
    """A log file that drops what it cannot write (a full disk) instead of printing logging's own traceback."""

    def handleError(self, record):  # noqa: N802 - logging's name
        pass

    def flush(self):
        try:
            super().flush()
        except OSError:  # what is buffered when the disk is full is dropped like every other line
            pass

    def close(self):
        try:
            super().close()
        except OSError:
            pass


@contextlib.contextmanager
def library_log(path: pathlib.Path | None, say: Callable[[str], None]):
    """Send what the libraries say (Python logging, including absl's and asyncio's; warnings; exceptions in
    threads and in finalizers) to the file `path` instead of the terminal while inside. cdjax's own CheckpointWarning is
    said (one line) instead. With path None, nothing is diverted."""
    if path is None:
        yield
        return
    from cdjax.io import CheckpointWarning

    root = logging.getLogger()
    handler = _QuietFileHandler(path, delay=True)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    saved_handlers, saved_level = root.handlers[:], root.level
    saved_showwarning, saved_hook = warnings.showwarning, threading.excepthook

    def showwarning(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, CheckpointWarning):
            say(str(message))
        else:
            logging.getLogger("py.warnings").warning(warnings.formatwarning(message, category, filename, lineno, line))

    def thread_hook(args):
        logging.getLogger("threading").error("exception in thread %s:\n%s", getattr(args.thread, "name", "?"),
                                             "".join(traceback.format_exception(args.exc_type, args.exc_value,
                                                                                args.exc_traceback)))

    def unraisable_hook(args):
        logging.getLogger("unraisable").error("%s: %s\n%s", args.err_msg or "Exception ignored in", args.object,
                                              "".join(traceback.format_exception(args.exc_type, args.exc_value,
                                                                                 args.exc_traceback)))

    saved_unraisable = sys.unraisablehook
    root.handlers = [handler]
    root.setLevel(logging.WARNING)
    warnings.showwarning, threading.excepthook, sys.unraisablehook = showwarning, thread_hook, unraisable_hook
    try:
        yield
    finally:
        root.handlers = saved_handlers
        root.setLevel(saved_level)
        warnings.showwarning, threading.excepthook, sys.unraisablehook = (saved_showwarning, saved_hook,
                                                                          saved_unraisable)
        handler.close()
