"""Reading images with errors that say which file and what is wrong."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from cell.errors import InputError


def read_image(path: str | Path) -> np.ndarray:
    """BGR uint8 image from a file, or InputError naming the file."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: image file not found")
    if not path.is_file():
        raise InputError(f"{path}: not a file")
    data = np.fromfile(str(path), dtype=np.uint8)
    image = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    if image is None:
        raise InputError(f"{path}: cannot decode image (empty, corrupt or not an image format OpenCV reads)")
    return image


def write_image_atomic(path: str | Path, image: np.ndarray) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(path.suffix or ".png", image)
    if not ok:
        raise InputError(f"{path}: cannot encode image as {path.suffix!r}")
    tmp = path.with_name(f".{path.name}.tmp")
    buf.tofile(str(tmp))
    tmp.replace(path)
