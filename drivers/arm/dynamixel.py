"""A 4-axis arm of Dynamixel Protocol 2.0 servos (XM430 control table) through the ROBOTIS SDK.

The only module that knows the servos' control table. Goals go out in one GroupSyncWrite
(all joints start together), positions come back through GroupSyncRead. On any fault the
torque is released, as the brief for this cell requires, and the error names the servo.
"""

from __future__ import annotations

import logging
import math
import termios
import time

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
ADDR_MOVING = 122  # read 122..135: Moving, Moving Status, PWM, Current, Velocity, Position
ADDR_PRESENT_POSITION = 132
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
        self._read = GroupSyncRead(self.ph, self.packet, ADDR_MOVING, ADDR_PRESENT_POSITION + 4 - ADDR_MOVING)
        self._read_errors = GroupSyncRead(self.ph, self.packet, ADDR_HARDWARE_ERROR, 1)
        for i in self.all_ids:
            self._read.addParam(i)
            self._read_errors.addParam(i)

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
        self._torque_off = True
        try:
            with self._guard("connect"):
                self._check_servos()
                self._sync_write(
                    ADDR_PROFILE_ACCELERATION,
                    8,
                    {i: [*_le(self.cfg.profile_acceleration), *_le(self.cfg.profile_velocity)] for i in self.all_ids},
                    "profile acceleration and velocity",
                )
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
        goals = self.kin.to_ticks([math.radians(v) for v in self.cfg.home_joints_deg])
        self._move_joints(goals, wait=True, what="home")

    def move_to(self, x_mm, y_mm, z_mm, angle_deg=None, *, wait=True) -> None:
        goals = plan_move(self.kin, self.cfg, x_mm, y_mm, z_mm, angle_deg)
        self._move_joints(goals, wait, f"move to ({x_mm}, {y_mm}, {z_mm}) mm")

    def open_gripper(self) -> None:
        self._gripper(self.cfg.gripper_open_ticks, closed=False)

    def close_gripper(self) -> None:
        self._gripper(self.cfg.gripper_closed_ticks, closed=True)

    def wait_until_idle(self, timeout_s: float | None = None) -> None:
        with self._guard("wait"):
            self._ready()
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
            errors = self._hardware_errors()
        pose = self.kin.forward(self.kin.from_ticks([present[i][1] for i in self.cfg.joint_ids]))
        moving = any(present[i][0] for i in self.all_ids)
        state = "fault" if errors else ("moving" if moving else self._state)
        detail = "; ".join(f"servo {i}: {decode_hardware_error(b)}" for i, b in errors.items())
        g = present[self.cfg.gripper_id][1]
        closed = abs(g - self.cfg.gripper_closed_ticks) < abs(g - self.cfg.gripper_open_ticks)
        return ArmStatus(state, Pose(pose.x_mm, pose.y_mm, pose.z_mm, pose.angle_deg), closed, detail)

    # ----- bus -----

    def _ready(self) -> None:
        if not self._connected:
            if not self._lost:
                raise NotConnected("the arm is not connected", port=self.port)
            log.warning("reconnecting to the servo bus on %s", self.port)
            wait_for_port(self.port, self.cfg.reconnect_timeout_s)
            self.connect()
        elif self._torque_off:
            self._torque_on()

    def _torque_on(self) -> None:
        """Torque on (each servo holds where it is), refused while a servo reports a hardware error."""
        if errors := self._hardware_errors():
            raise self._fault_error(errors, "torque on")
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

    def _move_joints(self, goals: list[int], wait: bool, what: str) -> None:
        with self._guard(what):
            self._ready()
            self._sync_write(
                ADDR_GOAL_POSITION, 4, {i: _le(t) for i, t in zip(self.cfg.joint_ids, goals, strict=True)}, what
            )
            self._state = "moving"
            if wait:
                self._wait_arrival(dict(zip(self.cfg.joint_ids, goals, strict=True)), what)

    def _gripper(self, ticks: int, closed: bool) -> None:
        what = "close gripper" if closed else "open gripper"
        with self._guard(what):
            self._ready()
            gid = self.cfg.gripper_id
            self._call(lambda: self.packet.write4ByteTxRx(self.ph, gid, ADDR_GOAL_POSITION, ticks), what, gid)
            # A gripper closing on a part stops short of its goal: wait for it to stop, not arrive.
            self._wait_stopped([gid], self.cfg.move_timeout_s)
            self._gripper_closed = closed

    def _wait_arrival(self, goals: dict[int, int], what: str) -> None:
        deadline = time.monotonic() + self.cfg.move_timeout_s
        while True:
            present = self._present()
            if errors := self._hardware_errors():
                raise self._fault_error(errors, what)
            off = {i: present[i][1] - g for i, g in goals.items()}
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
            if errors := self._hardware_errors():
                raise self._fault_error(errors, "wait")
            if not any(present[i][0] for i in ids):
                self._state = "idle"
                return
            if time.monotonic() >= deadline:
                raise NoResponse(f"servos {ids} still moving after {timeout_s} s", port=self.port, command="wait")
            time.sleep(self.cfg.poll_interval_s)

    def _present(self) -> dict[int, tuple[int, int]]:
        """(moving flag, present position ticks) per servo, in one sync read."""
        self._call(self._read.txRxPacket, "sync read present position")
        out = {}
        for i in self.all_ids:
            if not self._read.isAvailable(i, ADDR_PRESENT_POSITION, 4):
                raise NoResponse(
                    f"servo {i} missing from the sync read",
                    port=self.port,
                    command="sync read present position",
                    hint=BUS_HINT,
                )
            pos = self._read.getData(i, ADDR_PRESENT_POSITION, 4)
            out[i] = (self._read.getData(i, ADDR_MOVING, 1), pos - (1 << 32) if pos & 0x80000000 else pos)
        return out

    def _hardware_errors(self) -> dict[int, int]:
        self._call(self._read_errors.txRxPacket, "sync read hardware error status")
        errors = {i: self._read_errors.getData(i, ADDR_HARDWARE_ERROR, 1) for i in self.all_ids}
        return {i: b for i, b in errors.items() if b}

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
