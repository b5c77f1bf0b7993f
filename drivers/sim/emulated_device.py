"""What both emulated arms share: the pty server's hooks, tool listeners and armed faults."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

log = logging.getLogger(__name__)

ToolListener = Callable[[bool, float, float, float, float], None]


class EmulatedDevice:
    """Base of the emulators that drivers.sim.pty_port.PtyServer serves.

    The server calls the device from its own thread under `lock`; `server` is set by it, so
    tests reach unplug/replug through the device. Subclasses name their faults in FAULTS.
    """

    FAULTS: tuple[str, ...] = ()

    def __init__(self) -> None:
        self.lock = threading.RLock()
        self.unplug_requested = False
        self.server = None  # set by PtyServer
        self._listeners: list[ToolListener] = []
        self._faults: dict[str, dict] = {}
        self._restart_on_plug = False

    def add_tool_listener(self, listener: ToolListener) -> None:
        """Call listener(closed, x_mm, y_mm, z_mm, angle_deg) on every gripper open/close."""
        with self.lock:
            self._listeners.append(listener)

    def clear_faults(self) -> None:
        with self.lock:
            self._faults.clear()

    def unplug(self) -> None:
        self.server.unplug()

    def replug(self, *, power_cycled: bool = False) -> None:
        """The cable is plugged back in. power_cycled: the device lost its power meanwhile too and
        starts afresh; otherwise it kept running and only the link comes back."""
        with self.lock:
            self._restart_on_plug = power_cycled
        self.server.replug()

    def _take_restart_on_plug(self) -> bool:
        restart, self._restart_on_plug = self._restart_on_plug, False
        return restart

    def _arm_fault(self, fault: str, params: dict) -> None:
        if fault not in self.FAULTS:
            raise ValueError(f"unknown fault {fault!r} (known: {', '.join(self.FAULTS)})")
        with self.lock:
            self._faults[fault] = params

    def _notify_tool(self, closed: bool, pose: tuple[float, float, float, float]) -> None:
        for listener in list(self._listeners):
            try:
                listener(closed, *pose)
            except Exception:  # a broken listener must not kill the emulator's thread
                log.exception("tool listener failed")
