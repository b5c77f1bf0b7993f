"""Operator signals for every command, installed before any device is opened.

SIGINT (Ctrl-C), SIGTERM and SIGHUP (the terminal or SSH session closed) request a safe
stop; SIGUSR1 toggles a pause (only the pick loop acts on it; nothing dies of it).

Where the code can be interrupted (start-up, calibration, a pick step), a stop signal
raises StopRequested at once, so `with` blocks close ports and remove temporary folders
on the way out. Where it must not be (making the arm safe, ending the run), the signal is
only recorded (`Controls.stop`) and acted on by the code that checks it.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Callable, Iterator
from types import FrameType
from typing import Any

STOP_SIGNALS = {signal.SIGINT: "Ctrl-C", signal.SIGTERM: "SIGTERM", signal.SIGHUP: "SIGHUP (terminal closed)"}
EXIT_STOPPED = 130


# What signal.signal returns: the handler it replaced.
_Handler = Callable[[int, FrameType | None], Any] | int | signal.Handlers | None


class StopRequested(KeyboardInterrupt):
    """A stop signal arrived where the code may be interrupted; `reason` names it."""

    def __init__(self, reason: str = "Ctrl-C"):
        super().__init__(reason)
        self.reason = reason


class Controls:
    """Operator requests, safe to set from another thread or a signal handler."""

    def __init__(self) -> None:
        self.stop = threading.Event()  # the safe stop (signals, Halt): arm safe, torque released
        self.pause = threading.Event()
        self.finish = threading.Event()  # the line service's Stop: end the job at the next safe point, arm homed
        self.wake = threading.Event()  # cuts a continuous run's WAIT short when any request arrives
        self.stop_reason = "stop requested"
        self.faulted = False  # the stop is a fault raised from outside the job (request_fault)
        self.interruptible = True  # False: a stop signal is recorded, not raised

    def request(self, event: threading.Event, on: bool = True, reason: str | None = None) -> None:
        """From another thread (the line service): set or clear a request, never raising, and
        wake a waiting runner to see it."""
        if reason is not None:
            self.stop_reason = reason
        event.set() if on else event.clear()
        self.wake.set()

    def request_fault(self, reason: str) -> None:
        """From another thread: something the job needs has failed (e.g. its history cannot be
        written): stop safely at once, and end as a fault, not a stop."""
        self.faulted = True
        self.request(self.stop, reason=reason)

    def request_stop(self, reason: str) -> None:
        """Record a stop; raise StopRequested if the code running now may be interrupted."""
        self.stop_reason = reason
        self.stop.set()
        if self.interruptible:
            raise StopRequested(reason)

    def toggle_pause(self) -> None:
        self.pause.clear() if self.pause.is_set() else self.pause.set()

    @contextlib.contextmanager
    def shielded(self, shield: bool = True) -> Iterator[None]:
        """Run a block that a stop signal must not interrupt (or, with shield=False, may)."""
        before = self.interruptible
        self.interruptible = not shield
        try:
            yield
        finally:
            self.interruptible = before


@contextlib.contextmanager
def handling_signals(controls: Controls | None = None, install: bool = True) -> Iterator[Controls]:
    """Install the handlers (even over inherited 'ignore'), yield the Controls they act on, restore.
    `install=False`: they are already in place for `controls` (cell.launch); only yield them."""
    controls = controls or Controls()
    if not install:
        yield controls
        return
    previous: dict[signal.Signals, _Handler] = {}

    def on_stop(signum: int, _frame: FrameType | None) -> None:
        controls.request_stop(STOP_SIGNALS[signal.Signals(signum)])

    def on_pause(_signum: int, _frame: FrameType | None) -> None:
        controls.toggle_pause()

    for sig in STOP_SIGNALS:
        previous[sig] = signal.signal(sig, on_stop)
    previous[signal.SIGUSR1] = signal.signal(signal.SIGUSR1, on_pause)
    try:
        yield controls
    finally:
        with controls.shielded():
            for sig, handler in previous.items():
                signal.signal(sig, signal.SIG_DFL if handler is None else handler)
