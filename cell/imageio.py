"""Reading images with errors that say which file and what is wrong."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from cell.atomicfile import write_bytes_atomic
from cell.errors import InputError, OutputError
from cell.imagedecode import PNG_SIGNATURE, png_check
from drivers.cameras.imageheader import UnknownFormat, image_size


def read_image(path: str | Path, max_px: int | None = None, expected_size: tuple[int, int] | None = None) -> np.ndarray:
    """BGR uint8 image from a file, or InputError naming the file. The size is checked from the
    header first (against `max_px` pixels and an `expected_size` (w, h)), before decoding."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: image file not found")
    if not path.is_file():
        raise InputError(f"{path}: not a file")
    try:
        w, h = image_size(path)
    except UnknownFormat as e:
        raise InputError(f"{path}: cannot decode image ({e})") from None
    except OSError as e:
        raise InputError(f"{path}: cannot read image: {e.strerror or e}") from None
    if max_px is not None and w * h > max_px:
        raise InputError(
            f"{path}: image is {w} x {h} px ({w * h} px), more than camera.max_image_px {max_px}; not decoded"
        )
    if expected_size is not None and (w, h) != tuple(expected_size):
        raise InputError(
            f"{path}: image is {w} x {h} px but {expected_size[0]} x {expected_size[1]} px is expected; not decoded"
        )
    data = np.fromfile(str(path), dtype=np.uint8)
    if data[:8].tobytes() == PNG_SIGNATURE:
        png_check(data.tobytes(), str(path))  # its data may not inflate past the header's size (a PNG bomb)
    image = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    if image is None:
        raise InputError(f"{path}: cannot decode image (empty, corrupt or not an image format OpenCV reads)")
    return image


def check_image_path(path: str | Path) -> None:
    """OutputError unless `path` names a file OpenCV can encode by its extension."""
    path = Path(path)
    if path.is_dir():
        raise OutputError(f"{path}: is a folder, not an image file", hint="give a file path ending .png or .jpg")
    if not path.suffix or not cv2.haveImageWriter(f"x{path.suffix}"):
        raise OutputError(
            f"{path}: cannot write an image as {path.suffix or 'a file without extension'!r}", hint="use .png or .jpg"
        )


def write_image_atomic(path: str | Path, image: np.ndarray) -> None:
    """Encode by the file's extension, then write whole or not at all (cell.atomicfile)."""
    path = Path(path)
    check_image_path(path)
    ok, buf = cv2.imencode(path.suffix, image)
    if not ok:
        raise OutputError(f"{path}: cannot encode the image as {path.suffix!r}", hint="use .png or .jpg")
    write_bytes_atomic(path, buf.tobytes())
