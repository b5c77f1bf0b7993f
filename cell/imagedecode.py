"""Decoding images that come from outside (the screen's plate upload) within limits.

A PNG's header can say 1920 x 1080 while its compressed data inflates to gigabytes (20.9 MB
of deflated zeros hold 20 GB): libpng inflates all of it, 86 s of CPU, before OpenCV gives up.
So before anything is decoded:

- the size comes from the header, as before (drivers.cameras.imageheader);
- a PNG's image data is inflated here as a stream, counted and thrown away, and refused the
  moment it holds more bytes than its header's size can (`png_check`); its compressed
  text and colour-profile chunks likewise, up to 1 MiB each;

then the decode itself runs in a worker process (`DecodeWorker`), one at a time, killed when
it takes longer than its timeout or when the caller cancels (the client went away): a
decoder stuck in C cannot be stopped from a thread.
"""

from __future__ import annotations

import io
import logging
import multiprocessing
import struct
import threading
import time
import zlib
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from cell.errors import CellError, InputError

log = logging.getLogger(__name__)

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
TEXT_CHUNK_MAX_BYTES = 1 << 20  # what a zTXt, iTXt or iCCP chunk may inflate to
_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}  # PNG colour type -> samples per pixel
_ADAM7 = [(0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2)]


class DecodeBusy(CellError):
    """Another image is being decoded (one at a time)."""


class DecodeCancelled(CellError):
    """The caller gave up (the client went away) and the decode was stopped."""


# ---- PNG: how much its data may inflate to ------------------------------------------------------
def png_raw_bytes(width: int, height: int, bit_depth: int, colour_type: int, interlaced: bool) -> int:
    """Bytes the image data inflates to: each row's filter byte and packed samples, every Adam7 pass if interlaced."""
    bits = _CHANNELS[colour_type] * bit_depth

    def rows(w: int, h: int) -> int:
        return 0 if w == 0 or h == 0 else h * (1 + (w * bits + 7) // 8)

    if not interlaced:
        return rows(width, height)
    return sum(
        rows((width - x0 + dx - 1) // dx if width > x0 else 0, (height - y0 + dy - 1) // dy if height > y0 else 0)
        for x0, y0, dx, dy in _ADAM7
    )


def png_check(data: bytes, where: str = "upload") -> None:
    """InputError unless the PNG's compressed data inflates to no more than its header's size allows.
    Streams the inflation and keeps nothing; stops at the first byte too many (a bomb costs milliseconds)."""
    if not data.startswith(PNG_SIGNATURE):
        raise InputError(f"{where}: not a PNG image")
    pos, expected, idat = 8, None, _Inflater(0, where, "image data")
    while pos + 8 <= len(data):
        length, kind = struct.unpack(">I4s", data[pos : pos + 8])
        body = data[pos + 8 : pos + 8 + length]
        if len(body) < length:
            raise InputError(f"{where}: PNG chunk {kind!r} is cut short (corrupt or truncated file)")
        if kind == b"IHDR":
            expected = _expected(body, where)
            idat = _Inflater(expected, where, "image data")
        elif kind == b"IDAT":
            if expected is None:
                raise InputError(f"{where}: PNG image data before its header (corrupt file)")
            idat.feed(body)
        elif kind in (b"zTXt", b"iCCP", b"iTXt"):
            _check_text(kind, body, where)
        elif kind == b"IEND":
            return
        pos += 12 + length
    if expected is None:
        raise InputError(f"{where}: PNG without a header chunk (corrupt file)")


def _expected(ihdr: bytes, where: str) -> int:
    if len(ihdr) != 13:
        raise InputError(f"{where}: PNG header chunk of {len(ihdr)} bytes (corrupt file)")
    w, h, depth, colour, _, _, interlace = struct.unpack(">IIBBBBB", ihdr)
    if colour not in _CHANNELS or depth not in (1, 2, 4, 8, 16):
        raise InputError(f"{where}: PNG colour type {colour} with bit depth {depth} is not valid")
    return png_raw_bytes(w, h, depth, colour, interlace == 1)


class _Inflater:
    """A zlib stream fed in pieces, output counted and dropped; InputError past `limit` bytes."""

    def __init__(self, limit: int, where: str, what: str) -> None:
        self.limit, self.where, self.what = limit, where, what
        self.inflater = zlib.decompressobj()
        self.total = 0

    def feed(self, piece: bytes) -> None:
        if self.inflater.eof:
            if piece:
                raise InputError(f"{self.where}: PNG {self.what} goes on after its compressed stream ended")
            return
        while piece:
            try:
                out = self.inflater.decompress(piece, self.limit - self.total + 1)
            except zlib.error as e:
                raise InputError(f"{self.where}: PNG {self.what} is not valid compressed data ({e})") from None
            self.total += len(out)
            if self.total > self.limit:
                raise InputError(
                    f"{self.where}: PNG {self.what} inflates to more than the {self.limit} bytes its header allows "
                    "(a decompression bomb?): refused before decoding"
                )
            piece = self.inflater.unconsumed_tail
            if self.inflater.eof and self.inflater.unused_data:
                raise InputError(f"{self.where}: PNG {self.what} goes on after its compressed stream ended")


def _check_text(kind: bytes, body: bytes, where: str) -> None:
    """A compressed text or colour-profile chunk: inflate it with a cap (1 MiB)."""
    name_end = body.find(b"\0")
    if name_end < 0:
        return  # malformed: libpng skips it
    if kind == b"iTXt":
        if len(body) < name_end + 3 or body[name_end + 1] == 0:
            return  # not compressed
        rest = body[name_end + 3 :]
        for _ in range(2):  # language tag, translated keyword
            cut = rest.find(b"\0")
            if cut < 0:
                return
            rest = rest[cut + 1 :]
        stream = rest
    else:
        stream = body[name_end + 2 :]
    _Inflater(TEXT_CHUNK_MAX_BYTES, where, f"{kind.decode()} chunk").feed(stream)


# ---- the decode, in a process of its own ------------------------------------------------------------
def _serve(conn: Connection) -> None:
    """The worker: decode what comes, send back the pixels or why not, until the pipe closes."""
    import cv2

    cv2.setNumThreads(1)
    while True:
        try:
            data = conn.recv_bytes()
        except EOFError:
            return
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        if image is None:
            conn.send(("error", "cannot decode the image (corrupt or truncated)"))
        else:
            conn.send(("image", image.shape, str(image.dtype)))
            conn.send_bytes(image.tobytes())


class DecodeWorker:
    """Decodes in a child process, one image at a time; the child is killed (and made again for the next
    image) when a decode runs past its timeout or is cancelled."""

    def __init__(self, target: Callable[[Connection], None] | None = None) -> None:
        """`target`: the child's loop (tests give one that hangs); default the OpenCV decoder."""
        self.target = target
        self._lock = threading.Lock()
        self._proc: Any = None
        self._conn: Connection | None = None

    def decode(
        self, data: bytes, timeout_s: float, cancelled: threading.Event | None = None, where: str = "upload"
    ) -> np.ndarray:
        if not self._lock.acquire(blocking=False):
            raise DecodeBusy(f"{where}: another image is being decoded: try again when it is done")
        try:
            conn = self._start()
            conn.send_bytes(data)
            deadline = time.monotonic() + timeout_s
            while not conn.poll(0.05):
                if cancelled is not None and cancelled.is_set():
                    self._kill()
                    raise DecodeCancelled(f"{where}: decoding stopped: the client went away")
                if time.monotonic() > deadline or not self._proc.is_alive():
                    alive = self._proc.is_alive()
                    self._kill()
                    if alive:
                        raise InputError(f"{where}: decoding took longer than {timeout_s:g} s: refused")
                    raise InputError(f"{where}: the image decoder failed on this file: refused")
            reply = conn.recv()
            if reply[0] == "error":
                raise InputError(f"{where}: {reply[1]}")
            _, shape, dtype = reply
            return np.frombuffer(conn.recv_bytes(), dtype=dtype).reshape(shape).copy()
        except (EOFError, OSError) as e:
            self._kill()
            raise InputError(f"{where}: the image decoder failed ({e}): refused") from None
        finally:
            self._lock.release()

    def _start(self) -> Connection:
        if self._proc is None or not self._proc.is_alive():
            context = multiprocessing.get_context("spawn")  # no fork of a threaded server
            parent, child = context.Pipe()
            self._proc = context.Process(target=self.target or _serve, args=(child,), name="image-decode", daemon=True)
            self._proc.start()
            child.close()
            self._conn = parent
        assert self._conn is not None
        return self._conn

    def _kill(self) -> None:
        if self._proc is not None:
            self._proc.kill()
            self._proc.join(timeout=5)
        if self._conn is not None:
            self._conn.close()
        self._proc = self._conn = None

    def close(self) -> None:
        with self._lock:
            self._kill()


_WORKER = DecodeWorker()


def decode_limited(
    data: bytes,
    *,
    max_px: int,
    timeout_s: float,
    cancelled: threading.Event | None = None,
    where: str = "upload",
    worker: DecodeWorker | None = None,
) -> np.ndarray:
    """A BGR image from PNG or JPEG bytes: the size from the header (at most `max_px` pixels), a PNG's data
    checked to inflate to no more than that, then decoded in the worker within `timeout_s`."""
    from drivers.cameras.imageheader import UnknownFormat, image_size

    try:
        w, h = image_size(io.BytesIO(data))
    except UnknownFormat as e:
        raise InputError(f"{where}: not an image this cell reads ({e})") from None
    if w * h > max_px:
        raise InputError(f"{where}: image is {w} x {h} px, more than {max_px} px: not decoded")
    if data.startswith(PNG_SIGNATURE):
        png_check(data, where)
    return (worker or _WORKER).decode(data, timeout_s, cancelled, where)
