"""A GRBL 1.1-like controller for a Cartesian arm, for tests and the simulated cell.

Speaks GRBL's line protocol (`ok`, `error:N`, `ALARM:N`, banner, `[MSG:...]`) and its
real-time commands (`?` status, `!` feed hold, `~` resume, Ctrl-X soft reset). Motion runs
at finite speed against the clock; speed_scale > 1 runs it faster for tests. The spindle
drives the gripper (M3 S>0 closes, M5 opens), as on hobby arms with a servo gripper.
Faults can be injected to test the driver's error paths.

Machine position (MPos, what GRBL counts) and the tool's physical position differ after a
restart: the controller starts counting from start_mm wherever the tool stands, until a
homing cycle ($H) finds the physical zero again. A pulled cable leaves the controller
running its queue; only replug(power_cycled=True) or the restart fault restarts it.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any

from drivers.sim.emulated_device import EmulatedDevice

BANNER = b"\r\nGrbl 1.1h ['$' for help]\r\n"
UNLOCK_MSG = b"[MSG:'$H'|'$X' to unlock]\r\n"
RESET = 0x18

_WORD = re.compile(r"([A-Z])([-+]?(?:\d+\.?\d*|\.\d+))")

# GRBL's defaults for the settings the emulator uses.
DEFAULT_SETTINGS = {
    0: 10,
    1: 25,
    2: 0,
    3: 0,
    4: 0,
    5: 0,
    6: 0,
    10: 1,
    11: 0.010,
    12: 0.002,
    13: 0,
    20: 0,
    21: 0,
    22: 0,
    23: 0,
    24: 25.0,
    25: 500.0,
    26: 250,
    27: 1.0,
    30: 1000,
    31: 0,
    32: 0,
    100: 250.0,
    101: 250.0,
    102: 250.0,
    110: 500.0,
    111: 500.0,
    112: 500.0,
    120: 10.0,
    121: 10.0,
    122: 10.0,
    130: 200.0,
    131: 200.0,
    132: 200.0,
}


@dataclass
class _Segment:
    start: list[float]
    end: list[float]
    duration_s: float
    elapsed_s: float = 0.0

    def position(self) -> list[float]:
        f = 1.0 if self.duration_s <= 0 else min(1.0, self.elapsed_s / self.duration_s)
        return [a + (b - a) * f for a, b in zip(self.start, self.end, strict=True)]


class GrblEmulator(EmulatedDevice):
    """Emulated GRBL firmware; serve it with drivers.sim.pty_port.serve_pty."""

    FAULTS = ("no_answer", "garbage", "error", "alarm", "hold", "unplug", "restart")
    # Set by _power_up (every start-up), read by the pty server's calls before it in the source.
    _state: str
    _rx_line: bytearray

    def __init__(
        self,
        *,
        speed_scale: float = 1.0,
        homing_enabled: bool = False,
        rotary_axis: bool = False,
        start_mm: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ):
        super().__init__()
        self.speed_scale = speed_scale
        self.axes = "XYZA" if rotary_axis else "XYZ"
        self.settings = dict(DEFAULT_SETTINGS)
        self.settings[22] = int(homing_enabled)
        self._start_mm = start_mm
        self.lines_received: list[str] = []
        self.restarts: list[int] = []  # len(lines_received) at each restart after the first start-up
        self.motion_time_s = 0.0  # machine time spent moving, at the machine's own speed (not scaled)
        self._offset = [0.0, 0.0, 0.0, 0.0]  # physical tool position minus machine position
        self._running = False
        self._power_up(now_s=0.0)

    # ----- public API for tests and the simulated world -----

    def tool_pose(self) -> tuple[float, float, float, float]:
        """Where the tool physically is (x, y, z mm, robot base frame) and angle_deg."""
        with self.lock:
            p = self._physical()
            return p[0], p[1], p[2], p[3]

    def machine_position(self) -> tuple[float, float, float, float]:
        """What the controller counts (MPos): the tool pose until a restart, then offset from it."""
        with self.lock:
            p = self._position()
            return p[0], p[1], p[2], p[3]

    @property
    def gripper_closed(self) -> bool:
        return self._spindle_on

    @property
    def state(self) -> str:
        with self.lock:
            return self._state

    def inject(self, fault: str, **params: Any) -> None:
        """Arm a fault for what comes next.

        no_answer: stop answering anything (a hung controller).
        garbage: the next reply is replaced by noise bytes.
        error (code=N): the next G-code line is refused with error:N.
        alarm (code=N, after_s=T): ALARM:N during the next motion, T seconds into it.
        hold (after_s=T): the feed-hold input trips T seconds into the next motion: the machine
            stops (Hold:0) and stays stopped, answering as ever, until `~` or a reset.
        unplug (after_s=T): the cable is pulled T seconds into the next motion; the controller
            runs on (replug(power_cycled=True) restarts it as well).
        restart: the controller reboots at once (power dip): banner, MPos back to start_mm where
            the tool stands, spindle off (the gripper opens), in alarm if homing is enabled.
        """
        self._arm_fault(fault, params)

    # ----- ByteDevice interface (called by the pty server) -----

    def power_on(self, now_s: float) -> bytes:
        """Plugged in: the first start-up, or a restart after replug(power_cycled=True); after a
        plain replug only the link came back and the controller, still running, says nothing."""
        if self._running and not self._take_restart_on_plug():
            return b""
        return self._start_up(now_s)

    def receive(self, data: bytes, now_s: float) -> bytes:
        if "no_answer" in self._faults:
            return b""
        out = bytearray(self._advance(now_s))
        for byte in data:
            if byte == ord("?"):
                out += self._status_report()
            elif byte == ord("!"):
                if self._state in ("Run", "Jog", "Home"):
                    self._state = "Hold:0"
            elif byte == ord("~"):
                if self._state.startswith("Hold"):
                    self._state = "Run" if self._queue else "Idle"
            elif byte == RESET:
                out += self._soft_reset()
            elif byte in (ord("\n"), ord("\r")):
                if self._rx_line:
                    self._pending.append(self._rx_line.decode("ascii", "replace"))
                self._rx_line = bytearray()
            elif byte >= 0x80:
                continue  # other real-time commands (overrides, jog cancel): not emulated
            else:
                self._rx_line.append(byte)
        out += self._process_lines()
        return self._maybe_garble(bytes(out))

    def tick(self, now_s: float) -> bytes:
        if "no_answer" in self._faults:
            self._last_s = now_s
            return b""
        if self._faults.pop("restart", None) is not None:
            return self._start_up(now_s)
        out = self._advance(now_s)
        out += self._process_lines()
        return self._maybe_garble(out)

    # ----- internals -----

    def _start_up(self, now_s: float) -> bytes:
        restart, physical = self._running, self._physical()
        if restart:  # the tool stays where it is, the gripper lets go
            self.restarts.append(len(self.lines_received))
            self._set_spindle(False, 0.0)
        self._power_up(now_s)
        if restart:
            self._offset = [a - b for a, b in zip(physical, self._pos, strict=True)]
        self._running = True
        return self._banner()

    def _physical(self) -> list[float]:
        return [a + b for a, b in zip(self._position(), self._offset, strict=True)]

    def _power_up(self, now_s: float) -> None:
        self._pos = [*self._start_mm, 0.0][: len(self.axes)]
        self._pos += [0.0] * (4 - len(self._pos))
        self._queue: list[_Segment] = []
        self._pending: list[str] = []
        self._rx_line = bytearray()
        self._sync_waiting: str | None = None
        self._last_s = now_s
        self._absolute = True
        self._feed_mm_min = 0.0
        self._spindle_on = False
        self._spindle_speed = 0.0
        self._state = "Alarm" if self.settings[22] else "Idle"
        self._dwell_left_s = 0.0

    def _banner(self) -> bytes:
        return BANNER + (UNLOCK_MSG if self._state == "Alarm" else b"")

    def _soft_reset(self) -> bytes:
        out = b""
        if self._state in ("Run", "Home", "Jog") and self._queue:
            out += b"ALARM:3\r\n"
            self._state = "Alarm"
        self._pos = self._position()
        self._queue.clear()
        self._pending.clear()
        self._rx_line = bytearray()
        self._sync_waiting = None
        self._dwell_left_s = 0.0
        self._absolute = True
        self._feed_mm_min = 0.0
        self._set_spindle(False, 0.0)  # a reset stops the spindle: the gripper opens
        if self._state != "Alarm":
            self._state = "Idle"
        return out + self._banner()

    def _position(self) -> list[float]:
        return self._queue[0].position() if self._queue else list(self._pos)

    def _advance(self, now_s: float) -> bytes:
        """Run motion up to now; returns any push messages (alarms)."""
        dt = max(0.0, now_s - self._last_s) * self.speed_scale
        self._last_s = now_s
        if self._state.startswith("Hold") or self._state == "Alarm":
            return b""
        out = b""
        while self._queue and dt > 0:
            seg = self._queue[0]
            step = min(dt, seg.duration_s - seg.elapsed_s)
            seg.elapsed_s += step
            self.motion_time_s += step
            dt -= step
            params = self._faults.get("unplug")
            if params is not None and seg.elapsed_s >= params.get("after_s", 0.0) * self.speed_scale:
                del self._faults["unplug"]
                self.unplug_requested = True  # GRBL does not know: it runs on
            params = self._faults.get("hold")
            if params is not None and seg.elapsed_s >= params.get("after_s", 0.0) * self.speed_scale:
                del self._faults["hold"]
                self._state = "Hold:0"
                return out
            params = self._faults.get("alarm")
            if params is not None and seg.elapsed_s >= params.get("after_s", 0.0) * self.speed_scale:
                del self._faults["alarm"]
                self._pos = seg.position()
                self._queue.clear()
                self._state = "Alarm"
                self._pending.clear()
                self._sync_waiting = None
                return out + f"ALARM:{params.get('code', 1)}\r\n".encode() + b"[MSG:Reset to continue]\r\n"
            if seg.elapsed_s >= seg.duration_s:
                self._pos = seg.end
                self._queue.pop(0)
        if self._dwell_left_s > 0 and not self._queue:
            self._dwell_left_s = max(0.0, self._dwell_left_s - dt)
        if not self._queue and self._state in ("Run", "Home"):
            self._state = "Idle"
        return out

    def _process_lines(self) -> bytes:
        out = bytearray()
        while self._pending or self._sync_waiting:
            if self._sync_waiting is not None:
                if self._queue or self._dwell_left_s > 0 or self._state.startswith("Hold"):
                    break
                line, self._sync_waiting = self._sync_waiting, None
                out += self._finish_sync(line)
                continue
            line = self._pending.pop(0)
            self.lines_received.append(line)
            out += self._execute(line)
        return bytes(out)

    def _execute(self, raw: str) -> bytes:
        line = re.sub(r"\(.*?\)|;.*$|\s", "", raw).upper()
        if not line:
            return b"ok\r\n"
        if "error" in self._faults:
            code = self._faults.pop("error").get("code", 20)
            return f"error:{code}\r\n".encode()
        if line.startswith("$"):
            return self._system_command(line)
        if self._state == "Alarm":
            return b"error:9\r\n"
        return self._gcode(line)

    def _system_command(self, line: str) -> bytes:
        if line == "$$":
            body = "".join(f"${k}={v}\r\n" for k, v in sorted(self.settings.items()))
            return body.encode() + b"ok\r\n"
        if line == "$I":
            return b"[VER:1.1h.20190825:]\r\n[OPT:V,15,128]\r\nok\r\n"
        if line == "$X":
            if self._state == "Alarm":
                self._state = "Idle"
                return b"[MSG:Caution: Unlocked]\r\nok\r\n"
            return b"ok\r\n"
        if line == "$H":
            if not self.settings[22]:
                return b"error:5\r\n"
            # The cycle finds the physical zero: from here on the machine position is the tool's.
            self._pos = [a + b for a, b in zip(self._pos, self._offset, strict=True)]
            self._offset = [0.0, 0.0, 0.0, 0.0]
            self._state = "Home"
            self._plan([0.0, 0.0, 0.0, self._pos[3]], self.settings[25])
            self._sync_waiting = "$H"
            return b""
        m = re.fullmatch(r"\$(\d+)=([-+]?\d*\.?\d+)", line)
        if m:
            key = int(m.group(1))
            if key not in self.settings:
                return b"error:3\r\n"
            if self._state not in ("Idle", "Alarm"):
                return b"error:8\r\n"
            self.settings[key] = float(m.group(2))
            return b"ok\r\n"
        return b"error:3\r\n"

    def _gcode(self, line: str) -> bytes:
        words = _WORD.findall(line)
        if "".join(a + b for a, b in words) != line:
            return b"error:1\r\n" if not line[:1].isalpha() else b"error:2\r\n"
        motion = None
        target: dict[str, float] = {}
        spindle = None
        dwell = None
        p_word = None
        for letter, num in words:
            value = float(num)
            if letter == "G":
                if value in (0, 1):
                    motion = int(value)
                elif value == 4:
                    dwell = True
                elif value == 90:
                    self._absolute = True
                elif value == 91:
                    self._absolute = False
                elif value in (17, 21, 54, 94):
                    pass
                else:
                    return b"error:20\r\n"
            elif letter == "M":
                if value == 3:
                    spindle = True
                elif value == 5:
                    spindle = False
                else:
                    return b"error:20\r\n"
            elif letter in self.axes:
                target[letter] = value
            elif letter == "F":
                if value <= 0:
                    return b"error:4\r\n"
                self._feed_mm_min = value
            elif letter == "S":
                self._spindle_speed = value
            elif letter == "P":
                p_word = value
            else:
                return b"error:20\r\n"
        if dwell:
            if p_word is None:
                return b"error:28\r\n"
            self._dwell_left_s = p_word
            self._sync_waiting = "G4"
            return b""
        if spindle is not None:
            self._sync_waiting = "M3" if spindle else "M5"
            return b""
        if target:
            if motion is None:
                return b"error:31\r\n"
            if motion == 1 and self._feed_mm_min <= 0:
                return b"error:22\r\n"
            start = self._planned_end()
            end = list(start)
            for i, axis in enumerate(self.axes):
                if axis in target:
                    end[i] = target[axis] if self._absolute else start[i] + target[axis]
            rate = self.settings[110] if motion == 0 else min(self._feed_mm_min, self.settings[110])
            self._plan(end, rate)
        return b"ok\r\n"

    def _planned_end(self) -> list[float]:
        return list(self._queue[-1].end) if self._queue else list(self._pos)

    def _plan(self, end: list[float], rate_mm_min: float) -> None:
        start = self._planned_end()
        dist = math.dist(start[:3], end[:3]) or abs(end[3] - start[3])
        self._queue.append(_Segment(start, end, dist / (rate_mm_min / 60.0)))
        if self._state == "Idle":
            self._state = "Run"

    def _finish_sync(self, what: str) -> bytes:
        if what == "$H":
            self._state = "Idle"
        elif what in ("M3", "M5"):
            self._set_spindle(what == "M3" and self._spindle_speed > 0, self._spindle_speed)
        return b"ok\r\n"

    def _set_spindle(self, on: bool, speed: float) -> None:
        changed = on != self._spindle_on
        self._spindle_on = on
        self._spindle_speed = speed if on else 0.0
        if changed:
            self._notify_tool(on, self.tool_pose())

    def _status_report(self) -> bytes:
        pos = self._position()[: max(3, len(self.axes))]
        feed = self._feed_mm_min if self._state == "Run" else 0
        mpos = ",".join(f"{v:.3f}" for v in pos)
        return f"<{self._state}|MPos:{mpos}|FS:{feed:.0f},{self._spindle_speed:.0f}>\r\n".encode()

    def _maybe_garble(self, out: bytes) -> bytes:
        if out and "garbage" in self._faults:
            del self._faults["garbage"]
            return b"\xfe\x13Gr\x00\x9b#&~~\xff\r\n"
        return out
