"""The simulated world seen through a GenICam camera: Aravis's in-process Fake camera fed each
rendered frame, so the frames a simulated job picks from have come through Aravis (its stream
thread, its buffers, the driver's trigger and frame checks) and drivers/cameras/genicam.py.

`[sim] camera_source = "genicam:Fake_1"` (docs/cameras.md). At each capture the simulated camera
renders the table, the frame is turned into the Fake camera's pixel format (Mono8, or a Bayer
mosaic), and the driver's capture triggers the Fake camera, whose fill callback copies that frame
into the Aravis buffer it is filling.

Why ctypes and not PyGObject: Aravis 0.8.26 annotates `arv_fake_camera_set_fill_pattern`'s
callback `(scope call)` and has no destroy notifier, so PyGObject frees the callback when the call
returns and the stream thread then calls freed memory (Aravis added the notifier after 0.8.26).
Here the callback is a ctypes function kept alive by this object. And why a private field: the
Fake camera's stream sets the buffer's received size to 0 before filling it, and only the
callback can set it (its default pattern writes `buffer->priv->received_size`); no public call
does. The callback writes that one field, the layout of ArvBufferPrivate's head being the same
from 0.8.26 to Aravis's main branch; it is checked against the public getters at each frame
(the data pointer, the status, then the size read back), and a frame whose layout does not
check out is left empty, which the driver refuses in words.
"""

from __future__ import annotations

import ctypes
import logging
import threading
from typing import Any

import cv2
import numpy as np

from drivers.cameras.base import Camera
from drivers.cameras.errors import CameraError
from drivers.cameras.genicam import FAKE_PREFIX, GenICamCamera

log = logging.getLogger(__name__)

# ArvFakeCameraFillPattern: (ArvBuffer*, void *data, guint32 exposure_us, guint32 gain, ArvPixelFormat)
_FILL = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint32, ctypes.c_uint32)

# Where each colour sits in a 2x2 Bayer tile (row, column), by GenICam's name.
_BAYER: dict[str, dict[str, tuple[int, int]]] = {
    "BayerRG8": {"R": (0, 0), "G1": (0, 1), "G2": (1, 0), "B": (1, 1)},
    "BayerGR8": {"G1": (0, 0), "R": (0, 1), "B": (1, 0), "G2": (1, 1)},
    "BayerBG8": {"B": (0, 0), "G1": (0, 1), "G2": (1, 0), "R": (1, 1)},
    "BayerGB8": {"G1": (0, 0), "B": (0, 1), "R": (1, 0), "G2": (1, 1)},
}
FED_FORMATS = ("Mono8", *_BAYER)


class _GObjectHead(ctypes.Structure):
    """GObject's public instance struct (gobject/gobject.h), the head of every Aravis object."""

    _fields_ = [("g_type_instance", ctypes.c_void_p), ("ref_count", ctypes.c_uint), ("qdata", ctypes.c_void_p)]


class _BufferPrivateHead(ctypes.Structure):
    """The head of Aravis's ArvBufferPrivate (src/arvbufferprivate.h, 0.8.26 to main)."""

    _fields_ = [
        ("allocated_size", ctypes.c_size_t),
        ("is_preallocated", ctypes.c_int),
        ("data", ctypes.c_void_p),
        ("user_data", ctypes.c_void_p),
        ("user_data_destroy_func", ctypes.c_void_p),
        ("status", ctypes.c_int),
        ("received_size", ctypes.c_size_t),
    ]


class _Buffer(ctypes.Structure):
    """struct _ArvBuffer: { GObject object; ArvBufferPrivate *priv; }"""

    _fields_ = [("object", _GObjectHead), ("priv", ctypes.POINTER(_BufferPrivateHead))]


class _Lib:
    """libaravis's and libgobject's few C calls the feed needs (the same libraries PyGObject loaded)."""

    _lock = threading.Lock()
    _loaded: _Lib | None = None

    def __init__(self) -> None:
        arv = ctypes.CDLL("libaravis-0.8.so.0")
        gobject = ctypes.CDLL("libgobject-2.0.so.0")
        # 0.8.26 takes (camera, callback, data); later ones add a GDestroyNotify: a NULL fourth argument
        # suits both (the C calling convention lets a callee ignore an extra argument)
        arv.arv_fake_camera_set_fill_pattern.argtypes = [ctypes.c_void_p, _FILL, ctypes.c_void_p, ctypes.c_void_p]
        arv.arv_fake_camera_set_fill_pattern.restype = None
        arv.arv_buffer_get_data.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_size_t)]
        arv.arv_buffer_get_data.restype = ctypes.c_void_p
        arv.arv_buffer_get_status.argtypes = [ctypes.c_void_p]
        arv.arv_buffer_get_status.restype = ctypes.c_int
        for name in ("arv_buffer_get_image_width", "arv_buffer_get_image_height"):
            getattr(arv, name).argtypes = [ctypes.c_void_p]
            getattr(arv, name).restype = ctypes.c_int
        for name in ("arv_get_major_version", "arv_get_minor_version", "arv_get_micro_version"):
            getattr(arv, name).argtypes = []
            getattr(arv, name).restype = ctypes.c_uint
        gobject.g_type_name_from_instance.argtypes = [ctypes.c_void_p]
        gobject.g_type_name_from_instance.restype = ctypes.c_char_p
        self.arv, self.gobject = arv, gobject
        self.version = (arv.arv_get_major_version(), arv.arv_get_minor_version(), arv.arv_get_micro_version())

    @classmethod
    def get(cls) -> _Lib:
        with cls._lock:
            if cls._loaded is None:
                cls._loaded = cls()
            return cls._loaded


def encode(bgr: np.ndarray, pixel_format: str) -> np.ndarray:
    """A BGR frame as the sensor would give it: Mono8 (luma) or one colour per pixel in a Bayer tile."""
    if pixel_format == "Mono8":
        return np.ascontiguousarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
    tile = _BAYER[pixel_format]
    out = np.empty(bgr.shape[:2], np.uint8)
    for colour, (r, c) in tile.items():
        out[r::2, c::2] = bgr[r::2, c::2, {"B": 0, "G1": 1, "G2": 1, "R": 2}[colour]]
    return out


class FedGenICamCamera(Camera):
    """A GenICam camera on Aravis's Fake interface whose frames are `render`'s (the simulated camera)."""

    def __init__(self, render: Camera, genicam: GenICamCamera):
        if not genicam.wanted.startswith(FAKE_PREFIX):
            raise CameraError(
                f"only Aravis's Fake camera can be fed the simulated frames, not {genicam.wanted}",
                source=genicam.source,
                hint='set sim.camera_source to "sim" or "genicam:Fake_1"',
            )
        if genicam.cfg.pixel_format not in FED_FORMATS:
            raise CameraError(
                f"pixel format {genicam.cfg.pixel_format} cannot be fed the simulated frames",
                source=genicam.source,
                hint=f"set camera.genicam.pixel_format to one of {', '.join(FED_FORMATS)}",
            )
        self.render, self.genicam = render, genicam
        self.source = genicam.source
        self.width_px, self.height_px = genicam.width_px, genicam.height_px
        self.rendered = 0  # frames asked of `render`
        self.fed = 0  # frames the Fake camera's stream took from here
        self.refused: str | None = None  # why the last fill was left empty
        self._lib = _Lib.get()
        self._callback = _FILL(self._fill)  # alive as long as this object: the stream thread calls it
        self._frame: np.ndarray | None = None
        self._fake: Any = None  # the ArvFakeCamera fed (its Python wrapper, holding a reference)

    @property
    def is_connected(self) -> bool:
        return self.genicam.is_connected

    def connect(self) -> None:
        self.genicam.on_warning, self.genicam.on_clear = self.on_warning, self.on_clear
        self.render.connect()
        self.genicam.connect()
        self._attach()

    def disconnect(self) -> None:
        try:
            if self._fake is not None:  # the default pattern again: no call into this object once it is gone
                self._lib.arv.arv_fake_camera_set_fill_pattern(hash(self._fake), _FILL(), None, None)
            self.genicam.disconnect()
        finally:
            self._fake = None
            self.render.disconnect()

    def _grab(self) -> np.ndarray:
        self._frame = encode(self.render.capture(), self.genicam.cfg.pixel_format)
        self.rendered += 1
        self._attach()  # the driver may have opened the camera again (a new Fake camera)
        return self.genicam.capture()

    def _attach(self) -> None:
        camera = self.genicam.aravis_camera
        if camera is None:  # closed or lost: the driver's capture opens it again, then the next one feeds it
            return
        fake = camera.get_device().get_fake_camera()
        if self._fake is not None and hash(fake) == hash(self._fake):
            return
        pointer = hash(fake)  # PyGObject's hash of a GObject wrapper is the object's address
        kind = self._lib.gobject.g_type_name_from_instance(pointer)
        if kind != b"ArvFakeCamera":
            raise CameraError(
                f"cannot feed the Fake camera: its object is a {kind!r}, not an ArvFakeCamera",
                source=self.source,
                hint="this PyGObject does not hash a GObject to its address; run with sim.camera_source = 'sim'",
            )
        self._lib.arv.arv_fake_camera_set_fill_pattern(pointer, self._callback, None, None)
        self._fake = fake
        log.info("camera %s: Aravis %d.%d.%d's Fake camera fed the simulated frames", self.source, *self._lib.version)

    def _fill(self, buffer: int, _data: int, _exposure_us: int, _gain: int, _pixel_format: int) -> None:
        """In Aravis's stream thread: the latest rendered frame into `buffer` (its geometry already set)."""
        try:
            self._fill_buffer(buffer)
        except Exception as e:  # an exception must not cross into C: the frame is left empty, refused in words
            self.refused = f"{type(e).__name__}: {e}"
            log.error("camera %s: feeding the Fake camera: %s", self.source, self.refused)

    def _fill_buffer(self, buffer: int) -> None:
        arv = self._lib.arv
        frame = self._frame
        width, height = arv.arv_buffer_get_image_width(buffer), arv.arv_buffer_get_image_height(buffer)
        if frame is None or frame.shape != (height, width):
            self.refused = f"no rendered frame of {width}x{height} px to feed"
            return
        size = ctypes.c_size_t()
        data = arv.arv_buffer_get_data(buffer, ctypes.byref(size))
        priv = _Buffer.from_address(buffer).priv.contents
        if priv.data != data or priv.received_size != size.value or priv.status != arv.arv_buffer_get_status(buffer):
            self.refused = f"Aravis {'.'.join(map(str, self._lib.version))}'s buffer is not laid out as expected"
            return
        if priv.allocated_size < frame.nbytes:
            self.refused = f"buffer of {priv.allocated_size} bytes, the frame has {frame.nbytes}"
            return
        ctypes.memmove(data, frame.ctypes.data, frame.nbytes)
        priv.received_size = frame.nbytes
        arv.arv_buffer_get_data(buffer, ctypes.byref(size))
        if size.value != frame.nbytes:  # the field written is not the one the getter reads: give nothing
            priv.received_size = 0
            self.refused = f"Aravis {'.'.join(map(str, self._lib.version))}'s received size is not where expected"
            return
        self.refused = None
        self.fed += 1


def fed_genicam(render: Camera, genicam: Camera) -> FedGenICamCamera:
    """`render`'s frames through `genicam` (the driver built for a Fake camera with camera's settings)."""
    if not isinstance(genicam, GenICamCamera):
        raise CameraError(
            f"{genicam.source} is not a GenICam camera", source=genicam.source, hint='use "genicam:Fake_1"'
        )
    return FedGenICamCamera(render, genicam)
