"""Frame sources: folders, video files, devices; no frame or a wrong size is a CameraError."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from cell.config import CameraConfig
from drivers.cameras.errors import CameraError
from drivers.cameras.factory import make_camera
from drivers.cameras.folder import FolderCamera
from drivers.cameras.opencv import OpenCVCamera
from drivers.cameras.video import VideoFileCamera


def frames(n, w=64, h=48):
    return [np.full((h, w, 3), 40 * i, np.uint8) for i in range(n)]


def test_folder_gives_images_in_name_order_then_a_clear_error(tmp_path):
    for i, f in enumerate(frames(2)):
        cv2.imwrite(str(tmp_path / f"{i:03d}.png"), f)
    (tmp_path / "notes.txt").write_text("ignored")
    with FolderCamera(tmp_path, 64, 48) as cam:
        assert cam.capture()[0, 0, 0] == 0 and cam.capture()[0, 0, 0] == 40
        with pytest.raises(CameraError, match="no more images"):
            cam.capture()
    with FolderCamera(tmp_path, 64, 48, loop=True) as cam:
        assert [cam.capture()[0, 0, 0] for _ in range(3)] == [0, 40, 0]


def test_wrong_frame_size_is_a_camera_error_naming_both_sizes(tmp_path):
    cv2.imwrite(str(tmp_path / "a.png"), frames(1)[0])
    with FolderCamera(tmp_path, 1920, 1080) as cam, pytest.raises(CameraError, match="64x48 px, expected 1920x1080"):
        cam.capture()


def test_empty_or_missing_folder_and_unreadable_image(tmp_path):
    with pytest.raises(CameraError, match="no images"):
        FolderCamera(tmp_path, 64, 48).connect()
    with pytest.raises(CameraError, match="not found"):
        FolderCamera(tmp_path / "nope", 64, 48).connect()
    (tmp_path / "x.png").write_bytes(b"not a png")
    with FolderCamera(tmp_path, 64, 48) as cam, pytest.raises(CameraError, match="not a readable image"):
        cam.capture()


def test_capture_before_connect_is_an_error(tmp_path):
    with pytest.raises(CameraError, match="before connect"):
        FolderCamera(tmp_path, 64, 48).capture()


def test_video_file_frames_then_end(tmp_path):
    path = tmp_path / "v.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 5, (64, 48))
    for f in frames(3):
        writer.write(f)
    writer.release()
    with VideoFileCamera(path, 64, 48) as cam:
        got = [cam.capture() for _ in range(3)]
        assert all(g.shape == (48, 64, 3) for g in got)
        with pytest.raises(CameraError, match="no more frames"):
            cam.capture()
    with pytest.raises(CameraError, match="not found"):
        VideoFileCamera(tmp_path / "none.avi", 64, 48).connect()


def test_a_device_that_cannot_be_opened_is_a_camera_error():
    with pytest.raises(CameraError, match="cannot open"):
        OpenCVCamera("/dev/video-does-not-exist-77", 640, 480, timeout_s=1.0, warmup_frames=0).connect()


def test_factory_picks_the_source_kind(tmp_path):
    assert isinstance(make_camera(CameraConfig(source=str(tmp_path))), FolderCamera)
    (tmp_path / "v.avi").write_bytes(b"")
    assert isinstance(make_camera(CameraConfig(source=str(tmp_path / "v.avi"))), VideoFileCamera)
    assert isinstance(make_camera(CameraConfig(source="0")), OpenCVCamera)
    assert isinstance(make_camera(CameraConfig(source="rtsp://cam.local/stream")), OpenCVCamera)
    with pytest.raises(CameraError, match="no such device"):
        make_camera(CameraConfig(source=str(tmp_path / "missing")))


def test_a_folder_image_of_the_wrong_size_is_refused_from_its_header(tmp_path):
    """A 20000 x 20000 PNG (1.2 GB once decoded) in the folder is never decoded."""
    import struct
    import zlib

    ihdr = struct.pack(">IIBBBBB", 20000, 20000, 8, 2, 0, 0, 0)
    (tmp_path / "big.png").write_bytes(
        b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    )
    with (
        FolderCamera(tmp_path, 64, 48) as cam,
        pytest.raises(CameraError, match="big.png: frame is 20000x20000 px, expected 64x48 px; not decoded"),
    ):
        cam.capture()
