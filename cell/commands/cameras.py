"""`run-cell cameras`: every camera this computer sees, on every interface, with the config line
that uses it: video devices for OpenCV (camera.source = their index) and GenICam cameras (GigE
Vision, USB3 Vision) through Aravis (camera.source = "genicam:<id>")."""

from __future__ import annotations

import argparse

from drivers.cameras.errors import CameraError
from drivers.cameras.opencv import video_devices

DESCRIPTION = (
    "List every camera this computer sees and the [camera] line that uses it: the video devices OpenCV "
    "opens by index (webcams, UVC), and GenICam cameras (GigE Vision, USB3 Vision) found by Aravis with "
    "their vendor, model, serial number, address and interface. GigE discovery waits about a second for "
    "the cameras' replies. docs/cameras.md says how to choose and wire one."
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "cameras", help="list the cameras on every interface, with the config line to use", description=DESCRIPTION
    )
    p.add_argument(
        "--fake", action="store_true", help="include Aravis's in-process Fake camera (for trying the GenICam path)"
    )
    p.set_defaults(func=cmd_cameras)


def cmd_cameras(args: argparse.Namespace) -> int:
    videos = video_devices()
    print(f"OpenCV video devices: {len(videos) or 'none'}")
    for index, name in videos:
        label = f" ({name})" if name else ""
        print(f"  /dev/video{index}{label}")
        print(f'      [camera] source = "{index}"')
    try:
        from drivers.cameras.genicam import list_devices

        devices = list_devices(fake=args.fake)
    except CameraError as e:  # Aravis or PyGObject absent: say so, the OpenCV part stands
        print(f"GenICam cameras: none listed: {e}")
        return 0
    print(f"GenICam cameras (Aravis): {len(devices) or 'none'}")
    for d in devices:
        print(f"  {d.vendor} {d.model}, serial {d.serial or '?'}, address {d.address or '-'}, {d.interface}")
        print(f'      [camera] source = "{d.source}"')
    if not devices:
        print(
            "  (none answered: for GigE check the cable, the link's address, the firewall and rp_filter; docs/cameras.md)"
        )
    return 0
