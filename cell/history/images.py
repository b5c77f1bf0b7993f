"""Images of what went wrong: the frame (lossless PNG) and its annotation, for a miss, a failed
part, a fault and parts left unknown, in the data folder, linked from the rows by id.

Bounded work: an image waits in a queue of `history.images_queue`; when that is full the
newest is dropped and counted, so the saver never falls behind the picks without end nor
holds frames in memory; once the queue is empty the encoders' buffers are given back to the
system (cell.memory), not kept by the saver's thread. Retention: after each save, files older than `images_max_days`
and then the oldest until the folder is under `images_max_mb` are deleted (their rows
marked deleted). Below `min_free_mb` of free disk no image is written and a warning alarm
is raised (cleared once there is room again): images never fill the disk.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import cv2
import numpy as np

from cell.atomicfile import write_bytes_atomic
from cell.core.events import FrameRef
from cell.core.worker import BoundedQueue, QueueWorker
from cell.history.config import HistoryConfig
from cell.history.rows import ImageWanted, Op
from cell.memory import release_free_memory

log = logging.getLogger(__name__)
_PNG = [cv2.IMWRITE_PNG_COMPRESSION, 1]  # lossless; level 1: 3-4x faster than the default for 10-20 % more bytes
_RECENT = 256  # ids remembered so one frame (a miss, then its part failed) is saved once


@dataclass
class ImageStats:
    saved: int = 0
    dropped: int = 0  # the queue was full (or still held it at close)
    skipped_low_disk: int = 0
    failed: int = 0
    deleted: int = 0


_Item = tuple[ImageWanted, FrameRef, datetime]


class _ImageQueue(BoundedQueue[_Item]):
    """The saver's queue: an image already queued or saved (one frame: a miss, then its part
    failed) is not queued again, and counts as taken."""

    def __init__(self, maxsize: int):
        super().__init__(maxsize)
        self.recent: deque[str] = deque(maxlen=_RECENT)

    def put(self, item: _Item) -> bool:
        image = item[0].image_id
        if image in self.recent:
            return True
        if not super().put(item):
            return False
        self.recent.append(image)
        return True


class ImageSaver:
    """A thread writing images from a bounded queue (a cell.core.worker.QueueWorker); each saved
    image becomes an `image` row (via `emit`)."""

    def __init__(
        self,
        folder: Path,
        config: HistoryConfig,
        cell: str,
        emit: Callable[[list[Op]], None],
        warn: Callable[[str, str], None],
        clear: Callable[[], None],
    ):
        self.folder, self.config, self.cell = Path(folder), config, cell
        self.emit, self.warn, self.clear = emit, warn, clear
        self._counts = ImageStats()  # saved, skipped_low_disk, deleted (the worker counts the rest)
        self._low_disk = False
        self._files: dict[Path, tuple[float, int]] = {}  # path -> (mtime, bytes), for retention
        self._scanned = False
        self._queue = _ImageQueue(config.images_queue)
        self._worker: QueueWorker[_Item, _Item] = QueueWorker(
            "history-images",
            lambda item: self._save(*item),
            self._queue,
            label="history: image saver",
            on_drained=release_free_memory,  # a rare burst of PNG work done: its buffers go back to the system
            describe=lambda item: f"image {item[0].image_id} (not saved)",
        )

    @property
    def stats(self) -> ImageStats:
        w = self._worker.stats()
        c = self._counts
        return ImageStats(c.saved, w.dropped, c.skipped_low_disk, w.failed, c.deleted)

    # ---- the converter's side (never blocks) -------------------------------------------
    def offer(self, wanted: ImageWanted, ref: FrameRef, t: datetime) -> bool:
        """True if the image is queued (or was already); False if dropped (queue full) or closing."""
        if wanted.image_id in self._queue.recent:  # only this thread (the offerer's) changes it
            return True
        return self._worker.offer((wanted, ref, t))

    def _room(self) -> bool:
        try:
            free_mb = shutil.disk_usage(self.folder).free / 2**20
        except OSError:
            free_mb = 0.0
        if free_mb < self.config.min_free_mb:
            self._counts.skipped_low_disk += 1
            if not self._low_disk:
                self._low_disk = True
                self.warn(
                    f"history: {free_mb:.0f} MB free on the data folder's disk, under history.min_free_mb "
                    f"({self.config.min_free_mb:g} MB): images of misses and faults are not saved",
                    "free disk space, or lower history.images_max_mb",
                )
            return False
        if self._low_disk:
            self._low_disk = False
            self.clear()
        return True

    def _save(self, wanted: ImageWanted, ref: FrameRef, t: datetime) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        if not self._scanned:
            self._scan()
        if not self._room():
            return
        day = self.folder / f"{t:%Y-%m-%d}"
        day.mkdir(exist_ok=True)
        frame_path = day / f"{wanted.image_id}.png"
        annotated_path = day / f"{wanted.image_id}-annotated.png"
        size = 0
        for path, image in ((frame_path, ref.image), (annotated_path, _annotated(ref))):
            ok, buf = cv2.imencode(".png", image, _PNG)
            if not ok:
                raise ValueError(f"PNG encoding failed for {path.name}")
            write_bytes_atomic(path, buf.tobytes())
            size += len(buf)
            self._files[path] = (time.time(), len(buf))
        rel = lambda p: str(p.relative_to(self.folder))  # noqa: E731
        self._counts.saved += 1
        self.emit(
            [
                Op(
                    "image",
                    (
                        wanted.image_id,
                        self.cell,
                        t,
                        wanted.kind,
                        wanted.job_id,
                        wanted.pick_id or None,
                        int(ref.frame_no),
                        rel(frame_path),
                        rel(annotated_path),
                        size,
                    ),
                )
            ]
        )
        self._trim()

    # ---- retention ------------------------------------------------------------------------------
    def _scan(self) -> None:
        self._scanned = True
        for path in self.folder.glob("*/*.png"):
            with contextlib.suppress(OSError):
                st = path.stat()
                self._files[path] = (st.st_mtime, st.st_size)

    def _trim(self) -> None:
        """Oldest first: everything past images_max_days, then until the folder is under images_max_mb."""
        now = time.time()
        max_age_s = self.config.images_max_days * 86400
        max_bytes = self.config.images_max_mb * 2**20
        total = sum(size for _, size in self._files.values())
        gone: list[Op] = []
        for path, (mtime, size) in sorted(self._files.items(), key=lambda kv: kv[1][0]):
            if now - mtime <= max_age_s and total <= max_bytes:
                break
            with contextlib.suppress(FileNotFoundError):
                os.unlink(path)
            del self._files[path]
            total -= size
            self._counts.deleted += 1
            if not path.stem.endswith("-annotated"):
                gone.append(Op("image_deleted", (datetime.now(UTC), path.stem)))
        if gone:
            for folder in [p for p in self.folder.iterdir() if p.is_dir()]:
                with contextlib.suppress(OSError):
                    folder.rmdir()  # only when empty
            self.emit(gone)

    # ---- control ----------------------------------------------------------------------------------
    def wait_idle(self, timeout_s: float) -> bool:
        return self._worker.wait_idle(timeout_s)

    def close(self, timeout_s: float) -> bool:
        """Save what is queued within the time given; drop (and count) the rest. True if the thread ended."""
        return self._worker.close(timeout_s)


def _annotated(ref: FrameRef) -> np.ndarray:
    from cell.vision.annotate import annotate

    if ref.result is None:
        return ref.image
    return annotate(ref.image, ref.result)
