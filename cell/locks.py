"""One process per device and per file: an advisory lock per resource, naming its holder.

A second `run-cell jog` on the port of a running job would soft-reset the controller under
it; two recalibrations would interleave their backups. So each command takes the lock of
every serial port, camera device and calibration file it uses, for as long as it uses it:
an flock on a file in the lock folder (RUN_CELL_LOCK_DIR, default <tmp>/run-cell-locks)
named after the resource's real path, holding "<program> pid N". The kernel drops the lock
when the process dies, however it dies, so a stale file never blocks anyone.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import re
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

from cell.errors import CellError
from drivers.arm.config import ArmConfig

LOCK_DIR_ENV = "RUN_CELL_LOCK_DIR"


class Busy(CellError):
    """A device or file is in use by another process."""

    exit_code = 2


def lock_dir() -> Path:
    return Path(os.environ.get(LOCK_DIR_ENV) or Path(tempfile.gettempdir()) / "run-cell-locks")


def lock_path(resource: str) -> Path:
    """The lock file of a device path, URL or file: one per real path (symlinks resolved)."""
    real = resource if "://" in resource else os.path.realpath(resource)
    readable = re.sub(r"[^A-Za-z0-9._-]+", "_", real).strip("_")[-60:]
    digest = hashlib.sha256(real.encode()).hexdigest()[:12]
    return lock_dir() / f"{readable}-{digest}.lock"


def holder_name() -> str:
    return f"{Path(sys.argv[0]).name or 'python'} pid {os.getpid()}"


@contextlib.contextmanager
def holding(resource: str | os.PathLike[str], what: str = "port", wait_s: float = 0.0) -> Iterator[Path]:
    """Hold the lock of `resource` for the block; Busy naming the holder if another process
    keeps it longer than `wait_s` (0: do not wait)."""
    resource = str(resource)
    path = lock_path(resource)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
    try:
        _acquire(fd, resource, what, wait_s)
        os.ftruncate(fd, 0)
        os.pwrite(fd, holder_name().encode(), 0)
        try:
            yield path
        finally:
            with contextlib.suppress(OSError):
                os.ftruncate(fd, 0)
            fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)


def _acquire(fd: int, resource: str, what: str, wait_s: float) -> None:
    deadline = time.monotonic() + wait_s
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return
        except BlockingIOError:
            if time.monotonic() >= deadline:
                holder = os.pread(fd, 200, 0).decode(errors="replace").strip() or "another process"
                raise Busy(
                    f"{what} {resource} in use by {holder}",
                    hint=f"wait for it to finish or stop it; lock file {lock_path(resource)}",
                ) from None
            time.sleep(0.05)


def camera_lock(camera_source: str | None) -> contextlib.AbstractContextManager[object]:
    """The lock of a camera device (an index is /dev/videoN) or of a GenICam camera (by its id); a
    file, folder, URL or the simulation needs none."""
    source = (camera_source or "").strip()
    if source.startswith("genicam:"):
        return holding(f"genicam://{source.removeprefix('genicam:').strip()}", "camera")
    device = f"/dev/video{source}" if source.isdigit() else source if source.startswith("/dev/") else None
    return holding(device, "camera") if device else contextlib.nullcontext()


def device_locks(arm_cfg: ArmConfig | None, camera_source: str | None = None) -> contextlib.ExitStack:
    """The locks of the configured arm's serial port and of a camera device (an index is
    /dev/videoN), for a `with` block; a mock arm and a file or URL camera need none."""
    stack = contextlib.ExitStack()
    try:
        if arm_cfg is not None and arm_cfg.kind != "mock" and arm_cfg.port:
            stack.enter_context(holding(arm_cfg.port, "port"))
        stack.enter_context(camera_lock(camera_source))
    except BaseException:
        stack.close()
        raise
    return stack


def holder_of(resource: str | os.PathLike[str]) -> str | None:
    """Who holds the lock of `resource` now ("run-cell pid N"), or None when nobody does; takes
    nothing (a lock that is free is released at once)."""
    path = lock_path(str(resource))
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
    except FileNotFoundError:
        return None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return os.pread(fd, 200, 0).decode(errors="replace").strip() or "another process"
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


def cell_resource(data_dir: str | os.PathLike[str]) -> str:
    """The resource a running line service holds for its whole life: its history data folder
    (`run-cell restore` refuses a target whose data folder is held)."""
    return os.path.join(os.path.realpath(data_dir), ".cell")


def cell_lock(data_dir: str | os.PathLike[str]) -> contextlib.AbstractContextManager[Path]:
    """Held by `run-cell serve` while it runs: Busy names the holder when another service runs on
    the same data folder."""
    return holding(cell_resource(data_dir), "cell (its history data folder)")
