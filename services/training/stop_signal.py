"""Stop an in-process training run between two steps, on SIGINT or SIGTERM, with its checkpoint saved.

    with graceful_stop() as stop_requested:
        outcome = train_loop(config, session, stop_requested=stop_requested)

Inside the block the first SIGINT (Ctrl-C) or SIGTERM (`kill`, a parent's clean-up) only raises a flag:
`stop_requested()` then returns the signal's name ("SIGINT"), and the loop saves a checkpoint at the
step it just finished and returns. A second SIGINT raises KeyboardInterrupt at once (the way out when a
step takes too long to wait for); a SIGTERM after the first signal changes nothing (already stopping).
The previous handlers come back when the block ends; a signal the process ignores (SIG_IGN, e.g. SIGINT
of a job started in the background) stays ignored.

Why: the default handlers end a run mid-step, so a rerun resumed from its last periodic checkpoint —
up to `checkpoint_every` steps back (100–200 steps, 10–25 minutes of a small-preset flow stage on one
thread). Only the main thread can install handlers (Python's rule); elsewhere the block changes nothing
and `stop_requested()` is always None. Ray Train workers never use it: Ray owns their signals.
"""

from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from typing import Callable, Iterator

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def raise_keyboard_interrupt(signum, frame) -> None:
    """A signal handler that makes SIGTERM stop a process as Ctrl-C does (graceful_stop takes it over while a
    training stage runs)."""
    raise KeyboardInterrupt


def interrupt_text(error: KeyboardInterrupt) -> str:
    """What an interrupt says about itself: our own subclasses' text (a TrainingInterrupted says where its
    checkpoint is), nothing for a plain Ctrl-C, whose text if any is CPython's (a Ctrl-C inside a codec comes back
    as "decoding with 'cp437' codec failed (KeyboardInterrupt: )")."""
    return str(error) if type(error) is not KeyboardInterrupt else ""


def never() -> str | None:
    """The `stop_requested` of a run nothing can stop (Ray workers; tests)."""
    return None


@contextmanager
def graceful_stop() -> Iterator[Callable[[], str | None]]:
    """Within the block SIGINT / SIGTERM request a stop instead of ending the process (module docstring).
    Yields `stop_requested() -> signal name | None`."""
    if threading.current_thread() is not threading.main_thread():
        yield never
        return
    requested: list[str] = []

    def handle(signum: int, frame) -> None:
        if requested and signum == signal.SIGINT:
            raise KeyboardInterrupt  # the second Ctrl-C: stop now, without the checkpoint
        if not requested:
            requested.append(signal.Signals(signum).name)

    previous = {}
    try:
        # One at a time, each restored on the way out even if a signal's old handler raises while the
        # next is installed. A signal the process was told to ignore stays ignored: a run started in the
        # background by a non-interactive shell, or under nohup, inherits SIGINT ignored, and its starter
        # meant it.
        for sig in STOP_SIGNALS:
            if signal.getsignal(sig) is not signal.SIG_IGN:
                previous[sig] = signal.signal(sig, handle)
        yield lambda: requested[0] if requested else None
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
