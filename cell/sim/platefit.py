"""The simulated plate's calibration, kept between runs: a dry run's slowest start-up step.

Rendering the 1080p plate and fitting it takes about 0.8 s of CPU, at every `run-cell --dry-run`
and `run-cell serve --dry-run`. The fit is a pure function of the camera model, the seed, the
plate, detection and calibration settings and the code that renders and fits, so the first run
fits it and writes the calibration (its own JSON format, checked on load like any calibration
file) to the user's cache folder, under a name keyed by all of that: the source of the
calibration package, the renderer and the camera model, and numpy's, OpenCV's and Python's
versions. A later run with the same key loads it; a missing, damaged or foreign file is fitted
again and rewritten, never a failed start; a file that cannot be written is logged.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import sys
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from cell.cachedir import user_cache_dir
from cell.calibration.store import Calibration, write_json_atomic
from cell.errors import CellError, OutputError

log = logging.getLogger(__name__)

SCHEMA = "pick-cell/sim-plate-fit"
_KEPT = 8  # fits of other cameras or configs kept beside the newest
_CELL = Path(__file__).resolve().parents[1]
_CODE = (*sorted((_CELL / "calibration").glob("*.py")), _CELL / "sim" / "render.py", _CELL / "camera_model.py")

Fit = tuple[Calibration, str]  # the calibration and why its model was chosen


def default_dir() -> Path:
    return user_cache_dir("sim")


def code_fingerprint() -> str:
    """What else the fit depends on: the code that renders and fits, and the libraries'."""
    h = hashlib.sha256()
    for path in _CODE:
        h.update(path.name.encode() + b"\0" + path.read_bytes())
    h.update(f"{np.__version__}|{cv2.__version__}|{sys.version_info[:3]}".encode())
    return h.hexdigest()


def cached_fit(key: str, folder: Path | None, fit: Callable[[], Fit]) -> Fit:
    """The fit for `key` (everything of the config and camera it depends on) from `folder`, or
    fitted now and written there; `folder` None: always fitted."""
    if folder is None:
        return fit()
    full_key = json.dumps([key, code_fingerprint()])
    path = folder / f"plate-{hashlib.sha256(full_key.encode()).hexdigest()[:24]}.json"
    if path.exists():
        try:
            return _read(path, full_key)
        except (OSError, ValueError, KeyError, TypeError, CellError) as e:
            log.warning("simulated plate fit %s unusable (%s: %s): fitted again", path, type(e).__name__, e)
    calibration, why = fit()
    _write(path, full_key, calibration, why)
    return calibration, why


def _read(path: Path, full_key: str) -> Fit:
    d = json.loads(path.read_text(encoding="utf-8"))
    if not isinstance(d, dict) or d.get("schema") != SCHEMA:
        raise ValueError("not a simulated plate fit")
    if d.get("key") != full_key:
        raise ValueError("made for another camera, config or code")
    why = d["why"]
    if not isinstance(why, str):
        raise ValueError("no note")
    return Calibration.from_dict(d["calibration"], source=str(path)), why


def _write(path: Path, full_key: str, calibration: Calibration, why: str) -> None:
    d = {"schema": SCHEMA, "key": full_key, "why": why, "calibration": calibration.to_dict()}
    try:
        path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        write_json_atomic(path, d)
    except (OSError, OutputError, ValueError, TypeError) as e:
        log.warning("simulated plate fit not kept (%s): %s", path, e)
        return
    others = sorted(path.parent.glob("plate-*.json"), key=_mtime, reverse=True)
    for old in others[_KEPT + 1 :]:
        with contextlib.suppress(OSError):
            old.unlink()


def _mtime(path: Path) -> float:
    try:
        return path.stat().st_mtime
    except OSError:
        return 0.0
