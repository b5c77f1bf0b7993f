"""Replacing the active calibration: the quality gate (limits and plausibility), the change check
against the active file, and the atomic replacement with a backup of the previous one.

Every way of recalibrating (the script, `run-cell recalibrate`, the operator screen) goes
through `replace_active`; on any refusal the active file is untouched and no temporary file
is left. Recalibrations of one file are serialised by its lock; each keeps its own backup.
"""

from __future__ import annotations

import logging
from datetime import datetime
from pathlib import Path

from cell.atomicfile import copy_unique, ensure_folder
from cell.calibration.gates import change_problems, plausibility_problems
from cell.calibration.store import Calibration
from cell.errors import CalibrationRejected, InputError
from cell.locks import holding
from cell.signals import Controls

log = logging.getLogger(__name__)


def check_image_size(image, config, source: str) -> None:
    """A plate image must be the camera's size: the calibration maps that camera's pixels."""
    h, w = image.shape[:2]
    want = (config.camera.width_px, config.camera.height_px)
    if (w, h) != want:
        raise InputError(
            f"{source}: image is {w} x {h} px but the camera is configured for "
            f"{want[0]} x {want[1]} px (camera.width_px, camera.height_px)"
        )


def gate_failure(result, config) -> str | None:
    """Why a fit fails the quality gate (calibration.max_cv_*, a plausible plate and camera), or None."""
    limits = config.calibration
    cv = result.chosen.cv
    problems = []
    if cv.rms_mm > limits.max_cv_rms_mm or cv.max_mm > limits.max_cv_error_mm:
        problems.append(
            f"cross-validated error RMS {cv.rms_mm:.4f} mm / max {cv.max_mm:.4f} mm exceeds "
            f"calibration.max_cv_rms_mm {limits.max_cv_rms_mm} mm / max_cv_error_mm {limits.max_cv_error_mm} mm"
        )
    problems += plausibility_problems(result, limits, config.plate)
    return "; ".join(problems) or None


def replace_active(
    result, config, out: Path | None = None, accept_change: bool = False, controls: Controls | None = None
) -> tuple[Path, Path | None]:
    """The quality gate, then under the file's lock the change check and the atomic replacement
    (the previous file kept as a backup of its own). Every way of recalibrating (the script,
    `run-cell recalibrate`, the operator screen) goes through here; on any refusal the active
    file is untouched. Returns the file written and the backup, if any."""
    limits = config.calibration
    target = out or limits.active_path
    if why := gate_failure(result, config):
        raise CalibrationRejected(f"{why}; {target} left unchanged")
    backup_dir = limits.backup_dir if out is None else target.parent / "backups"
    with holding(target, "calibration file", wait_s=limits.lock_wait_s):  # one recalibration of a file at a time
        backup = _replace(target, result.calibration, backup_dir, accept_change, limits, controls or Controls())
    cv = result.chosen.cv
    log.info(
        "recalibrated: %s written (%s; CV RMS %.4f mm, max %.4f mm)%s",
        target,
        result.chosen.label,
        cv.rms_mm,
        cv.max_mm,
        f"; previous kept as {backup}" if backup else "",
    )
    return target, backup


def _replace(out: Path, new: Calibration, backup_dir: Path, accept_change: bool, limits, controls: Controls):
    """Under the file's lock: compare with the active file, back it up under a name of its own,
    write the new one; a signal waits until both are done. Returns the backup path or None."""
    if not out.exists():
        new.save(out)
        return None
    try:
        active = Calibration.load(out)
    except InputError as e:
        log.warning("the active calibration cannot be compared (%s); it is replaced and kept as a backup", e)
        active = None
    if active is not None and (problems := change_problems(new, active, limits)) and not accept_change:
        raise CalibrationRejected(
            "; ".join(problems) + f"; {out} left unchanged",
            hint="if the camera or plate was moved on purpose, rerun with --accept-change",
        )
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    with controls.shielded():
        backup = copy_unique(out, ensure_folder(backup_dir), f"{out.stem}.{stamp}", out.suffix)
        new.save(out)
    return backup
