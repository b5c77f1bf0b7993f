"""`run-cell ports`, `run-cell jog` and `run-cell home`: the operator's hands on the arm."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import get_args

from serial.tools import list_ports

from cell.assembly import arm_only
from cell.commands.argtypes import finite_float
from cell.config import CellConfig, load_config
from cell.errors import InputError
from drivers.arm.base import Arm
from drivers.arm.config import ArmKind

log = logging.getLogger(__name__)


def register(sub) -> None:
    p = sub.add_parser(
        "ports",
        help="list serial ports with their USB descriptions",
        description="List the serial ports with their USB descriptions and IDs: which one is the arm "
        "(arm.port), a GRBL board or a Dynamixel U2D2.",
    )
    p.set_defaults(func=cmd_ports)

    j = sub.add_parser(
        "jog",
        help="move the gripper to a robot-frame point, or open/close it",
        description="Connect the configured arm and move the gripper to a point in the robot's base frame (mm), "
        "or open or close it. The target is checked against the arm's limits before anything is sent; "
        "prints where the arm is afterwards.",
    )
    add_arm_arguments(j)
    what = j.add_mutually_exclusive_group(required=True)
    what.add_argument(
        "--to", nargs=3, type=finite_float, metavar=("X", "Y", "Z"), help="target in mm, robot base frame"
    )
    what.add_argument("--gripper", choices=["open", "close"], help="open or close the gripper (instead of --to)")
    j.add_argument("--angle", type=finite_float, metavar="DEG", help="gripper angle about the vertical, with --to")
    j.set_defaults(func=cmd_jog)

    h = sub.add_parser(
        "home",
        help="home the arm (homing cycle or home pose)",
        description="Connect the configured arm and home it: GRBL's homing cycle ($H; needs $22=1 and limit "
        "switches), or a servo arm's home pose. Prints where the arm is afterwards.",
    )
    add_arm_arguments(h)
    h.set_defaults(func=cmd_home)


def add_arm_arguments(p: argparse.ArgumentParser) -> None:
    # SUPPRESS: the same options given before the sub-command (`run-cell --arm serial jog ...`) still count.
    p.add_argument("--config", type=Path, default=argparse.SUPPRESS, help="cell config TOML (default: built-in)")
    p.add_argument("--arm", choices=get_args(ArmKind), default=argparse.SUPPRESS, help="override arm.kind")
    p.add_argument("--port", default=argparse.SUPPRESS, help="override arm.port (device path or pyserial URL)")


def _config(args: argparse.Namespace) -> CellConfig:
    """The config from --config (or run-cell's own --config); --arm / --port are applied by arm_only."""
    return load_config(getattr(args, "config", None) or getattr(args, "run_config", None))


def jog(
    arm: Arm,
    to_mm: tuple[float, float, float] | None = None,
    angle_deg: float | None = None,
    gripper: str | None = None,
) -> None:
    """One jog on a connected arm, returning once it is done; what `run-cell teach` repeats."""
    if to_mm is not None:
        arm.move_to(*to_mm, angle_deg=angle_deg)
    if gripper == "open":
        arm.open_gripper()
    elif gripper == "close":
        arm.close_gripper()


def cmd_ports(args: argparse.Namespace) -> int:
    ports = sorted(list_ports.comports(), key=lambda p: p.device)
    if not ports:
        print("no serial ports found (is the arm's USB cable plugged in?)")
        return 0
    for p in ports:
        print(f"{p.device}\t{p.description}\t{p.hwid}")
    return 0


def cmd_jog(args: argparse.Namespace) -> int:
    if args.angle is not None and args.to is None:
        raise InputError("--angle goes with --to X Y Z")
    with arm_only(_config(args), getattr(args, "arm", None), getattr(args, "port", None)) as arm:
        if args.to is not None:
            x_mm, y_mm, z_mm = args.to
            arm.check_target(x_mm, y_mm, z_mm, args.angle)  # refuse before connecting, let alone moving
        with arm:  # the port is ours alone before anything is sent on it
            jog(arm, tuple(args.to) if args.to else None, args.angle, args.gripper)
            print(_describe(arm))
    return 0


def cmd_home(args: argparse.Namespace) -> int:
    with arm_only(_config(args), getattr(args, "arm", None), getattr(args, "port", None)) as arm, arm:
        arm.home()
        print(_describe(arm))
    return 0


def _describe(arm: Arm) -> str:
    s = arm.status()
    where = (
        "position unknown"
        if s.pose is None
        else (f"x={s.pose.x_mm:.2f} y={s.pose.y_mm:.2f} z={s.pose.z_mm:.2f} mm, angle {s.pose.angle_deg:.1f} deg")
    )
    grip = {None: "", True: ", gripper closed", False: ", gripper open"}[s.gripper_closed]
    return f"arm on {arm.port}: {s.state}, {where}{grip}"
