"""A G-code arm on a serial line, GRBL 1.1 by default; other firmware through the config's
command templates. The only module that knows this wire protocol.

Protocol (GRBL 1.1): each line is answered `ok` or `error:N`; `ALARM:N` may come at any
time; `?` (no newline) is answered by `<State|MPos:x,y,z|...>`; `!` holds the feed; Ctrl-X
resets and is answered by the banner `Grbl 1.1h ['$' for help]`. The driver never sends
`$X`: an alarm is for the operator to clear.
"""

from __future__ import annotations

import logging
import math
import re
import time

from drivers.arm.base import Arm, ArmStatus
from drivers.arm.config import SerialArmConfig
from drivers.arm.errors import (
    AlarmResponse,
    ArmError,
    ConnectionLost,
    ErrorResponse,
    NoResponse,
    NotConnected,
    OutOfReach,
)
from drivers.arm.grbl_codes import alarm_meaning, error_meaning
from drivers.arm.kinematics import Pose
from drivers.arm.serial_line import SerialLine

log = logging.getLogger(__name__)

SOFT_RESET = b"\x18"
FEED_HOLD = b"!"
STATUS_QUERY = b"?"
_BANNER = re.compile(r"Grbl (\S+)")
_STATUS = re.compile(r"<([A-Za-z]+)(?::\d+)?\|(.*)>")
_STATES = {
    "Idle": "idle",
    "Run": "moving",
    "Jog": "moving",
    "Home": "moving",
    "Hold": "hold",
    "Door": "hold",
    "Alarm": "alarm",
    "Check": "fault",
    "Sleep": "fault",
}
BAUD_HINT = "the device answers but not in GRBL's language: check arm.serial.baud and the firmware"


def plan_move(cfg: SerialArmConfig, x_mm: float, y_mm: float, z_mm: float, angle_deg: float | None = None) -> list[str]:
    """The G-code lines for a move, after checking the target; OutOfReach if refused."""
    where = f"target ({x_mm}, {y_mm}, {z_mm}) mm"
    if why := cfg.workspace.violation(x_mm, y_mm, z_mm):
        raise OutOfReach(f"{where}: {why} (arm.serial.workspace)")
    fields = dict(x_mm=x_mm, y_mm=y_mm, z_mm=z_mm, angle_deg=angle_deg or 0.0, feed_mm_min=cfg.speed_mm_s * 60.0)
    lines = []
    if angle_deg is not None:
        if not math.isfinite(angle_deg):
            raise OutOfReach(f"{where}: angle {angle_deg} deg is not a number")
        if not cfg.commands.rotate:
            raise OutOfReach(
                f"{where} at angle {angle_deg} deg: this arm has no tool rotation command",
                hint="omit the angle, or set arm.serial.commands.rotate (e.g. 'G0 A{angle_deg:.2f}')",
            )
        lines.append(cfg.commands.rotate.format(**fields))
    template = cfg.commands.rapid if cfg.rapid_moves else cfg.commands.feed
    lines.append(template.format(**fields))
    return lines


class SerialGcodeArm(Arm):
    """Drives a G-code arm through a SerialLine; see the module docstring for the protocol."""

    def __init__(self, line: SerialLine, cfg: SerialArmConfig):
        self.line = line
        self.port = line.port
        self.cfg = cfg
        self.firmware: str | None = None
        self._connected = False
        self._lost = False
        self._setup_done = False
        self._held = False
        self._state = "disconnected"
        self._pose: Pose | None = None
        self._angle_deg = 0.0
        self._gripper_closed: bool | None = None

    # ----- Arm interface -----

    @property
    def is_connected(self) -> bool:
        return self._connected and self.line.is_open

    def connect(self) -> None:
        self.line.open()
        try:
            self._handshake()
        except ArmError:
            self.line.close()
            raise

    def disconnect(self) -> None:
        self.line.close()
        self._connected = self._lost = False
        self._state = "disconnected"

    def check_target(self, x_mm, y_mm, z_mm, angle_deg=None) -> None:
        plan_move(self.cfg, x_mm, y_mm, z_mm, angle_deg)

    def home(self) -> None:
        cmd = self.cfg.commands.home
        if not cmd:
            self.move_to(*self.cfg.home_position_mm)
            return
        with self._guard(cmd):
            self._ready(allow_alarm=True)
            try:
                # GRBL answers $H only once the cycle is done.
                self._command(cmd, self.cfg.motion_timeout_s)
            except ErrorResponse as e:
                if e.code == 5:
                    e.hint = (
                        "homing is disabled on the controller ($22=0): enable it, or set "
                        'arm.serial.commands.home = "" to move to arm.serial.home_position_mm'
                    )
                raise
            self._state = "idle"
            self._setup()
            self._wait_idle(self.cfg.motion_timeout_s)

    def move_to(self, x_mm, y_mm, z_mm, angle_deg=None, *, wait=True) -> None:
        lines = plan_move(self.cfg, x_mm, y_mm, z_mm, angle_deg)
        with self._guard(lines[-1]):
            self._ready()
            for line in lines:
                self._command(line, self.cfg.command_timeout_s)
            if angle_deg is not None:
                self._angle_deg = angle_deg
            if wait:
                self._wait_idle(self.cfg.motion_timeout_s)

    def open_gripper(self) -> None:
        self._gripper(self.cfg.commands.gripper_open, closed=False)

    def close_gripper(self) -> None:
        self._gripper(self.cfg.commands.gripper_close, closed=True)

    def wait_until_idle(self, timeout_s: float | None = None) -> None:
        with self._guard(self.cfg.commands.wait or "?"):
            self._ready()
            self._wait_idle(timeout_s or self.cfg.motion_timeout_s)

    def stop(self) -> None:
        """Stop motion now, keeping the grip. With GRBL's feed hold '!' the machine decelerates
        and queued moves stay queued until the next command flushes them: a soft reset at
        once would also stop the spindle, i.e. open a spindle-driven gripper mid-air."""
        if not self.is_connected:
            return
        cmd = self.cfg.commands.stop
        try:
            if cmd == FEED_HOLD.decode():
                self.line.write(FEED_HOLD, cmd)
                self._held = True
            elif cmd:
                self._command(cmd, self.cfg.command_timeout_s)
            if self.cfg.status_query:
                deadline = time.monotonic() + self.cfg.command_timeout_s
                while time.monotonic() < deadline:
                    state = self._query_status()
                    if state in ("Hold:0", "Idle", "Alarm") or state.startswith("Door"):
                        break
                    time.sleep(self.cfg.poll_interval_s)
            log.info("arm on %s stopped (%s)", self.port, cmd or "no stop command configured")
        except ArmError as e:
            log.error("could not confirm the stop of the arm on %s: %s", self.port, e)

    def status(self) -> ArmStatus:
        if not self.is_connected:
            return ArmStatus("disconnected", self._pose, self._gripper_closed)
        with self._guard("?"):
            if self.cfg.status_query:
                self._query_status()
            return ArmStatus(self._state, self._pose, self._gripper_closed, self.firmware or "")

    # ----- protocol -----

    def _handshake(self) -> None:
        self._setup_done = self._held = False
        if self.cfg.soft_reset_on_connect:
            self.line.reset_input()
            self.line.write(SOFT_RESET, "Ctrl-X")
            self._await_banner()
        self._connected = True
        self._lost = False
        self._state = "idle"
        if self.cfg.status_query:
            self._query_status()
        if self._state == "alarm":
            log.warning("arm on %s is in alarm after start-up; it needs homing", self.port)
        else:
            self._setup()

    def _await_banner(self) -> None:
        deadline = time.monotonic() + self.cfg.connect_timeout_s
        seen = []
        while (line := self.line.read_line(deadline, "Ctrl-X")) is not None:
            if m := _BANNER.search(line):
                self.firmware = m.group(0)
                log.info("%s: %s", self.port, self.firmware)
                # Drain the start-up messages ([MSG:...]) that follow the banner.
                while (extra := self.line.read_line(time.monotonic() + 0.05)) is not None:
                    self._note(extra, "Ctrl-X")
                return
            if line:
                seen.append(line)
        raise NoResponse(
            f"no GRBL start-up banner within {self.cfg.connect_timeout_s} s after a soft reset",
            port=self.port,
            command="Ctrl-X",
            reply=" | ".join(seen)[:200] or None,
            hint=(BAUD_HINT if seen else "check the arm is powered and the port is right (`run-cell ports`)")
            + "; for non-GRBL firmware set arm.serial.soft_reset_on_connect = false",
        )

    def _setup(self) -> None:
        if self._held:
            # Flush moves left queued by a feed hold; safe: the machine is at rest.
            log.warning("arm on %s: flushing motion queued before the stop", self.port)
            self.line.write(SOFT_RESET, "Ctrl-X")
            self._await_banner()
            self._held = False
            self._gripper_closed = False
        for line in self.cfg.commands.setup:
            self._command(line, self.cfg.command_timeout_s)
        self._setup_done = True

    def _ready(self, allow_alarm: bool = False) -> None:
        if not self._connected:
            if not self._lost:
                raise NotConnected("the arm is not connected", port=self.port)
            self._reconnect()
        if self._state == "alarm" and not allow_alarm:
            raise AlarmResponse("the arm is in alarm and locked", port=self.port)
        if self._state != "alarm" and (not self._setup_done or self._held):
            self._setup()

    def _reconnect(self) -> None:
        log.warning("reconnecting to the arm on %s", self.port)
        self.line.close()
        self.line.wait_until_present(self.cfg.reconnect_timeout_s)
        self.line.open()
        self._handshake()

    def _gripper(self, cmd: str, closed: bool) -> None:
        if not cmd:
            raise ArmError(
                "this arm has no gripper command configured",
                port=self.port,
                hint="set arm.serial.commands.gripper_open / gripper_close",
            )
        with self._guard(cmd):
            self._ready()
            # GRBL runs spindle commands in order with motion: the ok may wait for moves to end.
            self._command(cmd, self.cfg.motion_timeout_s)
            self._gripper_closed = closed
            self._wait_idle(self.cfg.motion_timeout_s)

    def _command(self, cmd: str, timeout_s: float) -> None:
        """Send one line and wait for its `ok`."""
        self.line.write(cmd.encode("ascii") + b"\n", cmd)
        deadline = time.monotonic() + timeout_s
        while (reply := self.line.read_line(deadline, cmd)) is not None:
            if reply == "ok":
                return
            self._raise_if_refused(reply, cmd, "a command")
            self._note(reply, cmd)
        raise NoResponse(f"no reply within {timeout_s} s", port=self.port, command=cmd)

    def _raise_if_refused(self, reply: str, cmd: str, what: str) -> None:
        """GRBL's `error:N` to the command `cmd` as an ErrorResponse carrying its meaning."""
        if m := re.fullmatch(r"error:(\d+)", reply):
            code = int(m.group(1))
            raise ErrorResponse(
                f"arm refused {what}: error:{code}: {error_meaning(code)}",
                code=code,
                port=self.port,
                command=cmd,
                reply=reply,
            )

    def _note(self, reply: str, cmd: str) -> None:
        """Handle a line that is not the answer awaited: push messages, status, alarms, garbage."""
        if not reply:
            return
        if m := re.fullmatch(r"ALARM:(\d+)", reply):
            code = int(m.group(1))
            self._state = "alarm"
            raise AlarmResponse(
                f"arm alarm {code}: {alarm_meaning(code)}", code=code, port=self.port, command=cmd, reply=reply
            )
        if _BANNER.search(reply):
            self._connected = False
            self._lost = True
            raise ConnectionLost(
                "the arm controller restarted unexpectedly (power dip or USB reset); its position is lost",
                port=self.port,
                command=cmd,
                reply=reply,
            )
        if m := _STATUS.fullmatch(reply):
            self._parse_status(m)
            return
        if reply.startswith("[") and reply.endswith("]"):
            log.info("%s: %s", self.port, reply)
            return
        raise NoResponse("unreadable reply from the arm", port=self.port, command=cmd, reply=reply[:80], hint=BAUD_HINT)

    def _parse_status(self, m: re.Match) -> str:
        self._state = _STATES.get(m.group(1), "fault")
        for field in m.group(2).split("|"):
            key, _, value = field.partition(":")
            if key in ("MPos", "WPos"):
                try:
                    v = [float(s) for s in value.split(",")]
                except ValueError:
                    continue
                if len(v) >= 4:
                    self._angle_deg = v[3]
                self._pose = Pose(v[0], v[1], v[2], self._angle_deg)
        return m.group(0)[1:].split("|", 1)[0]

    def _query_status(self) -> str:
        """Send `?` and return the raw state word (e.g. 'Idle', 'Hold:0')."""
        self.line.write(STATUS_QUERY, "?")
        deadline = time.monotonic() + self.cfg.command_timeout_s
        while (reply := self.line.read_line(deadline, "?")) is not None:
            if m := _STATUS.fullmatch(reply):
                return self._parse_status(m)
            if reply in ("ok",) or reply.startswith("error:"):
                log.debug("%s: late reply %r", self.port, reply)
                continue
            self._note(reply, "?")
        raise NoResponse(f"no status report within {self.cfg.command_timeout_s} s", port=self.port, command="?")

    def _wait_idle(self, timeout_s: float) -> None:
        """Wait for the end of all motion: the wait command's `ok` (G4 P0 is a barrier),
        then '?' until Idle; '?' polled meanwhile so an alarm or hold is seen at once."""
        deadline = time.monotonic() + timeout_s
        wait_cmd = self.cfg.commands.wait
        if wait_cmd:
            self.line.write(wait_cmd.encode("ascii") + b"\n", wait_cmd)
            # Without status queries there is nothing to poll: just wait for the barrier's ok.
            next_poll = time.monotonic() + self.cfg.poll_interval_s if self.cfg.status_query else deadline
            while True:
                reply = self.line.read_line(min(deadline, next_poll), wait_cmd)
                if reply == "ok":
                    break
                if reply is not None:
                    self._raise_if_refused(reply, wait_cmd, "the wait command")
                    self._note(reply, wait_cmd)
                    if self._state == "alarm":
                        raise AlarmResponse(
                            "arm went into alarm while moving", port=self.port, command=wait_cmd, reply=reply
                        )
                if time.monotonic() >= deadline:
                    raise NoResponse(
                        f"motion not finished within {timeout_s} s",
                        port=self.port,
                        command=wait_cmd,
                        hint="raise arm.serial.motion_timeout_s if the move is long",
                    )
                if self.cfg.status_query and time.monotonic() >= next_poll:
                    self.line.write(STATUS_QUERY, "?")
                    next_poll = time.monotonic() + self.cfg.poll_interval_s
        if not self.cfg.status_query:
            self._state = "idle"
            return
        while True:
            state = self._query_status()
            if state == "Idle":
                return
            if state == "Alarm":
                raise AlarmResponse("arm went into alarm while moving", port=self.port, command="?", reply=state)
            if time.monotonic() >= deadline:
                raise NoResponse(
                    f"arm not idle within {timeout_s} s (state {state})",
                    port=self.port,
                    command="?",
                    reply=state,
                    hint="raise arm.serial.motion_timeout_s if the move is long",
                )
            time.sleep(self.cfg.poll_interval_s)

    def _link_lost(self) -> None:
        self._connected = False
        self._lost = True
        self._state = "disconnected"
        self.line.close()

    def _leave_safe(self, error: ArmError) -> None:
        """Feed hold; after an alarm the machine has already halted itself."""
        if not isinstance(error, AlarmResponse):
            self.stop()
