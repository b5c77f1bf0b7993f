"""A GigE Vision or USB3 Vision camera through Aravis (GenICam), used from Python by PyGObject.

Imported only when a config names a `genicam:` source (drivers.cameras.factory), so a cell without
one needs neither Aravis nor PyGObject. Every setting of `[camera.genicam]` is checked against the
camera's own GenICam description when it opens: an unknown feature or a value out of its range is a
CameraError naming it, before the first frame.

A capture is one complete frame exposed after the request: frames already queued are dropped first,
a software trigger is sent after that, and a frame whose first packet came before the request is
never returned. An incomplete frame (GVSP packets lost) is counted and retried while the
acquisition timeout lasts; past `loss_alarm_percent` of the recent frames a warning goes to
`on_warning`. A camera that stops answering is "camera <serial> lost: ..." (CameraError); the next
capture or connect looks for the same serial again and goes on when it is back.
"""

from __future__ import annotations

import collections
import importlib
import ipaddress
import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from drivers.cameras.base import Camera
from drivers.cameras.config import GENICAM_PREFIX, FeatureValue, GenICamConfig
from drivers.cameras.errors import CameraError

log = logging.getLogger(__name__)

INSTALL_HINT = (
    "GenICam cameras need Aravis and PyGObject: `sudo apt install gir1.2-aravis-0.8 libgirepository1.0-dev "
    "libcairo2-dev pkg-config`, then `.venv/bin/pip install -e '.[genicam]'` (docs/cameras.md)"
)
LOSS_WARNING = "camera-frame-loss"
FAKE_PREFIX = "Fake_"
ATTEMPT_S = 0.5  # beyond twice the exposure: a triggered frame that has not come is lost  # Aravis's in-process Fake interface (tests, docs/cameras.md)

# GenICam's Bayer names give the first row's first two pixels; OpenCV's name the second row's.
_CONVERSIONS: dict[str, int] = {
    "BayerRG8": cv2.COLOR_BayerBG2BGR,
    "BayerGR8": cv2.COLOR_BayerGB2BGR,
    "BayerBG8": cv2.COLOR_BayerRG2BGR,
    "BayerGB8": cv2.COLOR_BayerGR2BGR,
    "RGB8": cv2.COLOR_RGB2BGR,
}
_CHANNELS = {"RGB8": 3, "BGR8": 3}

_aravis_lock = threading.Lock()  # Aravis's device list is process-wide


class GenICamUnavailable(CameraError):
    """Aravis or PyGObject is not installed."""


def aravis() -> Any:
    """The Aravis module through PyGObject; GenICamUnavailable saying what to install."""
    try:
        gi = importlib.import_module("gi")
        gi.require_version("Aravis", "0.8")
        return importlib.import_module("gi.repository.Aravis")
    except ImportError as e:
        raise GenICamUnavailable(f"no GenICam support here: {e}", hint=INSTALL_HINT) from None
    except ValueError as e:  # gi.require_version: the typelib is absent
        raise GenICamUnavailable(f"no GenICam support here: Aravis 0.8: {e}", hint=INSTALL_HINT) from None


def _glib_error() -> type[Exception]:
    glib = importlib.import_module("gi.repository.GLib")
    return glib.Error  # type: ignore[no-any-return]


def _is_address(text: str) -> bool:
    try:
        ipaddress.IPv4Address(text)
    except ValueError:
        return False
    return True


def _message(error: Exception) -> str:
    """A GLib.Error's own words (Aravis names the feature and register: "[TriggerSoftware] ... timeout")."""
    return str(getattr(error, "message", None) or error)


@dataclass(frozen=True)
class GenICamDevice:
    """One camera Aravis found on one of its interfaces."""

    device_id: str
    vendor: str
    model: str
    serial: str
    address: str
    interface: str  # GigEVision, USB3Vision or Fake

    @property
    def source(self) -> str:
        return f"{GENICAM_PREFIX}{self.device_id}"

    def matches(self, wanted: str) -> bool:
        return wanted in (self.device_id, self.serial) or (bool(self.address) and wanted == self.address)


def list_devices(fake: bool = False) -> list[GenICamDevice]:
    """Every GenICam camera on every interface (GigE discovery waits about a second for replies)."""
    ar = aravis()
    with _aravis_lock:
        if fake:
            ar.enable_interface("Fake")
        ar.update_device_list()
        return [
            GenICamDevice(
                device_id=ar.get_device_id(i) or "",
                vendor=ar.get_device_vendor(i) or "",
                model=ar.get_device_model(i) or "",
                serial=ar.get_device_serial_nbr(i) or "",
                address=ar.get_device_address(i) or "",
                interface=ar.get_device_protocol(i) or "",
            )
            for i in range(ar.get_n_devices())
        ]


@dataclass(frozen=True)
class FrameInfo:
    """What the camera said of the frame a capture returned."""

    frame_id: int  # the camera's block id (GigE Vision) or its frame counter
    timestamp_ns: int  # the camera's own clock
    system_timestamp_ns: int  # this computer's clock (time.time_ns) when the frame began to arrive
    attempts: int  # frames taken to get a complete one (1: the first was)


@dataclass
class GenICamStats:
    """Counters since connect; `recent` are the last frames' outcomes (True: complete)."""

    frames: int = 0
    incomplete: int = 0
    stale_dropped: int = 0
    timeouts: int = 0
    lost: int = 0
    reconnects: int = 0
    recent: collections.deque[bool] = field(default_factory=lambda: collections.deque(maxlen=100))

    def loss_percent(self) -> float:
        return 100.0 * self.recent.count(False) / len(self.recent) if self.recent else 0.0


class GenICamCamera(Camera):
    """`genicam:<id>`: the id is Aravis's device id, the serial number, or (GigE) the address."""

    def __init__(self, wanted: str, width_px: int, height_px: int, open_timeout_s: float, cfg: GenICamConfig):
        self.wanted = wanted.strip()
        self.source = f"{GENICAM_PREFIX}{self.wanted}"
        self.width_px, self.height_px = width_px, height_px
        self.open_timeout_s = open_timeout_s
        self.cfg = cfg
        self.stats = GenICamStats(recent=collections.deque(maxlen=cfg.loss_window_frames))
        self.last_frame: FrameInfo | None = None
        self.device: GenICamDevice | None = None  # what was opened (its serial is the one looked for again)
        self._connected = False  # between connect and disconnect, even while the camera is lost
        self._camera: Any = None
        self._stream: Any = None
        self._warned = False
        self._lost_reason: str | None = None
        self._attempt_s = ATTEMPT_S

    # -- connecting ------------------------------------------------------------------------------

    @property
    def is_connected(self) -> bool:
        return self._connected

    @property
    def name(self) -> str:
        """The camera as the operator knows it: its serial number once seen, else the configured id."""
        return self.device.serial if self.device is not None and self.device.serial else self.wanted

    @property
    def aravis_camera(self) -> Any:
        """The open Aravis.Camera (None while closed or lost); it changes when the camera is opened again."""
        return self._camera

    def connect(self) -> None:
        self.stats = GenICamStats(recent=collections.deque(maxlen=self.cfg.loss_window_frames))
        self._warned = False
        self._open()
        self._connected = True

    def disconnect(self) -> None:
        self._connected = False
        self._close()

    def _find(self, wait: bool) -> GenICamDevice | None:
        """The camera in Aravis's list (by its serial once seen), looked for until open_timeout_s if `wait`."""
        if _is_address(self.wanted):  # opened directly, no discovery (a camera beyond broadcast's reach too)
            return None
        wanted = self.device.serial if self.device is not None and self.device.serial else self.wanted
        deadline = time.monotonic() + (self.open_timeout_s if wait else 0.0)
        while True:
            found = [d for d in list_devices(fake=self.wanted.startswith(FAKE_PREFIX)) if d.matches(wanted)]
            if found or time.monotonic() >= deadline:
                return found[0] if found else None

    def _open(self, wait: bool = True) -> None:
        ar = aravis()
        glib_error = _glib_error()
        device = self._find(wait)
        if device is None and not _is_address(self.wanted):
            raise CameraError(
                f"no camera {self.wanted} answers",
                source=self.source,
                hint="`run-cell cameras` lists the cameras this computer sees; for GigE check the cable, power, "
                "the link's address range, the firewall (GVCP is UDP port 3956) and rp_filter (docs/cameras.md)",
            )
        target = device.device_id if device is not None else self.wanted  # an address: opened directly
        try:
            camera = ar.Camera.new(target)
        except glib_error as e:
            raise CameraError(
                f"cannot open: {_message(e)}",
                source=self.source,
                hint="`run-cell cameras` lists the cameras this computer sees; for GigE check the cable, "
                "the link's address range, the firewall (GVCP is UDP port 3956) and rp_filter (docs/cameras.md)",
            ) from None
        if device is None:
            device = GenICamDevice(
                device_id=target,
                vendor=camera.get_vendor_name() or "",
                model=camera.get_model_name() or "",
                serial=camera.get_device_serial_number() or "",
                address=target,
                interface="GigEVision" if camera.is_gv_device() else "USB3Vision",
            )
        if self.device is not None and self.device.serial and device.serial != self.device.serial:
            raise CameraError(
                f"{target} is now serial {device.serial}, not {self.device.serial} as when opened",
                source=self.source,
                hint="another camera took its address or id; name the camera by its serial number",
            )
        self.device = device
        self._camera = camera
        try:
            self._configure(ar, camera)
            payload = camera.get_payload()
            stream = camera.create_stream(None, None)
            if stream is None:
                raise self._refuse("cannot open its stream")
            if camera.is_gv_device():
                # room for a whole frame's packets in the kernel (each small packet costs it about twice its
                # size): four frames' bytes, capped by net.core.rmem_max (docs/cameras.md)
                stream.set_property("socket-buffer", ar.GvStreamSocketBuffer.FIXED)
                stream.set_property("socket-buffer-size", min(4 * payload, 2**31 - 1))
            for _ in range(self.cfg.buffer_count):
                stream.push_buffer(ar.Buffer.new_allocate(payload))
            self._stream = stream
            camera.start_acquisition()
        except glib_error as e:
            self._close(reachable=False)
            raise self._refuse(_message(e)) from None
        except BaseException:  # a setting refused: the camera answers, let it go at once
            self._close()
            raise
        self._lost_reason = None
        log.info(
            "camera %s: %s %s serial %s at %s (%s), %dx%d %s, trigger %s",
            self.source,
            device.vendor,
            device.model,
            device.serial,
            device.address,
            device.interface,
            self.width_px,
            self.height_px,
            self.cfg.pixel_format,
            self.cfg.trigger,
        )

    def _close(self, reachable: bool = True) -> None:
        """Stop and release the camera. Aravis's release of a camera that no longer answers waits for
        its control channel's timeouts (10 s): that is left to a thread of its own, not the caller."""
        held = [self._camera, self._stream]
        self._camera = self._stream = None
        camera, stream = held
        if reachable and camera is not None and stream is not None:
            try:
                camera.stop_acquisition()
            except Exception as e:  # a lost camera cannot be told to stop
                log.debug("camera %s: stop acquisition: %s", self.source, e)
        del camera, stream
        if reachable:
            held.clear()  # the stream's thread and socket, the control channel: released with the last reference
        else:
            threading.Thread(target=held.clear, name=f"release {self.source}", daemon=True).start()

    # -- settings, checked against the camera's description -----------------------------------------

    def _refuse(self, what: str, hint: str | None = None) -> CameraError:
        named = f"serial {self.name}: " if self.name != self.wanted else ""
        return CameraError(f"{named}{what}", source=self.source, hint=hint)

    def _configure(self, ar: Any, camera: Any) -> None:
        cfg = self.cfg
        formats = list(camera.dup_available_pixel_formats_as_strings() or [])
        if cfg.pixel_format not in formats:
            raise self._refuse(
                f"pixel format {cfg.pixel_format} not offered (it has {', '.join(formats)})",
                "set camera.genicam.pixel_format to one of these",
            )
        camera.set_pixel_format_from_string(cfg.pixel_format)
        self._set_region(camera)
        if cfg.exposure_us is not None:
            if camera.is_exposure_auto_available():
                camera.set_exposure_time_auto(ar.Auto.OFF)
            lo, hi = camera.get_exposure_time_bounds()
            if not lo <= cfg.exposure_us <= hi:
                raise self._refuse(f"exposure_us {cfg.exposure_us:g} out of range {lo:g} to {hi:g} µs")
            camera.set_exposure_time(cfg.exposure_us)
        if cfg.gain_db is not None:
            if camera.is_gain_auto_available():
                camera.set_gain_auto(ar.Auto.OFF)
            lo, hi = camera.get_gain_bounds()
            if not lo <= cfg.gain_db <= hi:
                raise self._refuse(f"gain_db {cfg.gain_db:g} out of range {lo:g} to {hi:g} dB")
            camera.set_gain(cfg.gain_db)
        self._set_trigger(ar, camera)
        if camera.is_gv_device():
            if cfg.packet_size_bytes is None:
                camera.gv_auto_packet_size()
            else:
                camera.gv_set_packet_size(cfg.packet_size_bytes)
            if cfg.inter_packet_delay_ns:
                camera.gv_set_packet_delay(cfg.inter_packet_delay_ns)
        for name, value in cfg.features.items():
            self._set_feature(camera.get_device(), name, value)
        # a software-triggered frame not begun within this is taken as lost whole and asked for again
        self._attempt_s = ATTEMPT_S + 2 * camera.get_exposure_time() / 1e6

    def _set_region(self, camera: Any) -> None:
        w_lo, w_hi = camera.get_width_bounds()
        h_lo, h_hi = camera.get_height_bounds()
        if not (w_lo <= self.width_px <= w_hi and h_lo <= self.height_px <= h_hi):
            raise self._refuse(
                f"{self.width_px}x{self.height_px} px does not fit its sensor ({w_hi}x{h_hi} px at most)",
                "set camera.width_px/height_px to at most the sensor's size",
            )
        camera.set_region(0, 0, self.width_px, self.height_px)
        _x, _y, w, h = camera.get_region()
        if (w, h) != (self.width_px, self.height_px):
            raise self._refuse(
                f"asked for {self.width_px}x{self.height_px} px, it took {w}x{h} px",
                "set camera.width_px/height_px to a multiple of the camera's width and height increments",
            )

    def _set_trigger(self, ar: Any, camera: Any) -> None:
        trigger = self.cfg.trigger
        if trigger == "free-run":
            camera.clear_triggers()
            camera.set_acquisition_mode(ar.AcquisitionMode.CONTINUOUS)
            return
        if not camera.is_software_trigger_supported() and trigger == "software":
            raise self._refuse("it has no software trigger", "set camera.genicam.trigger to 'line' or 'free-run'")
        source = "Software" if trigger == "software" else self.cfg.trigger_line
        available = list(camera.dup_available_trigger_sources() or [])
        if source not in available:
            raise self._refuse(
                f"trigger source {source} not offered (it has {', '.join(available)})",
                "set camera.genicam.trigger_line to one of these",
            )
        camera.set_trigger(source)

    def _set_feature(self, device: Any, name: str, value: FeatureValue) -> None:
        node = device.get_feature(name)
        if node is None or not device.is_feature_implemented(name):
            raise self._refuse(
                f"has no feature {name!r}", "check the name in the camera's manual (GenICam names are case-sensitive)"
            )
        kind = type(node).__name__  # GcFloatNode, GcIntegerNode, GcEnumeration, GcBoolean, GcStringNode, ...
        try:
            if "Enumeration" in kind:
                options = list(device.dup_available_enumeration_feature_values_as_strings(name) or [])
                if str(value) not in options:
                    raise self._refuse(f"feature {name} = {value!r} is not one of {', '.join(options)}")
                device.set_string_feature_value(name, str(value))
            elif "Boolean" in kind:
                if not isinstance(value, bool):
                    raise self._refuse(f"feature {name} is true or false, not {value!r}")
                device.set_boolean_feature_value(name, value)
            elif "Float" in kind or "Converter" in kind:
                if isinstance(value, bool) or not isinstance(value, int | float):
                    raise self._refuse(f"feature {name} is a number, not {value!r}")
                lo, hi = device.get_float_feature_bounds(name)
                if not lo <= value <= hi:
                    raise self._refuse(f"feature {name} = {value:g} out of range {lo:g} to {hi:g}")
                device.set_float_feature_value(name, float(value))
            elif "Integer" in kind or "Register" in kind:
                if isinstance(value, bool) or not isinstance(value, int):
                    raise self._refuse(f"feature {name} is a whole number, not {value!r}")
                lo, hi = device.get_integer_feature_bounds(name)
                if not lo <= value <= hi:
                    raise self._refuse(f"feature {name} = {value} out of range {lo} to {hi}")
                device.set_integer_feature_value(name, value)
            elif "String" in kind:
                device.set_string_feature_value(name, str(value))
            else:
                raise self._refuse(f"feature {name} is a {kind}, which cannot be set from the config")
        except _glib_error() as e:
            raise self._refuse(f"feature {name} = {value!r} refused: {_message(e)}") from None

    def settings(self) -> dict[str, object]:
        """What the open camera reports now (read back, not the config): exposure, gain, format, trigger."""
        camera = self._camera
        if camera is None:
            raise CameraError("settings before connect", source=self.source)
        device = camera.get_device()
        values: dict[str, object] = {
            "exposure_us": camera.get_exposure_time(),
            "gain_db": camera.get_gain(),
            "pixel_format": camera.get_pixel_format_as_string(),
            "region_px": tuple(camera.get_region()),
            "trigger_mode": device.get_string_feature_value("TriggerMode"),
            "trigger_source": camera.get_trigger_source(),
        }
        if camera.is_gv_device():
            values["packet_size_bytes"] = camera.gv_get_packet_size()
        return values

    def stream_counters(self) -> dict[str, int]:
        """Aravis's counters of the open stream since connect (n_completed_buffers, n_failures,
        n_missing_frames, n_missing_packets, n_resent_packets, n_underruns, ...): what reached this computer."""
        stream = self._stream
        if stream is None:
            raise CameraError("stream counters before connect", source=self.source)
        uint64 = importlib.import_module("gi.repository.GObject").TYPE_UINT64
        return {
            stream.get_info_name(i): int(stream.get_info_uint64(i))
            for i in range(stream.get_n_infos())
            if stream.get_info_type(i) == uint64
        }

    # -- frames ------------------------------------------------------------------------------------

    def _grab(self) -> np.ndarray:
        if self._camera is None:
            self._reopen()
        ar = aravis()
        glib_error = _glib_error()
        try:
            return self._acquire()
        except glib_error as e:
            reason, code = _message(e), getattr(e, "code", None)
        # outside the except clause: the failed call's frames (holding the camera) are gone
        gone = {int(ar.DeviceError.TIMEOUT), int(ar.DeviceError.NOT_CONNECTED), int(ar.DeviceError.TRANSFER_ERROR)}
        if code in gone or self._probe(self._camera) is not None:
            raise self._lost(reason)
        raise self._refuse(reason, "the camera answers but refused the request: see its manual for the feature named")

    def _reopen(self) -> None:
        """The camera was lost: open it again if the same serial answers; else it is still lost."""
        try:
            self._open(wait=False)
        except CameraError as e:
            raise CameraError(
                f"camera {self.name} lost: {self._lost_reason or 'not open'}; not back yet: {e.args[0]}",
                hint=f"check its cable and power ({self.source}); it is opened again when it answers",
            ) from None
        self.stats.reconnects += 1
        log.warning("camera %s: %s is back", self.source, self.name)

    def _lost(self, reason: str) -> CameraError:
        self._lost_reason = reason
        self.stats.lost += 1
        self._close(reachable=False)
        address = f" at {self.device.address}" if self.device is not None and self.device.address else ""
        return CameraError(
            f"camera {self.name} lost: {reason}",
            hint=f"check the camera{address} ({self.source}): its cable, power and link; "
            "it is opened again when it answers",
        )

    def _acquire(self) -> np.ndarray:
        ar = aravis()
        camera, stream = self._camera, self._stream
        success = ar.BufferStatus.SUCCESS
        while (stale := stream.try_pop_buffer()) is not None:  # queued before the request: never returned
            self.stats.stale_dropped += 1
            stream.push_buffer(stale)
        request_ns = time.time_ns()
        deadline = time.monotonic() + self.cfg.acquisition_timeout_s
        skip = 1 if self.cfg.trigger == "free-run" else 0  # the first one may have begun exposing before
        attempts = 0
        software = self.cfg.trigger == "software"
        if software:
            camera.software_trigger()
        while (remaining_s := deadline - time.monotonic()) > 0:
            wait_s = min(remaining_s, self._attempt_s) if software else remaining_s
            buffer = stream.timeout_pop_buffer(max(1, int(wait_s * 1e6)))
            if buffer is None:
                if not software or wait_s >= remaining_s:
                    break
                attempts += 1  # the whole frame vanished (its every packet lost): ask again
                self._count(False)
                camera.software_trigger()
                continue
            try:
                if buffer.get_system_timestamp() < request_ns:
                    self.stats.stale_dropped += 1
                    continue
                attempts += 1
                complete = buffer.get_status() == success
                self._count(complete)
                if not complete:
                    log.debug(
                        "camera %s: frame %d incomplete: %s", self.source, buffer.get_frame_id(), buffer.get_status()
                    )
                    if software:
                        camera.software_trigger()  # ask again while the time lasts
                    continue
                if skip:
                    skip -= 1
                    continue
                image = self._image(buffer)
                self.last_frame = FrameInfo(
                    frame_id=int(buffer.get_frame_id()),
                    timestamp_ns=int(buffer.get_timestamp()),
                    system_timestamp_ns=int(buffer.get_system_timestamp()),
                    attempts=attempts,
                )
                self.stats.frames += 1
                return image
            finally:
                stream.push_buffer(buffer)
        self.stats.timeouts += 1
        gone = self._probe(camera)
        del camera, stream
        if gone is not None:  # a camera gone is "lost", not a timeout
            raise self._lost(gone)
        raise self._refuse(
            f"no complete frame within {self.cfg.acquisition_timeout_s:g} s"
            + (f" ({attempts} incomplete)" if attempts else ""),
            "incomplete frames: lower packet_size_bytes or raise inter_packet_delay_ns, check MTU and cabling; "
            "none at all: check the trigger (its line and wiring) and the firewall for the stream (docs/cameras.md)",
        )

    def _probe(self, camera: Any) -> str | None:
        """Why the camera no longer answers on its control channel, or None if it does."""
        try:
            camera.get_device().read_register(0)
        except _glib_error() as e:
            return _message(e)
        return None

    def _count(self, complete: bool) -> None:
        stats = self.stats
        stats.recent.append(complete)
        if not complete:
            stats.incomplete += 1
        full = len(stats.recent) >= min(stats.recent.maxlen or 0, 10)
        share = stats.loss_percent()
        if full and share > self.cfg.loss_alarm_percent and not self._warned:
            self._warned = True
            reason = f"camera {self.name}: {share:.0f} % of the last {len(stats.recent)} frames came incomplete"
            hint = (
                "check the cable and switch; lower packet_size_bytes or raise inter_packet_delay_ns (docs/cameras.md)"
            )
            log.warning("%s (%s)", reason, hint)
            if self.on_warning is not None:
                self.on_warning(LOSS_WARNING, reason, hint)
        elif self._warned and share <= self.cfg.loss_alarm_percent / 2:
            self._warned = False
            log.info("camera %s: frame loss back to %.1f %%", self.name, share)
            if self.on_clear is not None:
                self.on_clear(LOSS_WARNING)

    def _image(self, buffer: Any) -> np.ndarray:
        width, height = int(buffer.get_image_width()), int(buffer.get_image_height())
        data = buffer.get_data()
        fmt = self.cfg.pixel_format
        channels = _CHANNELS.get(fmt, 1)
        if len(data) < width * height * channels:
            raise self._refuse(f"frame of {len(data)} bytes, {width}x{height} {fmt} needs {width * height * channels}")
        raw = np.frombuffer(data, np.uint8, width * height * channels)
        image = raw.reshape(height, width, channels) if channels > 1 else raw.reshape(height, width)
        conversion = _CONVERSIONS.get(fmt)
        if conversion is not None:
            return cv2.cvtColor(image, conversion)
        return image.copy() if channels > 1 else image
