"""Recalibration from the screen: a plate image (the cell's camera or an upload) -> the
report -> the operator accepts or rejects.

Accepting goes through cell.calibration.recalibrate.replace_active, the same quality gate
and atomic replacement as scripts/recalibrate.py, then service.install_calibration. Nothing
from the request names a file: an upload is bytes decoded as an image, the report's pictures
live in memory under a random id, and the files written are the config's.

Every step is the command table's before it does anything (issue 28): a capture is
CapturePlate (checked by the service), an upload is checked as CapturePlate before it is
decoded or fitted, an accept as InstallCalibration before the file is written, a reject
needs InstallCalibration's role. A report waits for its answer at most
`service.web.report_timeout_s`, then is rejected by itself (recorded, the hold released).
"""

from __future__ import annotations

import hashlib
import logging
import secrets
import struct
import threading
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from cell.calibration.pipeline import CalibrationResult, calibrate
from cell.calibration.recalibrate import check_image_size, gate_failure, replace_active
from cell.calibration.report import annotate_plate, deviation_png
from cell.config import CellConfig
from cell.core.api import LineServiceAPI
from cell.core.commands import Command, CommandRefused
from cell.core.events import SERVICE_ORIGIN, Interface, Origin, Role
from cell.core.records import CalibrationInfo
from cell.errors import InputError
from cell.imagedecode import decode_limited

log = logging.getLogger(__name__)


@dataclass
class Report:
    """A fitted calibration waiting for the operator's answer, and its pictures."""

    id: str
    result: CalibrationResult
    source: str  # for display only
    plate_jpeg: bytes
    deviation_png: bytes
    gate_failure: str | None

    def summary_json(self) -> dict[str, Any]:
        r, cv, fit = self.result, self.result.chosen.cv, self.result.chosen.fit
        return {
            "id": self.id,
            "source": self.source,
            "model": r.chosen.label,
            "why": r.why,
            "points": int(len(r.points.pixel)),
            "missing": [int(m) for m in r.points.missing],
            "fit_rms_mm": round(fit.rms_mm, 4),
            "fit_max_mm": round(fit.max_mm, 4),
            "cv_rms_mm": round(cv.rms_mm, 4),
            "cv_max_mm": round(cv.max_mm, 4),
            "models": [
                {"model": s.label, "cv_rms_mm": round(s.cv.rms_mm, 4), "cv_max_mm": round(s.cv.max_mm, 4)}
                for s in r.scores
            ],
            "passes": self.gate_failure is None,
            "gate_failure": self.gate_failure,
        }


HOLD_REASON = "a recalibration report is waiting for its answer: accept or reject it on the operator screen"
REJECT = "RejectCalibration"  # a report's rejection in the record (its role: InstallCalibration's)
UPLOAD = "UploadPlate"  # an uploaded plate image in the record (its role and states: CapturePlate's)
TIMEOUT_ORIGIN = Origin(Interface.SERVICE, "recalibration report timeout", Role.ENGINEER)


class Busy(Exception):
    """Another recalibration step is running, or the report asked for is not the open one."""


class NotInstalled(Exception):
    """The calibration file was written but the service refused to use it (the cell moved on meanwhile)."""

    def __init__(self, refusal: CommandRefused, path: Path):
        self.refusal, self.path = refusal, path
        super().__init__(f"{refusal}: {path} was written but the running cell did not take it")


def image_size_from_header(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG or JPEG header, read before decoding, so a tiny file claiming
    a gigapixel image is refused without allocating it. None: neither format."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) >= 24 and data[12:16] == b"IHDR":
        return struct.unpack(">II", data[16:24])
    if data[:2] != b"\xff\xd8":
        return None
    i = 2
    while i + 9 <= len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            i += 2
            continue
        length = struct.unpack(">H", data[i + 2 : i + 4])[0]
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            h, w = struct.unpack(">HH", data[i + 5 : i + 9])
            return w, h
        i += 2 + length
    return None


def decode_upload(data: bytes, config: CellConfig, cancelled: threading.Event | None = None) -> np.ndarray:
    """The uploaded bytes as a BGR image of the camera's size, or InputError saying why not. Decoded within
    limits (cell.imagedecode: a PNG's data may not inflate past its header's size; a worker process, one
    decode at a time, within service.web.decode_timeout_s, stopped when `cancelled` is set)."""
    if not data:
        raise InputError("upload: empty file")
    size = image_size_from_header(data)
    if size is None:
        raise InputError("upload: not a PNG or JPEG image")
    want = (config.camera.width_px, config.camera.height_px)
    if size != want:
        raise InputError(
            f"upload: image is {size[0]} x {size[1]} px but the camera is configured for {want[0]} x {want[1]} px"
        )
    image = decode_limited(
        data, max_px=want[0] * want[1], timeout_s=config.service.web.decode_timeout_s, cancelled=cancelled
    )
    check_image_size(image, config, "upload")
    return image


class RecalibrationDesk:
    """One recalibration at a time; the open report is the only one that can be accepted, and it waits for its
    answer at most `report_timeout_s`."""

    def __init__(self, service: LineServiceAPI, config: CellConfig, report_timeout_s: float = 600.0):
        self.service, self.config, self.report_timeout_s = service, config, report_timeout_s
        self._lock = threading.Lock()  # one fit or accept at a time (matplotlib is not thread-safe either)
        self._answer = threading.RLock()  # the open report, its hold and its timer change together
        self.open: Report | None = None
        self._release_hold: Callable[[], None] | None = None  # the service holds starts while a report is open
        self._timer: threading.Timer | None = None  # rejects the open report when nobody answers in time
        self.active_pictures: dict[str, bytes] = {}  # the accepted report's pictures, for the card
        self.active_time: datetime | None = None

    def has_pictures(self, info: CalibrationInfo | None) -> bool:
        """Whether the calibration in use is the one accepted here (whose pictures we hold)."""
        return bool(self.active_pictures) and info is not None and info.time_utc == self.active_time

    def from_camera(self, origin: Origin = SERVICE_ORIGIN) -> Report:
        image = self.service.capture_plate_image(origin)  # CapturePlate: the role and the cell at rest, first
        check_image_size(image, self.config, "camera frame")
        return self._fit(image, f"camera frame {_local_iso()}", origin)

    def authorize_upload(self, origin: Origin) -> None:
        """An upload is CapturePlate's (role, the cell at rest), checked and recorded before its bytes are even
        read: refused (CommandRefused), nothing is decoded, fitted or held."""
        self.service.authorize(Command.CAPTURE_PLATE, origin, UPLOAD)

    def from_upload(
        self, data: bytes, origin: Origin = SERVICE_ORIGIN, cancelled: threading.Event | None = None
    ) -> Report:
        """The report for an uploaded plate image; the upload was authorized (`authorize_upload`) first."""
        image = decode_upload(data, self.config, cancelled)
        digest = hashlib.sha256(data).hexdigest()[:12]
        return self._fit(image, f"uploaded image sha256 {digest}, {_local_iso()}", origin)

    def _fit(self, image: np.ndarray, source: str, origin: Origin) -> Report:
        if not self._lock.acquire(blocking=False):
            raise Busy("a recalibration is being computed: wait for its report")
        try:
            result = calibrate(image, self.config)  # PlateNotFound is an InputError-like CellError
            plate = annotate_plate(image, result)
            ok, jpeg = cv2.imencode(".jpg", plate, [cv2.IMWRITE_JPEG_QUALITY, 85])
            report = Report(
                secrets.token_urlsafe(16),
                result,
                source,
                jpeg.tobytes(),
                deviation_png(result),
                gate_failure(result, self.config),
            )
            self._set_open(report, origin)
            log.info("recalibration report %s from %s: %s", report.id, source, result.why)
            return report
        finally:
            self._lock.release()

    def report(self, report_id: str) -> Report:
        r = self.open
        if r is None or not secrets.compare_digest(r.id.encode(), report_id.encode()):
            raise Busy("no such recalibration report open (rejected, accepted, or replaced by a newer one)")
        return r

    def _set_open(self, report: Report | None, origin: Origin = SERVICE_ORIGIN) -> None:
        """The open report, the service's hold on starts while it waits for its answer, and its timeout."""
        with self._answer:
            self.open = report
            release, self._release_hold = self._release_hold, None
            timer, self._timer = self._timer, None
            if timer is not None:
                timer.cancel()
            if release is not None:
                release()
            if report is not None:
                self._release_hold = self.service.hold(HOLD_REASON, origin)
                self._timer = threading.Timer(self.report_timeout_s, self._expire, (report.id,))
                self._timer.name, self._timer.daemon = "recalibration-timeout", True
                self._timer.start()

    def reject(self, report_id: str, origin: Origin = SERVICE_ORIGIN) -> None:
        """The open report rejected: InstallCalibration's role first (a refusal changes nothing), then recorded."""
        self.service.authorize(Command.INSTALL_CALIBRATION, origin, state=False)  # a refusal is recorded
        with self._answer:
            self.report(report_id)
            self.service.authorize(
                Command.INSTALL_CALIBRATION, origin, REJECT, state=False, arguments={"report": report_id}
            )
            self._set_open(None)
        log.info("recalibration report %s rejected by %s", report_id, origin.describe())

    def _expire(self, report_id: str) -> None:
        """Nobody answered within report_timeout_s: the report is rejected by itself, recorded, the hold released."""
        with self._lock:  # a fit or an accept under way ends first (and may replace or close the report)
            with self._answer:
                if self.open is None or self.open.id != report_id:
                    return
                reason = f"no answer within {self.report_timeout_s:g} s (service.web.report_timeout_s)"
                try:
                    self.service.authorize(
                        Command.INSTALL_CALIBRATION,
                        TIMEOUT_ORIGIN,
                        REJECT,
                        state=False,
                        arguments={"report": report_id, "reason": reason},
                    )
                except CommandRefused as e:  # shutting down, or the record failed: the hold goes all the same
                    log.warning("recalibration report %s: its rejection was not recorded (%s)", report_id, e)
                self._set_open(None)
        log.warning(
            "recalibration report %s rejected by itself: %s; Start and Resume are no longer held", report_id, reason
        )

    def close(self) -> None:
        self._set_open(None)

    def accept(self, report_id: str, origin: Origin = SERVICE_ORIGIN) -> CalibrationInfo:
        """InstallCalibration's role and states first (refused: nothing written), then the gate, the atomic
        replacement, and the service starts using it. NotInstalled: written, but the cell moved on meanwhile."""
        with self._lock:
            self.service.authorize(Command.INSTALL_CALIBRATION, origin)  # refused: recorded, nothing written
            report = self.report(report_id)
            path, backup = replace_active(report.result, self.config)  # CalibrationRejected: file untouched
            cal, cv = report.result.calibration, report.result.chosen.cv
            info = CalibrationInfo(
                cal.model_name, cv.rms_mm, cv.max_mm, _created(cal.created_utc), report.source, cal.content_id
            )
            try:
                self.service.install_calibration(cal, info, origin)
            except CommandRefused as e:
                raise NotInstalled(e, path) from None
            self.active_pictures = {"plate.jpg": report.plate_jpeg, "deviation.png": report.deviation_png}
            self.active_time = info.time_utc
            self._set_open(None)
            log.info(
                "recalibration %s accepted from the screen: %s written%s",
                report_id,
                path,
                f", previous kept as {backup}" if backup else "",
            )
            return info


def _local_iso() -> str:
    """Now as the screen writes every date: ISO 8601, this PC's local time with its zone."""
    return datetime.now(UTC).astimezone().isoformat(timespec="seconds")


def _created(text: str) -> datetime | None:
    try:
        return datetime.fromisoformat(text)
    except ValueError:
        return None
