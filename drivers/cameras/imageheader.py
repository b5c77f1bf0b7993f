"""An image file's width and height from its header alone, so a huge image (a 1 MB PNG of
20000 x 20000 pixels decodes to 1.2 GB) is refused before anything is decoded.

Reads PNG, JPEG, BMP, TIFF, WebP and PNM (PGM/PPM) headers: the formats a camera or an
operator hands the cell. Anything else is reported as an unknown format.
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import BinaryIO

_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


class UnknownFormat(ValueError):
    """The header is not one of the formats read here, or is cut short."""


def image_size(path: str | Path | BinaryIO) -> tuple[int, int]:
    """(width, height) in pixels from the header of a file (a path, or an open binary file such as
    io.BytesIO over uploaded bytes); UnknownFormat if it cannot tell."""
    if hasattr(path, "read"):
        return _size(path)  # type: ignore[arg-type]
    with open(path, "rb") as f:  # type: ignore[arg-type]
        return _size(f)


def _size(f: BinaryIO) -> tuple[int, int]:
    head = f.read(32)
    for test, reader in _READERS:
        if test(head):
            f.seek(0)
            try:
                w, h = reader(f)
            except (struct.error, IndexError, ValueError) as e:
                raise UnknownFormat(f"corrupt header ({e})") from None
            if w <= 0 or h <= 0:
                raise UnknownFormat(f"header gives a size of {w} x {h} px")
            return w, h
    raise UnknownFormat("not a PNG, JPEG, BMP, TIFF, WebP or PNM image")


def _png(f: BinaryIO) -> tuple[int, int]:
    data = f.read(24)
    if data[12:16] != b"IHDR":
        raise ValueError("no IHDR chunk")
    return struct.unpack(">II", data[16:24])


def _jpeg(f: BinaryIO) -> tuple[int, int]:
    f.read(2)
    while True:
        marker = f.read(2)
        if len(marker) < 2 or marker[0] != 0xFF:
            raise ValueError("no frame header")
        if marker[1] in (0xD8, 0x01) or 0xD0 <= marker[1] <= 0xD7:
            continue
        (length,) = struct.unpack(">H", f.read(2))
        if marker[1] in _JPEG_SOF:
            h, w = struct.unpack(">xHH", f.read(5))
            return w, h
        f.seek(length - 2, 1)


def _bmp(f: BinaryIO) -> tuple[int, int]:
    data = f.read(26)
    w, h = struct.unpack("<ii", data[18:26])
    return w, abs(h)


def _tiff(f: BinaryIO) -> tuple[int, int]:
    order = "<" if f.read(2) == b"II" else ">"
    f.read(2)
    (ifd,) = struct.unpack(order + "I", f.read(4))
    f.seek(ifd)
    (count,) = struct.unpack(order + "H", f.read(2))
    size = {}
    for _ in range(count):
        tag, kind, _n, value = struct.unpack(order + "HHI4s", f.read(12))
        if tag in (256, 257):
            size[tag] = struct.unpack(order + ("H" if kind == 3 else "I"), value[: 2 if kind == 3 else 4])[0]
    return size[256], size[257]


def _webp(f: BinaryIO) -> tuple[int, int]:
    data = f.read(30)
    chunk = data[12:16]
    if chunk == b"VP8 ":
        w, h = struct.unpack("<HH", data[26:30])
        return w & 0x3FFF, h & 0x3FFF
    if chunk == b"VP8L":
        b = data[21:25]
        return 1 + (((b[1] & 0x3F) << 8) | b[0]), 1 + (((b[3] & 0xF) << 10) | (b[2] << 2) | ((b[1] & 0xC0) >> 6))
    if chunk == b"VP8X":
        return 1 + int.from_bytes(data[24:27], "little"), 1 + int.from_bytes(data[27:30], "little")
    raise ValueError(f"unknown WebP chunk {chunk!r}")


def _pnm(f: BinaryIO) -> tuple[int, int]:
    tokens: list[bytes] = []
    for line in f.read(1024).splitlines():
        tokens += line.split(b"#")[0].split()
        if len(tokens) >= 3:
            return int(tokens[1]), int(tokens[2])
    raise ValueError("no size in the header")


_READERS = [
    (lambda h: h.startswith(b"\x89PNG\r\n\x1a\n"), _png),
    (lambda h: h.startswith(b"\xff\xd8"), _jpeg),
    (lambda h: h.startswith(b"BM"), _bmp),
    (lambda h: h[:4] in (b"II*\x00", b"MM\x00*"), _tiff),
    (lambda h: h[:4] == b"RIFF" and h[8:12] == b"WEBP", _webp),
    (lambda h: h[:1] == b"P" and h[1:2] in b"123456" and h[1:2] != b"", _pnm),
]
