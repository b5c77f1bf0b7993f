"""Arm configuration: one model per device kind, validated like the rest of the cell's TOML.

Lengths in mm, angles in degrees, times in seconds; servo quantities in the servo's own
units (ticks), named so. Every model forbids unknown keys so a typo names itself.
"""

from __future__ import annotations

import ipaddress
import math
import string
from typing import Literal

from pydantic import Field, field_validator, model_validator

from drivers.config import Strict

# Placeholders each serial command template may use, with sample values for validation.
TEMPLATE_FIELDS = {"x_mm": 1.0, "y_mm": 2.0, "z_mm": 3.0, "angle_deg": 4.0, "feed_mm_min": 600.0}


class Workspace(Strict):
    """Box, in the robot base frame, that targets must lie in; checked before anything is sent."""

    x_min_mm: float = Field(0.0, description="smallest X of a move target, robot mm (the arm's base frame)")
    x_max_mm: float = Field(200.0, description="largest X of a move target, robot mm (the arm's base frame)")
    y_min_mm: float = Field(0.0, description="smallest Y of a move target, robot mm (the arm's base frame)")
    y_max_mm: float = Field(200.0, description="largest Y of a move target, robot mm (the arm's base frame)")
    z_min_mm: float = Field(0.0, description="lowest Z of a move target, robot mm (the arm's base frame)")
    z_max_mm: float = Field(200.0, description="highest Z of a move target, robot mm (the arm's base frame)")

    @model_validator(mode="after")
    def _ordered(self) -> Workspace:
        for axis in "xyz":
            lo, hi = getattr(self, f"{axis}_min_mm"), getattr(self, f"{axis}_max_mm")
            if lo >= hi:
                raise ValueError(f"{axis}_min_mm ({lo:g} mm) must be below {axis}_max_mm ({hi:g} mm)")
        return self

    def violation(self, x_mm: float, y_mm: float, z_mm: float) -> str | None:
        """Why the point is outside the box, or None if inside."""
        for axis, v in zip("xyz", (x_mm, y_mm, z_mm), strict=True):
            lo, hi = getattr(self, f"{axis}_min_mm"), getattr(self, f"{axis}_max_mm")
            if not math.isfinite(v) or not lo <= v <= hi:
                return f"{axis} = {v:g} mm is outside the workspace [{lo:g}, {hi:g}] mm"
        return None


class SerialCommands(Strict):
    """G-code templates, so GRBL, Marlin, uArm or custom firmware fit by configuration.

    Placeholders: {x_mm} {y_mm} {z_mm} {angle_deg} {feed_mm_min}. An empty string means the
    arm lacks that function.
    """

    setup: list[str] = Field(["G21", "G90"], description="sent after connect: mm units, absolute mode")
    rapid: str = Field(
        "G0 X{x_mm:.3f} Y{y_mm:.3f} Z{z_mm:.3f}", description="a move at the firmware's top speed (rapid_moves true)"
    )
    feed: str = Field(
        "G1 X{x_mm:.3f} Y{y_mm:.3f} Z{z_mm:.3f} F{feed_mm_min:.0f}",
        description="a move at speed_mm_s (rapid_moves false, the default); {feed_mm_min} is speed_mm_s x 60",
    )
    rotate: str = Field("", description="turns the tool to angle_deg, e.g. 'G0 A{angle_deg:.2f}'")
    gripper_open: str = Field(
        "M5", description="opens the gripper (default: GRBL's spindle off, for a gripper on the spindle output)"
    )
    gripper_close: str = Field("M3 S1000", description="closes the gripper (default: GRBL's spindle on at S1000)")
    wait: str = Field("G4 P0", description="answered only once all motion is done ('M400' on Marlin)")
    home: str = Field("$H", description="homing cycle; empty: move to home_position_mm instead")
    stop: str = Field(
        "!", description="stops motion at once: GRBL's real-time feed hold '!' (no newline), or a line ('M410')"
    )

    @field_validator("rapid", "feed", "rotate", "gripper_open", "gripper_close", "wait", "home", "stop")
    @classmethod
    def _template_ok(cls, v: str) -> str:
        _check_template(v)
        return v

    @field_validator("setup")
    @classmethod
    def _setup_ok(cls, v: list[str]) -> list[str]:
        for line in v:
            _check_template(line)
        return v


def _check_template(template: str) -> None:
    if "\n" in template or "\r" in template:
        raise ValueError(f"{template!r}: one G-code line only, no line breaks")
    try:
        names = {f for _, f, _, _ in string.Formatter().parse(template) if f is not None}
    except ValueError as e:
        raise ValueError(f"bad template {template!r}: {e}") from None
    unknown = names - set(TEMPLATE_FIELDS)
    if unknown:
        raise ValueError(
            f"unknown placeholder {{{sorted(unknown)[0]}}} in {template!r} "
            f"(allowed: {', '.join('{' + k + '}' for k in TEMPLATE_FIELDS)})"
        )
    try:
        template.format(**TEMPLATE_FIELDS)
    except (ValueError, IndexError) as e:
        raise ValueError(f"bad template {template!r}: {e}") from None


class SerialArmConfig(Strict):
    """A G-code arm on a serial line; GRBL 1.1 at its defaults unless told otherwise."""

    baud: int = Field(
        115200, ge=300, le=4_000_000, description="serial line speed in bit/s, as the controller's firmware expects it"
    )
    command_timeout_s: float = Field(2.0, gt=0, le=60, description="longest wait for 'ok' to a command")
    motion_timeout_s: float = Field(
        10.0,
        gt=0,
        le=600,
        description="shortest wait for motion to finish: the floor of each move's own timeout (its expected time "
        "from length, feed, max_rate_mm_min and acceleration_mm_s2, times motion_margin_factor, plus "
        "motion_margin_s), and the wait when nothing is queued",
    )
    motion_margin_factor: float = Field(
        1.5, ge=1, le=10, description="a move's timeout is its expected time times this, plus motion_margin_s"
    )
    motion_margin_s: float = Field(
        2.0, ge=0, le=600, description="added to a move's timeout: status polling, the wait barrier, the link's latency"
    )
    max_rate_mm_min: tuple[float, float, float] = Field(
        (500.0, 500.0, 500.0),
        description="each axis' top speed X, Y, Z in mm/min, the firmware's $110-$112 (GRBL's default 500): "
        "caps the feed and is the rapid rate; for the motion timeout only",
    )
    acceleration_mm_s2: tuple[float, float, float] = Field(
        (10.0, 10.0, 10.0),
        description="each axis' acceleration X, Y, Z in mm/s^2, the firmware's $120-$122 (GRBL's default 10); "
        "for the motion timeout only",
    )
    rotation_rate_deg_min: float = Field(
        500.0, gt=0, le=1_000_000, description="speed of commands.rotate in deg/min ($113 on 4-axis firmware)"
    )
    homing_timeout_s: float = Field(
        120.0, gt=0, le=1800, description="longest wait for the homing cycle (commands.home, GRBL's $H)"
    )
    connect_timeout_s: float = Field(3.0, gt=0, le=60, description="longest wait for the start-up banner")
    reconnect_timeout_s: float = Field(10.0, ge=0, le=600, description="how long to wait for a re-plugged port")
    poll_interval_s: float = Field(0.05, gt=0, le=5, description="period of '?' status queries while moving")
    status_query: bool = Field(True, description="firmware answers the GRBL real-time '?' status query")
    soft_reset_on_connect: bool = Field(True, description="send Ctrl-X and expect the GRBL banner on connect")
    speed_mm_s: float = Field(50.0, gt=0, le=5000, description="feed for moves; 0-length rapid moves unused")
    rapid_moves: bool = Field(False, description="use the rapid template (firmware's top speed) for moves")
    fixed_jaw_angle_deg: float = Field(
        0.0,
        ge=-90,
        le=90,
        description="without commands.rotate (a 3-axis machine): the direction the jaws close, robot frame, "
        "degrees counter-clockwise from +X; a grip asked at another angle is refused (the part left, with why)",
    )
    fixed_jaw_tolerance_deg: float = Field(
        5.0,
        gt=0,
        le=90,
        description="without commands.rotate: how far a grip's angle may be from fixed_jaw_angle_deg and still be "
        "made at the fixed angle (a bolt's jaws across its axis within this; the simulated jaws grip within 5)",
    )
    home_position_mm: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="where `home` moves when commands.home is empty"
    )
    workspace: Workspace = Workspace()
    commands: SerialCommands = SerialCommands()

    @model_validator(mode="after")
    def _consistent(self) -> SerialArmConfig:
        if not self.commands.home and (why := self.workspace.violation(*self.home_position_mm)):
            raise ValueError(f"home_position_mm: {why}")
        for name in ("max_rate_mm_min", "acceleration_mm_s2"):
            if not all(math.isfinite(v) and v > 0 for v in getattr(self, name)):
                raise ValueError(f"{name}: every axis needs a positive number, got {list(getattr(self, name))}")
        if not self.commands.wait and not self.status_query:
            raise ValueError("commands.wait is empty and status_query is false: the end of a move could not be known")
        return self


class Geometry(Strict):
    """A 4-axis arm (base yaw, shoulder, elbow, wrist pitch), gripper pointing down.

    Defaults: ROBOTIS OpenManipulator-X. Base frame: origin at the base, x forward, z up.
    """

    yaw_axis_x_mm: float = Field(12.0, ge=-500, le=500, description="x of the base yaw axis in the base frame")
    shoulder_height_mm: float = Field(76.5, ge=0, le=2000, description="shoulder axis above the base origin")
    upper_arm_rise_mm: float = Field(128.0, gt=0, le=2000, description="shoulder to elbow, along the arm at zero")
    upper_arm_offset_mm: float = Field(24.0, ge=0, le=2000, description="shoulder to elbow, sideways (forward) at zero")
    forearm_mm: float = Field(124.0, gt=0, le=2000, description="elbow to wrist")
    tool_mm: float = Field(126.0, gt=0, le=2000, description="wrist axis to the gripper's tool point")
    min_radius_mm: float = Field(60.0, ge=0, le=2000, description="closest the tool may come to the yaw axis")


class DynamixelArmConfig(Strict):
    """Dynamixel Protocol 2.0 servos on one bus; defaults as on an OpenManipulator-X."""

    baud: int = Field(
        1_000_000,
        ge=9600,
        le=4_500_000,
        description="bus speed in bit/s, as set in every servo and the adapter supports",
    )
    joint_ids: tuple[int, int, int, int] = Field((11, 12, 13, 14), description="base yaw to wrist pitch")
    gripper_id: int = Field(15, ge=0, le=252, description="servo id of the gripper (distinct from joint_ids)")
    geometry: Geometry = Geometry()
    joint_min_deg: tuple[float, float, float, float] = Field(
        (-162.0, -102.6, -54.0, -102.6),
        description="lowest angle per joint (base yaw to wrist pitch) from zero_ticks; a move needing less is refused",
    )
    joint_max_deg: tuple[float, float, float, float] = Field(
        (162.0, 90.0, 79.2, 117.0),
        description="highest angle per joint (base yaw to wrist pitch) from zero_ticks; a move needing more is refused",
    )
    joint_directions: tuple[int, int, int, int] = Field((1, 1, 1, 1), description="+1 or -1 per joint")
    zero_ticks: int = Field(2048, ge=0, le=4095, description="servo position of joint angle 0 rad")
    home_joints_deg: tuple[float, float, float, float] = Field(
        (0.0, -60.0, 20.0, 40.0),
        description="joint angles (base yaw to wrist pitch) `home` moves to; within the limits",
    )
    gripper_open_ticks: int = Field(
        1800, ge=0, le=4095, description="gripper servo's goal position to open (4096 ticks/rev)"
    )
    gripper_closed_ticks: int = Field(
        2400,
        ge=0,
        le=4095,
        description="gripper servo's goal position to close (4096 ticks/rev); a part held stops it short",
    )
    profile_velocity: int = Field(100, ge=0, le=32767, description="servo units of 0.229 rev/min; 0 = top speed")
    profile_acceleration: int = Field(20, ge=0, le=32767, description="servo units of 214.577 rev/min^2")
    tolerance_ticks: int = Field(10, ge=1, le=400, description="arrival tolerance per servo (4096 ticks/rev)")
    angle_tolerance_deg: float = Field(
        1.0, gt=0, le=90, description="a 4-axis arm turns its gripper with the base: a requested angle must match"
    )
    move_timeout_s: float = Field(10.0, gt=0, le=600, description="longest wait for the servos to arrive")
    poll_interval_s: float = Field(
        0.02, gt=0, le=5, description="period of the servos' state reads while waiting for a move or the gripper"
    )
    reconnect_timeout_s: float = Field(10.0, ge=0, le=600, description="how long to wait for a re-plugged adapter")
    comm_retries: int = Field(2, ge=0, le=10, description="retries of a failed bus transfer before giving up")
    latency_timer_ms: float = Field(
        16.0, ge=1, le=255, description="the USB adapter's latency timer; a status packet is awaited twice this + 2 ms"
    )
    workspace: Workspace = Workspace(
        x_min_mm=-400, x_max_mm=400, y_min_mm=-400, y_max_mm=400, z_min_mm=-100, z_max_mm=400
    )

    @model_validator(mode="after")
    def _consistent(self) -> DynamixelArmConfig:
        ids = [*self.joint_ids, self.gripper_id]
        if len(set(ids)) != len(ids):
            raise ValueError(f"joint_ids {list(self.joint_ids)} and gripper_id {self.gripper_id} must be distinct")
        for i in self.joint_ids:
            if not 0 <= i <= 252:
                raise ValueError(f"joint_ids: {i} is not a servo id (0-252)")
        for j, (lo, hi) in enumerate(zip(self.joint_min_deg, self.joint_max_deg, strict=True), start=1):
            if lo >= hi:
                raise ValueError(f"joint {j}: joint_min_deg ({lo:g} deg) must be below joint_max_deg ({hi:g} deg)")
            if lo < -180 or hi > 180:
                raise ValueError(
                    f"joint {j}: joint_min_deg/joint_max_deg must lie within -180..180 deg (one servo turn)"
                )
        for j, (d, h) in enumerate(zip(self.joint_directions, self.home_joints_deg, strict=True), start=1):
            if d not in (1, -1):
                raise ValueError(f"joint_directions: joint {j} is {d}, must be 1 or -1")
            if not self.joint_min_deg[j - 1] <= h <= self.joint_max_deg[j - 1]:
                raise ValueError(f"home_joints_deg: joint {j} at {h:g} deg is outside its limits")
        if self.gripper_open_ticks == self.gripper_closed_ticks:
            raise ValueError("gripper_open_ticks and gripper_closed_ticks must differ")
        return self


DeviceKind = Literal["serial", "dynamixel"]  # the arms with a driver
# mock: records and checks every command, moves nothing; sim: the simulated cell's arm (cell.sim);
# robot-server: an industrial robot runs its own program and asks the cell for each pick (docs/robots.md).
ArmKind = Literal["serial", "dynamixel", "mock", "sim", "robot-server"]


class RobotServerConfig(Strict):
    """arm.kind 'robot-server': the cell as the vision server a robot's program asks over TCP
    (and Modbus TCP); the robot does the motion. Protocol and register map: docs/robots.md."""

    host: str = Field("127.0.0.1", description="address to listen on (loopback unless the robot is elsewhere)")
    port: int = Field(
        50002, ge=0, le=65535, description="TCP port of the text protocol; 0: a free port the system picks (tests)"
    )
    allow: list[str] = Field(
        ["127.0.0.1", "::1"],
        description="robot addresses (an address or a network such as '192.168.0.0/24') allowed to connect; "
        "any other is refused, counted and alarmed (a robot program cannot log in)",
    )
    pick_timeout_s: float = Field(
        60.0,
        gt=0,
        le=3600,
        description="a robot that took a pick and reports nothing (PICKED, MISSED, PLACED) within this: "
        "the pick is recorded as unknown and the cell faults safely",
    )
    next_wait_s: float = Field(
        1.0,
        ge=0,
        le=60,
        description="how long a NEXT waits for the cell's next pick before it is answered (0) (nothing to pick now)",
    )
    modbus_port: int = Field(0, ge=0, le=65535, description="Modbus TCP server port for a PLC; 0 = off")
    simulated_robot: bool = Field(
        True,
        description="with the simulated camera: a simulated robot asks over the real socket and moves the "
        "simulated arm; false: an outside client plays the robot and the simulated world takes its reports",
    )
    max_line_bytes: int = Field(
        256, ge=32, le=65536, description="a request line longer than this closes the connection"
    )
    class_numbers: dict[str, int] = Field(
        {"bolt": 1, "nut": 2},
        description="the class_no the robot is told for each part class, over the recipe's: a class not listed gets "
        "its recipe's number (bolt 1, nut 2, a taught type its types.NAME.class_no), else 0",
    )

    @field_validator("allow")
    @classmethod
    def _addresses(cls, v: list[str]) -> list[str]:
        for a in v:
            try:
                ipaddress.ip_network(a, strict=False)
            except ValueError:
                raise ValueError(
                    f"{a!r} is not an IP address or network (e.g. 192.168.0.10 or 192.168.0.0/24)"
                ) from None
        return v


class ArmConfig(Strict):
    """Which arm the cell drives and where it is plugged in."""

    kind: ArmKind = Field(
        "mock",
        description="'mock' records and validates commands and moves nothing; 'sim': the simulated cell's arm; "
        "'robot-server': a robot's own program asks the cell for each pick ([robot_server], docs/robots.md)",
    )
    mock_of: DeviceKind = Field("serial", description="whose limits the mock arm checks")
    port: str = Field("", description="device path or pyserial URL (socket://, spy://); see `run-cell ports`")
    serial: SerialArmConfig = SerialArmConfig()
    dynamixel: DynamixelArmConfig = DynamixelArmConfig()
