"""Ctrl-C during training: the first SIGINT asks the loop to stop after the current step and save, a second one
aborts at once (KeyboardInterrupt)."""

from __future__ import annotations

import signal
import threading


class InterruptFlag:
    """A context manager holding `requested` (set by the first Ctrl-C); the previous SIGINT handler comes back on exit.
    Outside the main thread (where no handler can be installed) it never sets the flag."""

    def __init__(self):
        self.requested = False
        self._previous = None
        self._installed = False

    def __enter__(self) -> "InterruptFlag":
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)
            self._installed = True
        return self

    def _handle(self, signum, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True

    def __exit__(self, *exc) -> None:
        if self._installed:
            signal.signal(signal.SIGINT, self._previous)


__all__ = ["InterruptFlag"]
