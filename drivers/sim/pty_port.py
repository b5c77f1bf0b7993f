"""Serve an emulated device on a Linux pseudo-terminal, so drivers open a real device path.

The path handed out is a symlink to the pty's slave, kept stable across a simulated
unplug/replug the way /dev/serial/by-id/... is for a real USB adapter.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import select
import struct
import tempfile
import termios
import threading
import time
import tty
from collections.abc import Iterator
from typing import Protocol

log = logging.getLogger(__name__)


class ByteDevice(Protocol):
    """What an emulator offers the pty server, which calls it from its own thread under `lock`
    and sets `server` to itself (so tests reach unplug/replug/settle through the device)."""

    lock: threading.RLock
    unplug_requested: bool  # set by the device to have the cable pulled after this reply
    server: PtyServer | None

    def power_on(self, now_s: float) -> bytes: ...

    def receive(self, data: bytes, now_s: float) -> bytes: ...

    def tick(self, now_s: float) -> bytes: ...


class PtyServer:
    """Runs a ByteDevice on a fresh pty in a background thread; unplug()/replug() pull the cable."""

    def __init__(self, device: ByteDevice, name: str = "ttyEMU", tick_s: float = 0.002):
        self.device = device
        self.tick_s = tick_s
        self._dir = tempfile.mkdtemp(prefix="pty-")
        self.path = os.path.join(self._dir, name)
        self._master: int | None = None
        self._slave: int | None = None
        self._fd_lock = threading.Lock()
        self._cycle_lock = threading.Lock()  # held from reading bytes until they are handled
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"pty-{name}", daemon=True)
        device.server = self

    def start(self) -> PtyServer:
        self._plug()
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop once the device has handled what the driver sent last (a real device would get
        the last packet, say torque off, even if the driver closes its port right after)."""
        self.settle(timeout_s=0.5)
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2)
        self.unplug()
        with contextlib.suppress(OSError):
            os.rmdir(self._dir)

    @property
    def plugged(self) -> bool:
        return self._master is not None

    def settle(self, timeout_s: float = 1.0) -> None:
        """Wait until the device has handled every byte sent to it (for writes that get no reply)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self._cycle_lock:
                master = self._master
                if master is None or _unread_bytes(master) == 0:
                    return
            time.sleep(self.tick_s)

    def unplug(self) -> None:
        """The cable is pulled: the device path disappears and open handles fail."""
        with self._fd_lock:
            for fd in (self._master, self._slave):
                if fd is not None:
                    with contextlib.suppress(OSError):
                        os.close(fd)
            self._master = self._slave = None
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.path)
        log.debug("unplugged %s", self.path)

    def replug(self) -> None:
        """The cable is plugged back: a new pty behind the same path, the device powers up."""
        self._plug()

    def _plug(self) -> None:
        with self._fd_lock:
            if self._master is not None:
                return
            master, slave = os.openpty()
            # Raw from the start so nothing is echoed or translated before a driver opens it.
            tty.setraw(slave)
            os.set_blocking(master, False)
            # Keeping a slave fd open stops the master reading EIO while no driver has it open.
            self._master, self._slave = master, slave
            tmp = self.path + ".new"
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
            os.symlink(os.ttyname(slave), tmp)
            os.replace(tmp, self.path)
            with self.device.lock:
                self._write(self.device.power_on(time.monotonic()))
        log.debug("plugged %s -> %s", self.path, os.ttyname(slave))

    def _write(self, data: bytes) -> None:
        if not data or self._master is None:
            return
        try:
            os.write(self._master, data)
        except BlockingIOError:
            log.warning("pty buffer full; dropped %d bytes", len(data))
        except OSError as e:
            log.debug("pty write failed: %s", e)

    def _run(self) -> None:
        while not self._stop.is_set():
            master = self._master
            if master is None:
                time.sleep(self.tick_s)
                with self.device.lock:
                    self.device.tick(time.monotonic())
                continue
            with self._cycle_lock:
                try:
                    ready, _, _ = select.select([master], [], [], self.tick_s)
                    data = os.read(master, 4096) if ready else b""
                except (OSError, ValueError) as e:
                    if getattr(e, "errno", None) not in (errno.EIO, errno.EBADF, None):
                        log.debug("pty read failed: %s", e)
                    time.sleep(self.tick_s)
                    continue
                with self.device.lock:
                    now = time.monotonic()
                    out = self.device.receive(data, now) if data else b""
                    out += self.device.tick(now)
                    unplug = self.device.unplug_requested
                    self.device.unplug_requested = False
                with self._fd_lock:
                    if self._master == master:
                        self._write(out)
            if unplug:
                self.unplug()


def _unread_bytes(fd: int) -> int:
    try:
        (count,) = struct.unpack("I", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))
        return int(count)
    except OSError:
        return 0


@contextlib.contextmanager
def serve_pty(device: ByteDevice, name: str = "ttyEMU") -> Iterator[str]:
    """Start `device` on a fresh pty in a background thread; yield its device path; stop on exit."""
    server = PtyServer(device, name).start()
    try:
        yield server.path
    finally:
        server.stop()
