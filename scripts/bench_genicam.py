#!/usr/bin/env python3
"""GenICam benchmark: a GigE Vision camera over loopback beside OpenCV reading the same frames from a file.

Starts Aravis's fake GigE Vision camera (`arv-fake-gv-camera-0.8`, Debian aravis-tools) on 127.0.0.1
and opens it through the cell's driver (camera.source = "genicam:127.0.0.1"), 1920 x 1080 Mono8:

1. request to frame: --frames software-triggered captures, each timed from the call to the BGR frame
   in hand (wall, median / p95), and the CPU of this process per frame (time.process_time: Aravis's
   receiving thread included). The fake camera serves a software trigger at its next frame tick, so
   its AcquisitionFrameRate is set to 200 (5 ms ticks; faster, the fake answers its control channel
   late): the figure holds the fake's tick and its sending, beside the transport and the driver.
2. the reference, in the same run: the same frames written to a video file (FFV1, lossless) and read
   back through the cell's video-file camera (OpenCV), timed the same way.
3. sustained: free-run at --fps for --seconds, the frames read as they come; the stream's own counters
   (Aravis: completed, failed, missing frames and packets) over the whole run, at 0 % configured loss.

4. --pulls N (instead of the above): the camera killed and started again N times under an open driver
   (each: a capture lost in words, then captures until it is back); this process's descriptors,
   threads and resident memory before and after (and 15 s after, when Aravis has let go).

    python scripts/bench_genicam.py [--frames 100] [--fps 30] [--seconds 5] [--packet-size 8192]
    python scripts/bench_genicam.py --pulls 100
"""

from __future__ import annotations

import argparse
import fcntl
import os
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers.cameras.config import GenICamConfig  # noqa: E402
from drivers.cameras.errors import CameraError  # noqa: E402
from drivers.cameras.genicam import GenICamCamera  # noqa: E402
from drivers.cameras.video import VideoFileCamera  # noqa: E402

W, H = 1920, 1080


def gvcp_port_free() -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(("127.0.0.1", 3956))
        except OSError:
            return False
    return True


def genicam(**settings: object) -> GenICamCamera:
    """The cell's driver as make_camera builds it for camera.source = "genicam:127.0.0.1"."""
    return GenICamCamera("127.0.0.1", W, H, 5.0, GenICamConfig.model_validate(settings))


def timed(capture: Callable[[], np.ndarray], n: int) -> tuple[list[float], float, list[np.ndarray]]:
    """(wall ms per frame, CPU ms per frame, the frames)."""
    walls, frames = [], []
    cpu0 = time.process_time()
    for _ in range(n):
        t0 = time.perf_counter()
        frames.append(capture())
        walls.append(1e3 * (time.perf_counter() - t0))
    return walls, 1e3 * (time.process_time() - cpu0) / n, frames


def p95(values: list[float]) -> float:
    return sorted(values)[max(0, int(round(0.95 * len(values))) - 1)]


def line(name: str, walls: list[float], cpu_ms: float) -> str:
    return f"{name:<44} {statistics.median(walls):8.2f} {p95(walls):8.2f} {cpu_ms:10.2f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--pulls", type=int, default=0, help="only the cable-pull soak, N times")
    ap.add_argument(
        "--packet-size", type=int, default=None, help="GigE stream packet size in bytes (default: Aravis negotiates)"
    )
    args = ap.parse_args()
    fake = shutil.which("arv-fake-gv-camera-0.8")
    if fake is None:
        sys.exit("bench_genicam: no arv-fake-gv-camera-0.8 (Debian aravis-tools)")
    # the tests' lock on the one fake camera port: held for the whole run, so a test started meanwhile
    # waits rather than taking 127.0.0.1:3956 while the camera is pulled
    lock = os.open(Path(tempfile.gettempdir()) / "pick-cell-arv-fake-gv.lock", os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not gvcp_port_free():
            sys.exit("bench_genicam: 127.0.0.1:3956 (GVCP) is taken: another fake camera runs")
        fake_camera = FakeCamera(fake)
        try:
            if args.pulls:
                pulls(fake_camera, args.pulls)
            else:
                run(args)
        finally:
            fake_camera.stop()
    finally:
        os.close(lock)


class FakeCamera:
    def __init__(self, program: str):
        self.program = program
        self.proc = self.start()

    def start(self) -> subprocess.Popen[bytes]:
        proc = subprocess.Popen(
            [self.program, "-i", "127.0.0.1", "-s", "BENCH"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        while gvcp_port_free():
            time.sleep(0.02)
        return proc

    def stop(self) -> None:
        self.proc.kill()
        self.proc.wait()


def held() -> str:
    fds = len(os.listdir("/proc/self/fd"))
    threads = len(os.listdir("/proc/self/task"))
    with open("/proc/self/statm") as f:
        rss_mb = int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    return f"{fds} descriptors, {threads} threads, {rss_mb:.1f} MB resident"


def pulls(fake: FakeCamera, n: int) -> None:
    camera = GenICamCamera(
        "BENCH", 640, 480, 10.0, GenICamConfig(acquisition_timeout_s=1.0, features={"AcquisitionFrameRate": 200.0})
    )
    with camera:
        camera.capture()
        print(f"before: {held()}", flush=True)
        t0 = time.monotonic()
        for i in range(n):
            fake.stop()
            try:
                camera.capture()
                sys.exit("bench_genicam: a frame from a camera that is gone")
            except CameraError as e:
                assert " lost: " in str(e), e
            fake.proc = fake.start()
            while True:
                try:
                    camera.capture()
                    break
                except CameraError:
                    continue
            if (i + 1) % 10 == 0:
                print(f"after {i + 1} pulls: {held()}", flush=True)
        elapsed = time.monotonic() - t0
        time.sleep(15)
        print(
            f"15 s later: {held()}; lost {camera.stats.lost}, back {camera.stats.reconnects}, {elapsed / n:.1f} s a pull"
        )


def run(args: argparse.Namespace) -> None:
    cv2.setNumThreads(1)
    size = f"{args.packet_size} B packets" if args.packet_size else "packet size negotiated"
    print(f"{W} x {H} Mono8, {size}, {args.frames} frames; ms per frame (load average {os.getloadavg()[0]:.1f})")
    print(f"{'source':<44} {'median':>8} {'p95':>8} {'CPU/frame':>10}")
    camera = genicam(exposure_us=1000.0, packet_size_bytes=args.packet_size, features={"AcquisitionFrameRate": 200.0})
    with camera:
        print(f"(GigE stream packets of {camera.settings()['packet_size_bytes']} bytes)")
        camera.capture()  # the first: buffers touched, the path warm
        first_packet_ms: list[float] = []

        def capture() -> np.ndarray:
            asked_ns = time.time_ns()
            frame = camera.capture()
            assert camera.last_frame is not None
            first_packet_ms.append((camera.last_frame.system_timestamp_ns - asked_ns) / 1e6)
            return frame

        walls, cpu, frames = timed(capture, args.frames)
        counters = camera.stream_counters()
    print(line("GigE Vision over loopback, software trigger", walls, cpu))
    print(
        f"  of which from the request to the frame's first packet (the fake's tick and fill): median "
        f"{statistics.median(first_packet_ms):.2f} ms; the rest is the transfer and the driver"
    )
    with tempfile.TemporaryDirectory() as tmp:
        video = Path(tmp) / "frames.mkv"
        writer = cv2.VideoWriter(str(video), cv2.VideoWriter.fourcc(*"FFV1"), 30, (W, H), isColor=False)
        if not writer.isOpened():
            sys.exit("bench_genicam: OpenCV cannot write FFV1 here")
        for frame in frames:
            writer.write(frame[:, :, 0])
        writer.release()
        reference = VideoFileCamera(video, W, H)
        with reference:
            ref_walls, ref_cpu, ref_frames = timed(reference.capture, args.frames)
        same = all(np.array_equal(a, b) for a, b in zip(frames, ref_frames, strict=True))
    print(
        line("OpenCV, the same frames from a file (FFV1)", ref_walls, ref_cpu) + ("" if same else "  (frames differ!)")
    )
    print(
        f"stream during the triggered run: {counters.get('n_completed_buffers', 0)} complete, "
        f"{counters.get('n_failures', 0)} failed, {counters.get('n_missing_packets', 0)} packets missing"
    )
    camera = genicam(
        trigger="free-run", packet_size_bytes=args.packet_size, features={"AcquisitionFrameRate": args.fps}
    )
    with camera:
        start_counters = camera.stream_counters()
        t0 = time.monotonic()
        cpu0 = time.process_time()
        taken, ids = 0, []
        while time.monotonic() - t0 < args.seconds:
            camera.capture()
            taken += 1
            assert camera.last_frame is not None
            ids.append(camera.last_frame.frame_id)
        elapsed = time.monotonic() - t0
        cpu = time.process_time() - cpu0
        end = camera.stream_counters()
    done = end["n_completed_buffers"] - start_counters["n_completed_buffers"]
    sent = sum((b - a) % 65536 or 65536 for a, b in zip(ids, ids[1:], strict=False))  # GigE Vision 1: 16-bit ids
    lost = {
        k: end[k] - start_counters[k] for k in ("n_failures", "n_missing_frames", "n_missing_packets", "n_underruns")
    }
    print(
        f"free-run at {args.fps:g} frames/s for {elapsed:.1f} s: the camera sent {sent / elapsed:.1f} "
        f"frames/s (its frame ids), the stream received {done / elapsed:.1f} frames/s complete; "
        f"failed {lost['n_failures']}, frames missing {lost['n_missing_frames']}, packets missing "
        f"{lost['n_missing_packets']}, no buffer free {lost['n_underruns']}; captures {taken} "
        f"(each the first frame begun after its call); CPU {100 * cpu / elapsed:.0f} % of a core"
    )


if __name__ == "__main__":
    main()
