"""A G-code arm on a serial line, GRBL 1.1 by default; other firmware through the config's
command templates. The only module that knows this wire protocol.

Protocol (GRBL 1.1): each line is answered `ok` or `error:N`; `ALARM:N` may come at any
time; `?` (no newline) is answered by `<State|MPos:x,y,z|...>`; `!` holds the feed; Ctrl-X
resets and is answered by the banner `Grbl 1.1h ['$' for help]`. The driver sends `$X`
only from unlock(), at the operator's request: an alarm is for the operator to clear.

Controller restarts. GRBL keeps its machine position only in RAM: a restart (power dip,
brown-out, watchdog, the DTR pulse of an Arduino's auto-reset) starts it at MPos 0 (in alarm
if homing is enabled), the spindle off (the gripper open) and the parser reset. Two ways
the driver tells one from a mere link loss:

- The link stayed up: GRBL's banner arrives unasked, in the middle of a command. The driver
  latches PositionLost (Arm: no motion until homed or unlocked) and re-runs its handshake
  when homing or unlocking.
- The link went too (the adapter re-enumerated): no banner can be told apart, because the
  reconnect's own soft reset (or the port opening) makes one. What tells is the position:
  a controller that only lost the link kept its MPos and finished the moves it had queued,
  so after the handshake it reports the last position it reported or the end of the last
  move sent; a restarted one reports 0 (or its homing pull-off). Anything else within
  SAME_POSITION_MM latches PositionLost, and so does any reconnect to firmware with no
  status report (arm.serial.status_query = false): nothing can vouch for its position.
  A controller that restarts while the arm sits exactly at machine zero passes, and the
  position it then reports is right. A controller reset by the reconnect while still
  moving its queue raises GRBL's own ALARM:3 (the alarm lock). Every connection of a driver
  that knew a position compares, not only its automatic reconnect: the service connects the
  same driver for each job and holds the port's lock between them: no other run-cell moved it.
"""

from __future__ import annotations

import logging
import math
import re
import time

from drivers.arm.base import Arm, ArmState, ArmStatus
from drivers.arm.config import SerialArmConfig
from drivers.arm.errors import (
    AlarmResponse,
    ArmError,
    ErrorResponse,
    NoResponse,
    NotConnected,
    OutOfReach,
    PositionLost,
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
_STATES: dict[str, ArmState] = {
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
# Positions closer than this are the same (GRBL reports 3 decimals; half a step of a coarse 10
# steps/mm axis); a restart moves MPos to 0, far from where a job leaves the arm.
SAME_POSITION_MM = 0.05
NO_HOMING_CYCLE_HINT = (
    "this arm has no homing cycle (arm.serial.commands.home is empty): its position is the controller's "
    "count, which restarted at 0 wherever the arm stood; move the arm to machine zero by hand, then "
    "unlock it (Arm.unlock) or `run-cell home`; better, enable homing ($22=1, arm.serial.commands.home = '$H')"
)


def _at_fixed_jaw_angle(cfg: SerialArmConfig, where: str, angle_deg: float) -> None:
    """An arm without a rotation axis grips at its one jaw angle: OutOfReach, saying so, when the grip
    asked for is further from it than the tolerance (jaw angles repeat every 180 deg)."""
    fixed = cfg.fixed_jaw_angle_deg
    off = abs((angle_deg - fixed + 90.0) % 180.0 - 90.0)
    if off > cfg.fixed_jaw_tolerance_deg:
        raise OutOfReach(
            f"{where}: the grip needs the jaws at {angle_deg:.1f} deg, and this arm has no rotation axis: its jaws "
            f"close at {fixed:.1f} deg (arm.serial.fixed_jaw_angle_deg), {off:.1f} deg off, more than "
            f"arm.serial.fixed_jaw_tolerance_deg ({cfg.fixed_jaw_tolerance_deg:g} deg); the part is left",
            hint="a part turned the other way is picked; for every angle give the arm a rotation axis "
            "(arm.serial.commands.rotate, e.g. 'G0 A{angle_deg:.2f}')",
        )


def plan_move(cfg: SerialArmConfig, x_mm: float, y_mm: float, z_mm: float, angle_deg: float | None = None) -> list[str]:
    """The G-code lines for a move, after checking the target; OutOfReach if refused."""
    where = f"target ({x_mm:.1f}, {y_mm:.1f}, {z_mm:.1f}) mm"
    if why := cfg.workspace.violation(x_mm, y_mm, z_mm):
        raise OutOfReach(f"{where}: {why} (arm.serial.workspace)")
    fields = dict(x_mm=x_mm, y_mm=y_mm, z_mm=z_mm, angle_deg=angle_deg or 0.0, feed_mm_min=cfg.speed_mm_s * 60.0)
    lines = []
    if angle_deg is not None:
        if not math.isfinite(angle_deg):
            raise OutOfReach(f"{where}: angle {angle_deg} deg is not a number")
        if cfg.commands.rotate:
            lines.append(cfg.commands.rotate.format(**fields))
        else:
            _at_fixed_jaw_angle(cfg, where, angle_deg)  # no rotation axis: the jaws stay as they are
    template = cfg.commands.rapid if cfg.rapid_moves else cfg.commands.feed
    lines.append(template.format(**fields))
    return lines


def expected_move_s(
    cfg: SerialArmConfig, start_mm: tuple[float, float, float], end_mm: tuple[float, float, float]
) -> float:
    """Longest time the controller takes for one move from rest to rest, as GRBL plans it: a G1
    at the configured feed (a rapid at top speed), the speed along the path capped where any
    axis would exceed its max_rate_mm_min, and the acceleration capped by the slowest-accelerating
    axis' share of the path. Reaching the cruise speed v costs at most v / a over the cruise time
    (a triangular profile takes less: 2 sqrt(d / a) <= d / v + v / a)."""
    deltas = [abs(b - a) for a, b in zip(start_mm, end_mm, strict=True)]
    dist_mm = math.hypot(*deltas)
    if dist_mm == 0:
        return 0.0
    moving = [
        (d, r / 60.0, acc)
        for d, r, acc in zip(deltas, cfg.max_rate_mm_min, cfg.acceleration_mm_s2, strict=True)
        if d > 0
    ]
    top_mm_s = min(rate * dist_mm / d for d, rate, _ in moving)
    speed_mm_s = top_mm_s if cfg.rapid_moves else min(cfg.speed_mm_s, top_mm_s)
    accel_mm_s2 = min(acc * dist_mm / d for d, _, acc in moving)
    return dist_mm / speed_mm_s + speed_mm_s / accel_mm_s2


def motion_timeout_s(cfg: SerialArmConfig, expected_s: float) -> float:
    """How long to wait for motion expected to take expected_s: with the margins, never below
    motion_timeout_s."""
    return max(cfg.motion_timeout_s, expected_s * cfg.motion_margin_factor + cfg.motion_margin_s)


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
        self._state: ArmState = "disconnected"
        self._pose: Pose | None = None
        self._target_mm: tuple[float, float, float] | None = None  # end of the last move sent
        self._queued_s = 0.0  # expected time of the motion sent since the controller was last idle
        self.last_motion_timeout_s: float | None = None  # the wait for the last motion, for diagnostics
        self._stale = False  # the controller restarted under the driver: its session must be set up again
        self._position_lost_hint = None if cfg.commands.home else NO_HOMING_CYCLE_HINT
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

    def check_target(self, x_mm: float, y_mm: float, z_mm: float, angle_deg: float | None = None) -> None:
        plan_move(self.cfg, x_mm, y_mm, z_mm, angle_deg)

    def home(self) -> None:
        """The homing cycle, which also ends a PositionLost latch; without one (commands.home
        empty) a move to home_position_mm, refused while the position is lost."""
        cmd = self.cfg.commands.home
        if not cmd:
            self._refuse_while_position_lost("home")
            self.move_to(*self.cfg.home_position_mm)
            return
        with self._guard(cmd):
            self._ready(cmd, allow_alarm=True, recover=True)
            try:
                # GRBL answers $H only once the cycle is done.
                self._command(cmd, self.cfg.homing_timeout_s)
            except ErrorResponse as e:
                if e.code == 5:
                    e.hint = (
                        "homing is disabled on the controller ($22=0): enable it, or set "
                        'arm.serial.commands.home = "" to move to arm.serial.home_position_mm'
                    )
                raise
            self._state = "idle"
            self._setup()
            self._wait_idle(self.cfg.homing_timeout_s, "the homing cycle (arm.serial.homing_timeout_s)")
            self._target_mm = None  # where homing ends is the controller's to report
            self._position_regained("homed")

    def move_to(
        self, x_mm: float, y_mm: float, z_mm: float, angle_deg: float | None = None, *, wait: bool = True
    ) -> None:
        lines = plan_move(self.cfg, x_mm, y_mm, z_mm, angle_deg)
        self._refuse_while_position_lost(lines[-1])
        with self._guard(lines[-1]):
            self._ready(lines[-1])
            expected_s = self._move_time_s((x_mm, y_mm, z_mm), angle_deg)
            self._target_mm = (x_mm, y_mm, z_mm)  # before sending: a link lost mid-send may have delivered it
            self._queued_s += expected_s  # likewise
            for line in lines:
                self._command(line, self.cfg.command_timeout_s)
            if angle_deg is not None:
                self._angle_deg = angle_deg
            if wait:
                self._wait_motion()

    def open_gripper(self) -> None:
        self._gripper(self.cfg.commands.gripper_open, closed=False)

    def close_gripper(self) -> None:
        self._gripper(self.cfg.commands.gripper_close, closed=True)

    def wait_until_idle(self, timeout_s: float | None = None) -> None:
        cmd = self.cfg.commands.wait or "?"
        self._refuse_while_position_lost(cmd)
        with self._guard(cmd):
            self._ready(cmd)
            self._wait_motion(timeout_s)

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
            if self.position_lost:
                return ArmStatus("alarm", self._pose, self._gripper_closed, PositionLost.MESSAGE)
            return ArmStatus(self._state, self._pose, self._gripper_closed, self.firmware or "")

    def unlock(self) -> None:
        """For an operator who has checked the arm is where the controller says (its MPos; after
        a power-up without homing that is machine zero): motion resumes from that position and
        nothing moves. A controller in alarm (a power-up with homing enabled, or any other
        alarm) gets GRBL's `$X` here, the one place the driver sends it, because the operator
        asked; then the setup lines."""
        with self._guard("unlock"):
            self._ready("unlock", allow_alarm=True, recover=True)
            if self._state == "alarm":
                log.warning("arm on %s: operator unlock of the alarm ($X)", self.port)
                self._command("$X", self.cfg.command_timeout_s)
                self._state = "idle"
                self._setup()
            if self.cfg.status_query:
                self._query_status()
            self._target_mm = None
            self._position_regained("unlocked by the operator")

    # ----- protocol -----

    def _handshake(self) -> None:
        held = self._positions_held()
        self._pose = None  # what the controller reports now, not what it reported before
        self._setup_done = self._held = self._stale = False
        if self.cfg.soft_reset_on_connect:
            self._queued_s = 0.0  # the soft reset flushed anything queued
            self.line.reset_input()
            self.line.write(SOFT_RESET, "Ctrl-X")
            self._await_banner()
        self._connected = True
        self._lost = False
        self._state = "idle"
        if self.cfg.status_query:
            self._query_status()
        if held and not self.position_lost and (jump := self._position_jump(held)):
            self._restarted(jump, "connect")
        if self._in_alarm():  # as the status query just reported it
            log.warning("arm on %s is in alarm after start-up; it needs homing", self.port)
        else:
            self._setup()

    def _in_alarm(self) -> bool:
        return self._state == "alarm"

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
            self._queued_s = 0.0
            self._gripper_closed = False
        for line in self.cfg.commands.setup:
            self._command(line, self.cfg.command_timeout_s)
        self._setup_done = True

    def _ready(self, command: str, allow_alarm: bool = False, recover: bool = False) -> None:
        """Connected (reconnecting after a lost link), set up, not locked. recover (home,
        unlock): go on while the position is lost, after a fresh handshake if the controller
        restarted under the driver."""
        if not self._connected:
            if not self._lost:
                raise NotConnected("the arm is not connected", port=self.port)
            self._reconnect()
        elif self._stale and recover:
            self._handshake()
        if self.position_lost and not recover:
            self._refuse_while_position_lost(command)  # found by the reconnect
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

    def _positions_held(self) -> list[tuple[float, float, float]]:
        """Where a controller that kept running may be: the position it last reported, and the
        end of the last move sent (it finishes its queue while the link is down)."""
        held = [] if self._pose is None else [(self._pose.x_mm, self._pose.y_mm, self._pose.z_mm)]
        return list(dict.fromkeys(held + ([] if self._target_mm is None else [self._target_mm])))

    def _position_jump(self, held: list[tuple[float, float, float]]) -> str | None:
        """Why the controller's position after a handshake shows a restart (None: it does not)."""
        if not self.cfg.status_query:
            return "reconnected to a controller whose position cannot be read back (arm.serial.status_query = false)"
        if self._pose is None:
            return "reconnected to a controller whose status report gives no position"
        here = (self._pose.x_mm, self._pose.y_mm, self._pose.z_mm)
        if any(max(abs(a - b) for a, b in zip(here, h, strict=True)) <= SAME_POSITION_MM for h in held):
            return None
        where = " or ".join(_mm(h) for h in held)
        return f"MPos {_mm(here)} after reconnecting, where it was {where}"

    def _gripper(self, cmd: str, closed: bool) -> None:
        if not cmd:
            raise ArmError(
                "this arm has no gripper command configured",
                port=self.port,
                hint="set arm.serial.commands.gripper_open / gripper_close",
            )
        self._refuse_while_position_lost(cmd)
        with self._guard(cmd):
            self._ready(cmd)
            # GRBL runs spindle commands in order with motion: the ok may wait for moves to end.
            self._command(cmd, motion_timeout_s(self.cfg, self._queued_s))
            self._gripper_closed = closed
            self._wait_motion()

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
            # Restarted with the link up: the spindle is off (gripper open), setup and parser gone.
            self._stale = True
            self._setup_done = self._held = False
            self._gripper_closed = False
            raise self._restarted(f"{reply.strip()} mid-run", cmd)
        if m := _STATUS.fullmatch(reply):
            self._parse_status(m)
            return
        if reply.startswith("[") and reply.endswith("]"):
            log.info("%s: %s", self.port, reply)
            return
        raise NoResponse("unreadable reply from the arm", port=self.port, command=cmd, reply=reply[:80], hint=BAUD_HINT)

    def _parse_status(self, m: re.Match[str]) -> str:
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

    def _move_time_s(self, target_mm: tuple[float, float, float], angle_deg: float | None) -> float:
        """Expected time of a move to target_mm from where the last move ended (or the reported
        position); from anywhere in the workspace when neither is known."""
        start = self._target_mm
        if start is None and self._pose is not None:
            start = (self._pose.x_mm, self._pose.y_mm, self._pose.z_mm)
        if start is None:  # the farthest corner of the workspace
            ws = self.cfg.workspace
            x, y, z = target_mm
            start = (
                ws.x_min_mm if x - ws.x_min_mm >= ws.x_max_mm - x else ws.x_max_mm,
                ws.y_min_mm if y - ws.y_min_mm >= ws.y_max_mm - y else ws.y_max_mm,
                ws.z_min_mm if z - ws.z_min_mm >= ws.z_max_mm - z else ws.z_max_mm,
            )
        turn_s = 0.0
        if angle_deg is not None:
            turn_s = abs(angle_deg - self._angle_deg) / (self.cfg.rotation_rate_deg_min / 60.0)
        return turn_s + expected_move_s(self.cfg, start, target_mm)

    def _wait_motion(self, at_least_s: float | None = None) -> None:
        """Wait for the motion queued: its expected time with the margins (at least at_least_s)."""
        timeout_s = max(motion_timeout_s(self.cfg, self._queued_s), at_least_s or 0.0)
        why = (
            f"expected {self._queued_s:.1f} s for the moves sent, times arm.serial.motion_margin_factor "
            f"{self.cfg.motion_margin_factor:g} plus motion_margin_s {self.cfg.motion_margin_s:g} s, "
            f"at least motion_timeout_s {self.cfg.motion_timeout_s:g} s"
        )
        self._wait_idle(timeout_s, why)
        self._queued_s = 0.0

    def _wait_idle(self, timeout_s: float, why: str) -> None:
        """Wait for the end of all motion: the wait command's `ok` (G4 P0 is a barrier),
        then '?' until Idle; '?' polled meanwhile so an alarm or hold is seen at once.
        why: how timeout_s was chosen, for the error."""
        self.last_motion_timeout_s = timeout_s
        hint = (
            "the arm stalled, was held (feed hold, door) or runs slower than arm.serial says: check it; "
            "set arm.serial.max_rate_mm_min and acceleration_mm_s2 to the firmware's $110-$112 and $120-$122, "
            "or raise motion_margin_factor"
        )
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
                        f"motion not finished within {timeout_s:.1f} s ({why})",
                        port=self.port,
                        command=wait_cmd,
                        reply=None if self._state == "moving" else self._state,
                        hint=hint,
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
                    f"arm not idle within {timeout_s:.1f} s ({why}; state {state})",
                    port=self.port,
                    command="?",
                    reply=state,
                    hint=hint,
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


def _mm(xyz: tuple[float, float, float]) -> str:
    return "(" + ", ".join(f"{v:.3f}" for v in xyz) + ") mm"
