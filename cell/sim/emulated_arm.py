"""The real arm driver against its emulated firmware on a pseudo-terminal, acting on the
simulated world, so what the camera sees next is what the driver made the emulated arm do.

The driver comes from the normal factory with arm.port set to the pty: every command goes
through the real protocol code. The emulator's gripper events decide the world: closing
grips at the emulated tool point and jaw angle, opening releases there. The emulated GRBL
machine has an A axis turning the gripper; without arm.serial.commands.rotate it stands for a
3-axis gantry whose jaws close at arm.serial.fixed_jaw_angle_deg, and the driver refuses a grip
at any other angle (beyond fixed_jaw_tolerance_deg); the emulated bus knows the arm's config, so its tool pose
comes from the servos' present positions through the arm's kinematics.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Literal

from cell.sim.world import World
from drivers.arm.base import Arm
from drivers.arm.config import ArmConfig
from drivers.arm.factory import make_arm
from drivers.sim.dxl_emulator import DxlBusEmulator
from drivers.sim.emulated_device import ToolListener
from drivers.sim.grbl_emulator import GrblEmulator
from drivers.sim.pty_port import serve_pty

log = logging.getLogger(__name__)
EMULATED_LATENCY_TIMER_MS = 250.0  # status wait about 0.5 s a try: an emulator thread starved by a loaded machine (stalls of 0.6 s seen) still answers; a prompt reply costs no more

Emulator = GrblEmulator | DxlBusEmulator


@dataclass(frozen=True)
class EmulatedArm:
    """The real driver (unconnected when handed out) and the emulator behind its port."""

    arm: Arm
    emulator: Emulator
    port: str
    speed_scale: float

    @property
    def firmware(self) -> str:
        return "GRBL 1.1" if isinstance(self.emulator, GrblEmulator) else "Dynamixel XM430 bus"

    def motion_time_s(self) -> float:
        """Machine time the emulated arm has spent moving, at its own speed (not scaled)."""
        with self.emulator.lock:
            return self.emulator.motion_time_s


@contextlib.contextmanager
def emulated_arm(
    cfg: ArmConfig,
    world: World,
    speed_scale: float,
    fault_after_grips: int = 0,
    fault: Literal["alarm", "restart"] = "alarm",
) -> Iterator[EmulatedArm]:
    """Serve the emulator for cfg.kind on a fresh pty and yield the real driver for it; on exit
    (faults and Ctrl-C included) the driver's port is closed, the emulator stopped and the pty gone.

    fault_after_grips > 0 rehearses a fault as grip N closes: "alarm": GRBL raises ALARM:1 (hard
    limit) on its next move, or the Dynamixel gripper servo overloads; "restart": the controller
    restarts at once (GRBL's banner, its position counted from zero; every servo's supply dips).
    """
    emulator: GrblEmulator | DxlBusEmulator
    if cfg.kind == "serial":
        emulator, name = GrblEmulator(speed_scale=speed_scale, rotary_axis=True), "ttyGRBL"
    elif cfg.kind == "dynamixel":
        emulator, name = DxlBusEmulator(cfg.dynamixel, speed_scale=speed_scale), "ttyDXL"
    else:
        raise ValueError(f"no emulator for arm.kind {cfg.kind!r}")
    emulator.add_tool_listener(_acting_on(world, _fixed_jaws_deg(cfg)))
    if fault_after_grips:
        emulator.add_tool_listener(_fault_after(emulator, fault_after_grips, cfg.dynamixel.gripper_id, fault))
    with serve_pty(emulator, name) as path:
        arm = make_arm(_for_emulator(cfg, path))
        log.info("emulated %s arm on %s at %gx speed", cfg.kind, path, speed_scale)
        try:
            yield EmulatedArm(arm, emulator, path, speed_scale)
        finally:
            arm.disconnect()  # before the pty goes away under it


def _for_emulator(cfg: ArmConfig, path: str) -> ArmConfig:
    """The arm's config on the emulator's pty. The emulated bus answers from a Python thread that
    shares the CPU with the cell (and a test run's workers), so it gets a status wait of a
    loaded machine rather than a U2D2's 16 ms latency timer."""
    dxl = cfg.dynamixel.model_copy(
        update={"latency_timer_ms": max(cfg.dynamixel.latency_timer_ms, EMULATED_LATENCY_TIMER_MS)}
    )
    return cfg.model_copy(update={"port": path, "dynamixel": dxl})


def _fixed_jaws_deg(cfg: ArmConfig) -> float:
    """Where a G-code machine without a rotation axis has its jaws closing (the emulator's A axis then
    never turns: 0 plus this); 0 for the others, whose pose gives the angle."""
    if cfg.kind == "serial" and not cfg.serial.commands.rotate:
        return cfg.serial.fixed_jaw_angle_deg
    return 0.0


def _acting_on(world: World, jaws_offset_deg: float = 0.0) -> ToolListener:
    """The jaws act on the world where the emulated arm really is, not where it was told to go."""

    def on_gripper(closed: bool, x_mm: float, y_mm: float, z_mm: float, angle_deg: float) -> None:
        xyz = (x_mm, y_mm, z_mm)
        angle_deg += jaws_offset_deg
        what = world.grip(xyz, angle_deg).reason if closed else world.release(xyz)
        log.debug(
            "emulated gripper %s at (%.2f, %.2f, %.2f) mm, %.2f deg: %s",
            "closed" if closed else "opened",
            x_mm,
            y_mm,
            z_mm,
            angle_deg,
            what,
        )

    return on_gripper


def _fault_after(emulator: Emulator, grips: int, gripper_id: int, fault: str) -> ToolListener:
    """Arms the emulator's own fault injection at grip `grips`, so the driver meets it as it would on the line."""
    closes = 0

    def on_gripper(closed: bool, *pose: float) -> None:
        nonlocal closes
        closes += closed
        if closed and closes == grips:
            log.info("rehearsed fault (%s): armed after grip %d", fault, grips)
            grbl = isinstance(emulator, GrblEmulator)
            if fault == "restart":
                emulator.inject("restart" if grbl else "reboot")
            elif grbl:
                emulator.inject("alarm", code=1)
            else:
                emulator.inject("overload", id=gripper_id)

    return on_gripper
