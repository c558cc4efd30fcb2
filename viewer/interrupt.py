"""Ctrl-C that a long loop sees between its steps, never lost.

Python turns SIGINT into KeyboardInterrupt wherever the main thread happens to be; when that is
inside a destructor or a garbage-collection callback (pyopencl events, GL objects, numpy buffers
are released all the time), the exception is printed as "Exception ignored in ..." and dropped,
and the run goes on as if nothing happened (a bench under load finished all its frames after
Ctrl-C). `deferred_interrupt()` makes the first SIGINT set a flag that the loop reads between
steps; a second SIGINT raises KeyboardInterrupt at once, for a user who really wants out.

SIGTERM (`timeout`, a job scheduler, `kill`) is treated like Ctrl-C: inside the block it sets the
same flag, and `terminate_as_interrupt()` (the CLI installs it) makes it a KeyboardInterrupt
elsewhere, so every command's partial-report path keeps the work done (SIGTERM killed the process
with nothing written).
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass


@dataclass
class Interrupt:
    requested: bool = False  # the first Ctrl-C arrived: stop after the current step


SIGNALS = (signal.SIGINT, signal.SIGTERM)


def _raise_interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


@contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """Within the block SIGTERM raises KeyboardInterrupt, as SIGINT does (main thread only; a
    handler someone else installed is kept; the default comes back after the block)."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGTERM) != signal.SIG_DFL:
        yield
        return
    signal.signal(signal.SIGTERM, _raise_interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


@contextmanager
def deferred_interrupt() -> Iterator[Interrupt]:
    """Within the block, the first SIGINT or SIGTERM sets `.requested` (the previous handlers come
    back for the next one; an ignored signal stays ignored); outside the main thread, where signals
    cannot be handled, it never is."""
    state = Interrupt()
    if threading.current_thread() is not threading.main_thread():
        yield state
        return
    previous = {s: signal.getsignal(s) for s in SIGNALS}

    def restore() -> None:
        for s, handler in previous.items():
            signal.signal(s, handler if handler is not None else signal.SIG_DFL)

    def on_signal(signum, frame) -> None:
        state.requested = True
        restore()  # a second signal: KeyboardInterrupt (or termination) as before the block

    for s in SIGNALS:
        if previous[s] != signal.SIG_IGN:  # ignored by the parent (`cmd &` in a script: SIGINT): stays ignored
            signal.signal(s, on_signal)
    try:
        yield state
    finally:
        restore()
