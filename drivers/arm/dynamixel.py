"""A 4-axis arm of Dynamixel Protocol 2.0 servos (XM430 control table) through the ROBOTIS SDK.

The only module that knows the servos' control table. Goals go out in one GroupSyncWrite
(all joints start together), positions come back through GroupSyncRead. On any fault the
torque is released, as the brief for this cell requires, and the error names the servo.

Servo restarts. An XM430 restarts when its 12 V supply dips (a loose power cable, a
brown-out under load, the supply switched off and on) or on a Reboot instruction, while the
U2D2 on USB may stay up. It comes back with its RAM at the defaults: Torque Enable 0,
Hardware Error Status 0, Profile Velocity and Acceleration 0 (no limit: the next move would
run at full speed). The driver reads Torque Enable (64) to Hardware Error Status (70) with
the moving flag and present position, in the one sync read it polls motion with and makes
before every command: a servo whose torque is off while the driver has it on, with no
hardware error, has restarted (a hardware-error shutdown also turns torque off, but sets an
error bit: that is a HardwareFault). A real OpenManipulator-X shows exactly this after a
power dip of its servo supply; the driver is the only one on the bus (the port is
exclusive), so nothing else turns torque off. It then latches PositionLost: the joint
angles are still read right (absolute encoders, position mode), but the arm went limp and
sagged, may have dropped or crushed what it held, and lost its motion profiles. A pure link
loss (the U2D2 re-enumerating) leaves the servos powered with their torque on, so after the
reconnect they read torque on and motion resumes; torque off there, where the driver had
left it on, is a restart during the loss. Homing (the home joint angles, profiles written
first) or unlock() ends the latch.
"""

from __future__ import annotations

import logging
import math
import termios
import time
from typing import NamedTuple

import serial
from dynamixel_sdk import (
    COMM_RX_CORRUPT,
    COMM_RX_TIMEOUT,
    COMM_SUCCESS,
    GroupSyncRead,
    GroupSyncWrite,
    PacketHandler,
    PortHandler,
)

from drivers.arm.base import Arm, ArmStatus
from drivers.arm.config import DynamixelArmConfig
from drivers.arm.errors import (
    ArmError,
    ConnectionLost,
    ErrorResponse,
    HardwareFault,
    NoResponse,
    NotConnected,
    OutOfReach,
    PositionLost,
)
from drivers.arm.kinematics import FourAxisKinematics, Pose
from drivers.arm.serial_line import wait_for_port

log = logging.getLogger(__name__)

# XM430-W350 control table (Protocol 2.0).
ADDR_OPERATING_MODE = 11
ADDR_TORQUE_ENABLE = 64
ADDR_HARDWARE_ERROR = 70
ADDR_PROFILE_ACCELERATION = 108  # followed by Profile Velocity at 112
ADDR_GOAL_POSITION = 116
ADDR_MOVING = 122
ADDR_PRESENT_POSITION = 132
# One sync read covers Torque Enable .. Present Position: torque, hardware error, moving, position.
READ_START, READ_LENGTH = ADDR_TORQUE_ENABLE, ADDR_PRESENT_POSITION + 4 - ADDR_TORQUE_ENABLE
POSITION_MODES = {3: "position", 4: "extended position", 5: "current-based position"}
HARDWARE_ERRORS = {
    0x01: "input voltage error",
    0x04: "overheating error",
    0x08: "motor encoder error",
    0x10: "electrical shock error",
    0x20: "overload error",
}
STATUS_ERRORS = {
    1: "result fail",
    2: "instruction error",
    3: "CRC error",
    4: "data range error",
    5: "data length error",
    6: "data limit error",
    7: "access error",
}
BUS_HINT = "check the servos' power, and arm.port / arm.dynamixel.baud / ids (`run-cell ports`)"


class ExclusivePortHandler(PortHandler):
    """The SDK's PortHandler opening its port for this process alone (the SDK itself does not),
    and waiting for a status packet as long as the adapter's latency timer says (the SDK fixes 16 ms)."""

    def __init__(self, port_name: str, latency_timer_ms: float = 16.0):
        super().__init__(port_name)
        self.latency_timer_ms = latency_timer_ms

    def setPacketTimeout(self, packet_length):
        """The SDK's own formula (wire time + twice the latency timer + 2 ms) with the configured timer."""
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = self.tx_time_per_byte * packet_length + 2.0 * self.latency_timer_ms + 2.0

    def setupPort(self, cflag_baud):
        if self.is_open:
            self.closePort()
        self.ser = serial.Serial(
            port=self.port_name, baudrate=self.baudrate, bytesize=serial.EIGHTBITS, timeout=0, exclusive=True
        )
        self.is_open = True
        self.ser.reset_input_buffer()
        self.tx_time_per_byte = (1000.0 / self.baudrate) * 10.0
        return True


def plan_move(kin: FourAxisKinematics, cfg: DynamixelArmConfig, x_mm, y_mm, z_mm, angle_deg=None) -> list[int]:
    """Goal ticks for the joints (base to wrist), after the workspace and joint-limit checks."""
    if why := cfg.workspace.violation(x_mm, y_mm, z_mm):
        raise OutOfReach(f"target ({x_mm}, {y_mm}, {z_mm}) mm: {why} (arm.dynamixel.workspace)")
    return kin.to_ticks(kin.inverse(x_mm, y_mm, z_mm, angle_deg))


class ServoReading(NamedTuple):
    """What one sync read tells of one servo."""

    torque: bool
    hardware_error: int
    moving: bool
    ticks: int


def decode_hardware_error(bits: int) -> str:
    return ", ".join(name for bit, name in HARDWARE_ERRORS.items() if bits & bit) or f"0x{bits:02x}"


class DynamixelArm(Arm):
    """Joint servos and a gripper servo on one bus, driven through an SDK PortHandler."""

    def __init__(self, port_handler: PortHandler, cfg: DynamixelArmConfig):
        self.ph = port_handler
        self.port = port_handler.getPortName()
        self.cfg = cfg
        self.kin = FourAxisKinematics(cfg)
        self.packet = PacketHandler(2.0)
        self.all_ids = [*cfg.joint_ids, cfg.gripper_id]
        self._connected = False
        self._lost = False
        self._torque_off = True
        self._state = "disconnected"
        self._gripper_closed: bool | None = None
        self._read = GroupSyncRead(self.ph, self.packet, READ_START, READ_LENGTH)
        for i in self.all_ids:
            self._read.addParam(i)

    # ----- Arm interface -----

    @property
    def is_connected(self) -> bool:
        return self._connected

    def connect(self) -> None:
        try:
            opened = self.ph.openPort()
        except (serial.SerialException, OSError, ValueError) as e:
            raise ConnectionLost(
                f"cannot open the servo bus: {e}",
                port=self.port,
                hint="check the port path (`run-cell ports`) and that no other program holds it",
            ) from None
        if not opened or not self.ph.setBaudRate(self.cfg.baud):
            self._close()
            raise ConnectionLost(
                f"cannot set {self.cfg.baud} baud on the servo bus",
                port=self.port,
                hint="arm.dynamixel.baud must be a rate the adapter supports (e.g. 57600, 1000000)",
            )
        self._connected = True
        self._lost = False
        # Torque on when the driver last let go of the bus: the servos must still have it.
        torque_was_on, self._torque_off = not self._torque_off, True
        try:
            with self._guard("connect"):
                self._check_servos()
                self._write_profiles()
                try:
                    self._check(self._present(), "connect", torque_expected=torque_was_on)
                except PositionLost:
                    self.stop()  # latched: servos that kept their torque let go too
                    return
                self._torque_on()
        except ArmError:
            self._close()
            raise

    def disconnect(self) -> None:
        self._close()
        self._lost = False

    def check_target(self, x_mm, y_mm, z_mm, angle_deg=None) -> None:
        plan_move(self.kin, self.cfg, x_mm, y_mm, z_mm, angle_deg)

    def home(self) -> None:
        """Move to the home joint angles; also ends a PositionLost latch, after writing the
        profiles the restart reset: in position mode each joint angle comes from an absolute
        encoder, so a restart loses no angle (extended position mode's turn count excepted)."""
        goals = self.kin.to_ticks([math.radians(v) for v in self.cfg.home_joints_deg])
        self._move_joints(goals, wait=True, what="home", recover=True)
        self._position_regained("homed")

    def move_to(self, x_mm, y_mm, z_mm, angle_deg=None, *, wait=True) -> None:
        goals = plan_move(self.kin, self.cfg, x_mm, y_mm, z_mm, angle_deg)
        what = f"move to ({x_mm}, {y_mm}, {z_mm}) mm"
        self._refuse_while_position_lost(what)
        self._move_joints(goals, wait, what)

    def open_gripper(self) -> None:
        self._gripper(self.cfg.gripper_open_ticks, closed=False)

    def close_gripper(self) -> None:
        self._gripper(self.cfg.gripper_closed_ticks, closed=True)

    def wait_until_idle(self, timeout_s: float | None = None) -> None:
        self._refuse_while_position_lost("wait")
        with self._guard("wait"):
            self._ready("wait")
            self._wait_stopped(self.all_ids, timeout_s or self.cfg.move_timeout_s)

    def stop(self) -> None:
        """Release the torque of every servo: the arm goes limp rather than keep driving."""
        if not self._connected:
            return
        try:
            self._sync_write(ADDR_TORQUE_ENABLE, 1, {i: [0] for i in self.all_ids}, "torque off")
            self._torque_off = True
            if self._state != "fault":
                self._state = "hold"
            log.info("arm on %s: torque released", self.port)
        except ArmError as e:
            log.error("arm on %s: could not release the torque: %s", self.port, e)

    def status(self) -> ArmStatus:
        if not self._connected:
            return ArmStatus("disconnected", None, self._gripper_closed)
        with self._guard("status"):
            present = self._present()
            errors = {i: r.hardware_error for i, r in present.items() if r.hardware_error}
            if not errors:
                self._check(present, "status")  # a restart found here latches as anywhere
        pose = self.kin.forward(self.kin.from_ticks([present[i].ticks for i in self.cfg.joint_ids]))
        moving = any(r.moving for r in present.values())
        state = "fault" if errors else ("alarm" if self.position_lost else ("moving" if moving else self._state))
        detail = "; ".join(f"servo {i}: {decode_hardware_error(b)}" for i, b in errors.items())
        if self.position_lost and not errors:
            detail = PositionLost.MESSAGE
        g = present[self.cfg.gripper_id].ticks
        closed = abs(g - self.cfg.gripper_closed_ticks) < abs(g - self.cfg.gripper_open_ticks)
        return ArmStatus(state, Pose(pose.x_mm, pose.y_mm, pose.z_mm, pose.angle_deg), closed, detail)

    def unlock(self) -> None:
        """For an operator who has checked the arm's pose (nothing caught or crushed, the path
        clear): the joint angles are the encoders', so the pose is known again once the servos
        are powered. Writes the profiles a restart reset, then torque on: every servo holds
        where it is; no goal is sent. A servo with a hardware error still refuses (HardwareFault)."""
        with self._guard("unlock"):
            self._ready("unlock", recover=True)
            self._position_regained("unlocked by the operator")

    # ----- bus -----

    def _ready(self, what: str, recover: bool = False) -> None:
        """Connected (reconnecting after a lost link), torque on, no servo restarted. recover
        (home, unlock): go on while the position is lost, profiles written and torque on."""
        if not self._connected:
            if not self._lost:
                raise NotConnected("the arm is not connected", port=self.port)
            log.warning("reconnecting to the servo bus on %s", self.port)
            wait_for_port(self.port, self.cfg.reconnect_timeout_s)
            self.connect()
        if self.position_lost:
            if not recover:
                self._refuse_while_position_lost(what)  # found by the reconnect
            self._write_profiles()  # the restart reset them to 0: no limit
            self._torque_on()
        elif self._torque_off:
            self._torque_on()
        else:
            self._check(self._present(), what)  # a servo that restarted since the last command

    def _write_profiles(self) -> None:
        self._sync_write(
            ADDR_PROFILE_ACCELERATION,
            8,
            {i: [*_le(self.cfg.profile_acceleration), *_le(self.cfg.profile_velocity)] for i in self.all_ids},
            "profile acceleration and velocity",
        )

    def _torque_on(self) -> None:
        """Torque on (each servo holds where it is), refused while a servo reports a hardware error."""
        self._check(self._present(), "torque on", torque_expected=False)
        self._sync_write(ADDR_TORQUE_ENABLE, 1, {i: [1] for i in self.all_ids}, "torque on")
        self._torque_off = False
        self._state = "idle"

    def _close(self) -> None:
        if self.ph.is_open:
            try:
                self.ph.closePort()
            except (serial.SerialException, OSError):
                self.ph.is_open = False
        self._connected = False
        self._state = "disconnected"

    def _check_servos(self) -> None:
        for i in self.all_ids:
            model = self._call(lambda: self.packet.ping(self.ph, i), f"ping servo {i}", i)
            mode = self._call(
                lambda: self.packet.read1ByteTxRx(self.ph, i, ADDR_OPERATING_MODE),
                f"read operating mode of servo {i}",
                i,
            )
            log.debug("servo %d: model %d, operating mode %d", i, model, mode)
            if mode not in POSITION_MODES:
                raise ErrorResponse(
                    f"servo {i} is in operating mode {mode}, not a position mode",
                    port=self.port,
                    hint="set Operating Mode (address 11) to 3 (position) with the Dynamixel Wizard",
                )

    def _move_joints(self, goals: list[int], wait: bool, what: str, recover: bool = False) -> None:
        with self._guard(what):
            self._ready(what, recover)
            self._sync_write(
                ADDR_GOAL_POSITION, 4, {i: _le(t) for i, t in zip(self.cfg.joint_ids, goals, strict=True)}, what
            )
            self._state = "moving"
            if wait:
                self._wait_arrival(dict(zip(self.cfg.joint_ids, goals, strict=True)), what)

    def _gripper(self, ticks: int, closed: bool) -> None:
        what = "close gripper" if closed else "open gripper"
        self._refuse_while_position_lost(what)
        with self._guard(what):
            self._ready(what)
            gid = self.cfg.gripper_id
            self._call(lambda: self.packet.write4ByteTxRx(self.ph, gid, ADDR_GOAL_POSITION, ticks), what, gid)
            # A gripper closing on a part stops short of its goal: wait for it to stop, not arrive.
            self._wait_stopped([gid], self.cfg.move_timeout_s)
            self._gripper_closed = closed

    def _wait_arrival(self, goals: dict[int, int], what: str) -> None:
        deadline = time.monotonic() + self.cfg.move_timeout_s
        while True:
            present = self._present()
            self._check(present, what)
            off = {i: present[i].ticks - g for i, g in goals.items()}
            if all(abs(d) <= self.cfg.tolerance_ticks for d in off.values()):
                self._state = "idle"
                return
            if time.monotonic() >= deadline:
                worst = max(off, key=lambda i: abs(off[i]))
                raise NoResponse(
                    f"servos did not arrive within {self.cfg.move_timeout_s} s "
                    f"(servo {worst} is {off[worst]} ticks from its goal)",
                    port=self.port,
                    command=what,
                    hint="check for an obstruction; raise arm.dynamixel.move_timeout_s for slow profiles",
                )
            time.sleep(self.cfg.poll_interval_s)

    def _wait_stopped(self, ids: list[int], timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        time.sleep(self.cfg.poll_interval_s)  # let the servo start before asking if it is moving
        while True:
            present = self._present()
            self._check(present, "wait")
            if not any(present[i].moving for i in ids):
                self._state = "idle"
                return
            if time.monotonic() >= deadline:
                raise NoResponse(f"servos {ids} still moving after {timeout_s} s", port=self.port, command="wait")
            time.sleep(self.cfg.poll_interval_s)

    def _present(self) -> dict[int, ServoReading]:
        """Torque, hardware error, moving flag and present position of every servo, in one sync read."""
        self._call(self._read.txRxPacket, "sync read servo state")
        out = {}
        for i in self.all_ids:
            if not self._read.isAvailable(i, ADDR_PRESENT_POSITION, 4):
                raise NoResponse(
                    f"servo {i} missing from the sync read",
                    port=self.port,
                    command="sync read servo state",
                    hint=BUS_HINT,
                )
            pos = self._read.getData(i, ADDR_PRESENT_POSITION, 4)
            out[i] = ServoReading(
                torque=bool(self._read.getData(i, ADDR_TORQUE_ENABLE, 1)),
                hardware_error=self._read.getData(i, ADDR_HARDWARE_ERROR, 1),
                moving=bool(self._read.getData(i, ADDR_MOVING, 1)),
                ticks=pos - (1 << 32) if pos & 0x80000000 else pos,
            )
        return out

    def _check(self, present: dict[int, ServoReading], what: str, torque_expected: bool | None = None) -> None:
        """A hardware error is a HardwareFault; a servo found with its torque off while the driver
        had it on (torque_expected, default: whether the driver has it on), without one, has
        restarted: PositionLost, latched."""
        if errors := {i: r.hardware_error for i, r in present.items() if r.hardware_error}:
            raise self._fault_error(errors, what)
        expected = not self._torque_off if torque_expected is None else torque_expected
        if expected and (off := [i for i, r in present.items() if not r.torque]):
            servos = ", ".join(str(i) for i in off)
            raise self._restarted(f"torque off on servo {servos}, no hardware error: the driver had it on", what)

    def _fault_error(self, errors: dict[int, int], what: str) -> HardwareFault:
        text = "; ".join(f"servo {i}: {decode_hardware_error(b)}" for i, b in errors.items())
        return HardwareFault(
            f"servo hardware error ({text})",
            port=self.port,
            command=what,
            reply=", ".join(f"{i}: 0x{b:02x}" for i, b in errors.items()),
        )

    def _sync_write(self, addr: int, size: int, data: dict[int, list[int]], what: str) -> None:
        group = GroupSyncWrite(self.ph, self.packet, addr, size)
        for i, d in data.items():
            group.addParam(i, d)
        self._call(group.txPacket, what)

    def _call(self, fn, what: str, dxl_id: int | None = None):
        """Run one SDK transfer with retries; map its result codes and exceptions to ArmErrors."""
        for attempt in range(self.cfg.comm_retries + 1):
            try:
                out = fn()
            except (serial.SerialException, OSError, termios.error) as e:
                self.ph.is_using = False
                raise ConnectionLost(f"servo bus connection lost: {e}", port=self.port, command=what) from None
            except BaseException:
                # Ctrl-C mid-transfer: the SDK would keep the port marked in use and the late
                # reply would land in the next read, so the safe stop could not talk to the bus.
                self.ph.is_using = False
                self.ph.clearPort()
                raise
            result, error, value = _unpack(out)
            if result == COMM_SUCCESS:
                if error & 0x80 and dxl_id is not None:
                    raise HardwareFault(
                        f"servo {dxl_id} reports a hardware error",
                        port=self.port,
                        command=what,
                        reply=f"error byte 0x{error:02x}",
                    )
                if error & 0x7F:
                    code = error & 0x7F
                    raise ErrorResponse(
                        f"servo {dxl_id} refused: {STATUS_ERRORS.get(code, 'unknown error')}",
                        code=code,
                        port=self.port,
                        command=what,
                        reply=f"error byte 0x{error:02x}",
                    )
                return value
            if result not in (COMM_RX_TIMEOUT, COMM_RX_CORRUPT) or attempt == self.cfg.comm_retries:
                break
            log.debug("%s: %s, retrying", what, self.packet.getTxRxResult(result))
        who = f"servo {dxl_id}" if dxl_id is not None else "the servos"
        reason = "no status packet" if result == COMM_RX_TIMEOUT else self.packet.getTxRxResult(result)
        raise NoResponse(
            f"{who}: {reason}", port=self.port, command=what, reply=self.packet.getTxRxResult(result), hint=BUS_HINT
        )

    def _link_lost(self) -> None:
        self._close()
        self._lost = True

    def _leave_safe(self, error: ArmError) -> None:
        """Torque off on every servo (the arm sags, but nothing drives on)."""
        self._state = "fault"
        self.stop()


def _unpack(out) -> tuple[int, int, object]:
    """SDK calls return a result code, (result, error), or (value, result, error)."""
    if isinstance(out, int):
        return out, 0, None
    if len(out) == 2:
        return out[0], out[1], None
    return out[1], out[2], out[0]


def _le(value: int) -> list[int]:
    return list(int(value).to_bytes(4, "little", signed=value < 0))
