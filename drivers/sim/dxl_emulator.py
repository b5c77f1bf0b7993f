"""A bus of Dynamixel Protocol 2.0 servos (XM430-W350 control table) for tests and the sim.

Answers ping, read, write, sync read, sync write and reboot with status packets (CRC-16,
byte stuffing, error byte with the alert bit); servos move toward their goal at their
profile velocity (speed_scale > 1 runs faster). When given the arm config it also knows
which servos are joints and gripper, so it can tell a simulated world the tool pose and
call listeners on gripper open/close. Faults can be injected.
"""

from __future__ import annotations

import math

from drivers.arm.config import DynamixelArmConfig
from drivers.arm.kinematics import FourAxisKinematics
from drivers.sim.emulated_device import EmulatedDevice

HEADER = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE
STATUS = 0x55
PING, READ, WRITE, REBOOT, SYNC_READ, SYNC_WRITE = 0x01, 0x02, 0x03, 0x08, 0x82, 0x83
# Status packet error numbers (bit 7 is the hardware alert).
ERR_INSTRUCTION, ERR_CRC, ERR_DATA_RANGE, ERR_DATA_LENGTH, ERR_DATA_LIMIT, ERR_ACCESS = 2, 3, 4, 5, 6, 7
ALERT = 0x80

# XM430-W350 control table: address -> (size in bytes, default).
XM430_MODEL = 1020
TABLE = {
    0: (2, XM430_MODEL),
    6: (1, 52),
    7: (1, 1),
    8: (1, 1),
    9: (1, 250),
    10: (1, 0),
    11: (1, 3),
    12: (1, 255),
    13: (1, 2),
    20: (4, 0),
    24: (4, 10),
    31: (1, 80),
    32: (2, 160),
    34: (2, 95),
    36: (2, 885),
    38: (2, 1193),
    44: (4, 200),
    48: (4, 4095),
    52: (4, 0),
    63: (1, 52),
    64: (1, 0),
    65: (1, 0),
    68: (1, 2),
    69: (1, 0),
    70: (1, 0),
    76: (2, 1920),
    78: (2, 100),
    80: (2, 0),
    82: (2, 0),
    84: (2, 800),
    88: (2, 0),
    90: (2, 0),
    98: (1, 0),
    100: (2, 885),
    102: (2, 1193),
    104: (4, 0),
    108: (4, 0),
    112: (4, 0),
    116: (4, 2048),
    120: (2, 0),
    122: (1, 0),
    123: (1, 0),
    124: (2, 0),
    126: (2, 0),
    128: (4, 0),
    132: (4, 2048),
    136: (4, 0),
    140: (4, 0),
    144: (2, 120),
    146: (1, 35),
}
TABLE_SIZE = 147
TORQUE_ENABLE, HW_ERROR, GOAL_POSITION, MOVING, PRESENT_POSITION = 64, 70, 116, 122, 132
PROFILE_VELOCITY, VELOCITY_LIMIT, MAX_POSITION, MIN_POSITION = 112, 44, 48, 52
OVERLOAD = 0x20
RPM_PER_UNIT = 0.229


def crc16(data: bytes) -> int:
    """CRC-16 of Protocol 2.0 (polynomial 0x8005, no reflection, initial 0)."""
    crc = 0
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else crc << 1
            crc &= 0xFFFF
    return crc


def stuff(payload: bytes) -> bytes:
    """Insert 0xFD after every FF FF FD so a header never appears inside a packet."""
    out = bytearray()
    for b in payload:
        out.append(b)
        if out[-3:] == b"\xff\xff\xfd":
            out.append(0xFD)
    return bytes(out)


def unstuff(payload: bytes) -> bytes:
    out = bytearray()
    i = 0
    while i < len(payload):
        out.append(payload[i])
        if out[-3:] == b"\xff\xff\xfd" and i + 1 < len(payload) and payload[i + 1] == 0xFD:
            i += 1
        i += 1
    return bytes(out)


def packet(dxl_id: int, instruction: int, params: bytes = b"") -> bytes:
    """A complete Protocol 2.0 packet (instruction or status) with stuffing and CRC."""
    body = stuff(bytes([instruction]) + params)
    head = HEADER + bytes([dxl_id]) + (len(body) + 2).to_bytes(2, "little")
    frame = head + body
    return frame + crc16(frame).to_bytes(2, "little")


class Servo:
    """One XM430-W350: control table plus a position moving toward the goal at finite speed."""

    def __init__(self, dxl_id: int, position_ticks: int):
        self.table = bytearray(TABLE_SIZE)
        for addr, (size, value) in TABLE.items():
            self.set(addr, size, value)
        self.set(7, 1, dxl_id)
        self.position = float(position_ticks)
        self.set(PRESENT_POSITION, 4, position_ticks)
        self.set(GOAL_POSITION, 4, position_ticks)

    @property
    def id(self) -> int:
        return self.table[7]

    def get(self, addr: int, size: int) -> int:
        return int.from_bytes(self.table[addr : addr + size], "little", signed=size == 4)

    def set(self, addr: int, size: int, value: int) -> None:
        self.table[addr : addr + size] = int(value).to_bytes(size, "little", signed=size == 4 and value < 0)

    @property
    def torque(self) -> bool:
        return bool(self.table[TORQUE_ENABLE])

    def speed_ticks_s(self) -> float:
        units = self.get(PROFILE_VELOCITY, 4) or self.get(VELOCITY_LIMIT, 4)
        return units * RPM_PER_UNIT / 60.0 * 4096.0

    def advance(self, dt_s: float) -> float:
        """Move toward the goal for dt_s; returns the seconds of it spent moving."""
        goal = self.get(GOAL_POSITION, 4)
        moved_s = 0.0
        if self.torque and self.position != goal:
            speed = self.speed_ticks_s()
            step = speed * dt_s
            delta = goal - self.position
            if abs(delta) <= step:
                self.position, moved_s = float(goal), abs(delta) / speed
            else:
                self.position, moved_s = self.position + step * (1 if delta > 0 else -1), dt_s
        self.set(PRESENT_POSITION, 4, round(self.position))
        self.table[MOVING] = int(self.torque and round(self.position) != goal)
        return moved_s

    def restart(self) -> None:
        """Power-up (a supply dip, or the Reboot instruction): the RAM area back to its defaults
        (torque off, no hardware error, profiles 0), the EEPROM kept; goal = present position."""
        for addr, (size, value) in TABLE.items():
            if addr >= TORQUE_ENABLE:
                self.set(addr, size, value)
        self.set(PRESENT_POSITION, 4, round(self.position))
        self.set(GOAL_POSITION, 4, round(self.position))

    def fault(self, bits: int) -> None:
        """A hardware error: the servo releases its torque, as an XM430 does at shutdown."""
        self.table[HW_ERROR] |= bits
        self.table[TORQUE_ENABLE] = 0
        self.table[MOVING] = 0


class DxlBusEmulator(EmulatedDevice):
    """Servos sharing one Protocol 2.0 bus; serve it with drivers.sim.pty_port.serve_pty."""

    FAULTS = ("no_answer", "garbage", "bad_crc", "status_error", "overload", "unplug", "reboot")

    def __init__(
        self,
        arm: DynamixelArmConfig | None = None,
        *,
        ids: tuple[int, ...] | None = None,
        speed_scale: float = 1.0,
        start_joints_deg: tuple[float, float, float, float] | None = None,
    ):
        super().__init__()
        self.arm = arm or DynamixelArmConfig()
        self.kinematics = FourAxisKinematics(self.arm)
        self.speed_scale = speed_scale
        ids = ids or (*self.arm.joint_ids, self.arm.gripper_id)
        start = self.arm.home_joints_deg if start_joints_deg is None else start_joints_deg
        joint_ticks = dict(
            zip(self.arm.joint_ids, self.kinematics.to_ticks([math.radians(v) for v in start]), strict=True)
        )
        self.servos = {
            i: Servo(i, joint_ticks.get(i, self.arm.gripper_open_ticks if i == self.arm.gripper_id else 2048))
            for i in ids
        }
        self.packets_received: list[bytes] = []
        self.reboots: list[int] = []  # len(packets_received) at each restart of the servos' supply
        self._rx = bytearray()
        self._last_s: float | None = None
        self._gripper_closed = False
        self.motion_time_s = 0.0  # time some servo was moving, at the servos' own speed (not scaled)

    # ----- public API for tests and the simulated world -----

    def tool_pose(self) -> tuple[float, float, float, float]:
        """Tool point (x, y, z mm, robot base frame) and angle_deg, from the joints' present positions."""
        with self.lock:
            ticks = [self.servos[i].position for i in self.arm.joint_ids]
            p = self.kinematics.forward(self.kinematics.from_ticks(ticks))
            return p.x_mm, p.y_mm, p.z_mm, p.angle_deg

    @property
    def gripper_closed(self) -> bool:
        return self._gripper_closed

    def inject(self, fault: str, **params) -> None:
        """Arm a fault.

        no_answer (ids=None: all): those servos stop answering.
        garbage (count=1): the next status packets are replaced by noise.
        bad_crc (count=1): the next status packets carry a wrong CRC.
        status_error (error=N, count=1): the next status packets carry error number N.
        overload (id, after_s=0): that servo trips Overload Error (bit 5) T seconds into its next move.
        unplug (after_s=0): the cable is pulled T seconds into the next move; the servos run on.
        reboot (ids=None: all, after_s=None: at once): those servos' supply dips, T seconds into
            the next move or at once: they restart (RAM defaults: torque off, profiles 0), and a
            gripper servo among them lets go of what it held.
        """
        self._arm_fault(fault, {"count": 1, **params, "elapsed_s": 0.0})

    # ----- ByteDevice interface -----

    def power_on(self, now_s: float) -> bytes:
        # The USB adapter was plugged in; the servos kept their power and state unless
        # replug(power_cycled=True) says their supply went too.
        self._rx.clear()
        if self._take_restart_on_plug():
            self._reboot(None)
        return b""

    def receive(self, data: bytes, now_s: float) -> bytes:
        self.tick(now_s)
        self._rx += data
        out = bytearray()
        while True:
            start = self._rx.find(HEADER)
            if start < 0:
                del self._rx[: max(0, len(self._rx) - 3)]
                break
            del self._rx[:start]
            if len(self._rx) < 7:
                break
            total = 7 + int.from_bytes(self._rx[5:7], "little")
            if len(self._rx) < total:
                break
            frame = bytes(self._rx[:total])
            del self._rx[:total]
            self.packets_received.append(frame)
            out += self._handle(frame)
        return bytes(out)

    def tick(self, now_s: float) -> bytes:
        dt = 0.0 if self._last_s is None else max(0.0, now_s - self._last_s)
        self._last_s = now_s
        reboot = self._faults.get("reboot")
        if reboot is not None and reboot.get("after_s") is None:
            del self._faults["reboot"]
            self._reboot(reboot.get("ids"))
        moving_before = any(
            s.table[MOVING] or s.get(GOAL_POSITION, 4) != round(s.position) for s in self.servos.values() if s.torque
        )
        # Servos move together: the bus was moving for as long as its longest-moving servo.
        self.motion_time_s += max(s.advance(dt * self.speed_scale) for s in self.servos.values())
        if moving_before:
            self._motion_faults(dt)
        return b""

    # ----- internals -----

    def _motion_faults(self, dt: float) -> None:
        for name in ("overload", "unplug", "reboot"):
            params = self._faults.get(name)
            if params is None:
                continue
            params["elapsed_s"] += dt
            if params["elapsed_s"] < params.get("after_s", 0.0):
                continue
            del self._faults[name]
            if name == "overload":
                self.servos[params["id"]].fault(OVERLOAD)
            elif name == "reboot":
                self._reboot(params.get("ids"))
            else:
                self.unplug_requested = True

    def _reboot(self, ids: list[int] | None) -> None:
        self.reboots.append(len(self.packets_received))
        for i in self.servos if ids is None else ids:
            self.servos[i].restart()
        gripper_limp = ids is None or self.arm.gripper_id in ids
        if gripper_limp and self._gripper_closed and self.arm.gripper_id in self.servos:
            self._gripper_closed = False
            self._notify_tool(False, self.tool_pose())

    def _handle(self, frame: bytes) -> bytes:
        dxl_id = frame[4]
        if crc16(frame[:-2]) != int.from_bytes(frame[-2:], "little"):
            return self._status(dxl_id, ERR_CRC) if dxl_id in self.servos else b""
        body = unstuff(frame[7:-2])
        inst, params = body[0], body[1:]
        if inst == SYNC_WRITE:
            self._sync_write(params)
            return b""
        if inst == SYNC_READ:
            addr, size = int.from_bytes(params[0:2], "little"), int.from_bytes(params[2:4], "little")
            return b"".join(self._read(i, addr, size) for i in params[4:] if i in self.servos)
        if dxl_id == BROADCAST_ID and inst == PING:
            return b"".join(self._ping(i) for i in self.servos)
        if dxl_id not in self.servos:
            return b""
        if inst == PING:
            return self._ping(dxl_id)
        if inst == READ:
            addr, size = int.from_bytes(params[0:2], "little"), int.from_bytes(params[2:4], "little")
            return self._read(dxl_id, addr, size)
        if inst == WRITE:
            return self._status(dxl_id, self._write(dxl_id, int.from_bytes(params[0:2], "little"), params[2:]))
        if inst == REBOOT:
            reply = self._status(dxl_id, 0)
            self.servos[dxl_id].restart()
            return reply
        return self._status(dxl_id, ERR_INSTRUCTION)

    def _ping(self, dxl_id: int) -> bytes:
        s = self.servos[dxl_id]
        return self._status(dxl_id, 0, s.get(0, 2).to_bytes(2, "little") + bytes([s.table[6]]))

    def _read(self, dxl_id: int, addr: int, size: int) -> bytes:
        if addr + size > TABLE_SIZE or size == 0:
            return self._status(dxl_id, ERR_DATA_LENGTH)
        return self._status(dxl_id, 0, bytes(self.servos[dxl_id].table[addr : addr + size]))

    def _write(self, dxl_id: int, addr: int, data: bytes) -> int:
        """Apply a write; returns the status error number (0 if accepted)."""
        servo = self.servos[dxl_id]
        if addr + len(data) > TABLE_SIZE or not data:
            return ERR_DATA_LENGTH
        if addr < TORQUE_ENABLE and servo.torque:
            return ERR_ACCESS  # EEPROM area is locked while torque is on
        if addr <= GOAL_POSITION < addr + len(data):
            off = GOAL_POSITION - addr
            goal = int.from_bytes(data[off : off + 4], "little", signed=True)
            if not servo.get(MIN_POSITION, 4) <= goal <= servo.get(MAX_POSITION, 4):
                return ERR_DATA_LIMIT
        if addr <= TORQUE_ENABLE < addr + len(data) and data[TORQUE_ENABLE - addr] and servo.table[HW_ERROR]:
            return ERR_ACCESS  # torque cannot come back until a reboot clears the error
        was_torque = servo.torque
        servo.table[addr : addr + len(data)] = data
        if servo.torque and not was_torque:
            servo.set(GOAL_POSITION, 4, round(servo.position))  # torque on holds where it is
        if dxl_id == self.arm.gripper_id and addr <= GOAL_POSITION < addr + len(data) and servo.torque:
            self._gripper_goal(servo.get(GOAL_POSITION, 4))
        return 0

    def _sync_write(self, params: bytes) -> None:
        addr, size = int.from_bytes(params[0:2], "little"), int.from_bytes(params[2:4], "little")
        rest = params[4:]
        for k in range(0, len(rest) - size, size + 1):
            dxl_id = rest[k]
            if dxl_id in self.servos:
                self._write(dxl_id, addr, rest[k + 1 : k + 1 + size])

    def _gripper_goal(self, goal: int) -> None:
        closed = abs(goal - self.arm.gripper_closed_ticks) < abs(goal - self.arm.gripper_open_ticks)
        if closed == self._gripper_closed:
            return
        self._gripper_closed = closed
        self._notify_tool(closed, self.tool_pose())

    def _status(self, dxl_id: int, error: int, params: bytes = b"") -> bytes:
        no_answer = self._faults.get("no_answer")
        if no_answer is not None and (no_answer.get("ids") is None or dxl_id in no_answer["ids"]):
            return b""
        if self.servos[dxl_id].table[HW_ERROR]:
            error |= ALERT
        injected = self._take("status_error")
        if injected is not None:
            error = injected.get("error", ERR_DATA_RANGE)
        reply = packet(dxl_id, STATUS, bytes([error]) + params)
        if self._take("bad_crc") is not None:
            reply = reply[:-2] + bytes([reply[-2] ^ 0xFF, reply[-1]])
        if self._take("garbage") is not None:
            reply = b"\x13\x37" * (len(reply) // 2)
        return reply

    def _take(self, fault: str) -> dict | None:
        params = self._faults.get(fault)
        if params is None:
            return None
        params["count"] -= 1
        if params["count"] <= 0:
            del self._faults[fault]
        return params
