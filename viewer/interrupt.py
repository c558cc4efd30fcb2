"""Ctrl-C that a long loop sees between its steps, never lost.

Python turns SIGINT into KeyboardInterrupt wherever the main thread happens to be; when that is
inside a destructor or a garbage-collection callback (pyopencl events, GL objects, numpy buffers
are released all the time), the exception is printed as "Exception ignored in ..." and dropped,
and the run goes on as if nothing happened (a bench under load finished all its frames after
Ctrl-C). `deferred_interrupt()` makes the first SIGINT set a flag that the loop reads between
steps; a second SIGINT raises KeyboardInterrupt at once, for a user who really wants out.
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


@contextmanager
def deferred_interrupt() -> Iterator[Interrupt]:
    """Within the block, the first SIGINT sets `.requested` (the previous handler comes back for
    the next one); outside the main thread, where signals cannot be handled, it never is."""
    state = Interrupt()
    if threading.current_thread() is not threading.main_thread():
        yield state
        return
    previous = signal.getsignal(signal.SIGINT)

    def on_sigint(signum, frame) -> None:
        state.requested = True
        signal.signal(signal.SIGINT, previous)  # a second Ctrl-C: KeyboardInterrupt as usual

    signal.signal(signal.SIGINT, on_sigint)
    try:
        yield state
    finally:
        signal.signal(signal.SIGINT, previous)
