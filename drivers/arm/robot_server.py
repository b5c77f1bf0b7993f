"""The cell as the vision server an industrial robot's program asks (arm.kind 'robot-server').

The robot runs its own program and does the motion; the cell keeps its state machine, vision,
verification and record. The runner drives this arm as any other: `announce` offers the pick,
the first motion waits until the robot has taken it (NEXT) and reported PICKED or MISSED, the
move over the bin waits for PLACED; a robot that took a pick and reports nothing within
`pick_timeout_s` makes that motion fail (RobotSilent: the pick is unknown, the cell faults).

Three parts, each usable alone:
- PickBoard: the protocol's meaning (the pick offered, taken, reported; the answer codes, the
  state numbers), shared by the TCP text protocol and the Modbus TCP register map;
- RobotServer: the TCP text protocol on its own threads (an acceptor and one connection);
- RobotServerArm: the Arm the runner holds.

Protocol, answer codes and state numbers: docs/robots.md. Nothing here imports the cell.
"""

from __future__ import annotations

import collections
import contextlib
import enum
import ipaddress
import itertools
import logging
import math
import selectors
import socket
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, Literal

from drivers.arm.base import Arm, ArmStatus, PickPlan
from drivers.arm.config import RobotServerConfig
from drivers.arm.errors import (
    ArmError,
    ConnectionLost,
    NotConnected,
    OutOfReach,
    PickUnknown,
    PickWithdrawn,
    RobotSilent,
)

log = logging.getLogger(__name__)

# What the cell is doing, as the robot needs to know it (the line service says it; a lone job: running).
CellStatus = Literal["starting", "ready", "running", "waiting", "paused", "halted", "error", "hold", "stopping"]

Answer = tuple[float, ...]


class StateNo(enum.IntEnum):
    """STATE's answer `(state_no)`."""

    NOT_READY = 0  # starting or stopping
    READY = 1  # no job: NEXT answers (-1,2)
    LOOKING = 2  # a job runs: capturing, locating, verifying, planning
    OFFERED = 3  # a pick is waiting for the robot's NEXT
    TAKEN = 4  # the robot has the pick: PICKED or MISSED awaited
    PICKED = 5  # the robot holds the part: PLACED (or MISSED) awaited
    WAITING = 6  # continuous job, nothing to pick: the cell keeps looking
    PAUSED = 7
    HALTED = 8
    ERROR = 9  # a fault: the alarm says why; Reset on the cell
    HOLD = 10  # a recalibration report or a plate capture holds the cell


class NotNow(enum.IntEnum):
    """NEXT's `(-1,code)`: the cell cannot give a pick now."""

    FAULT = 1
    NOT_RUNNING = 2
    HALTED = 3
    PAUSED = 4
    HOLD = 5
    NOT_READY = 6  # starting or stopping
    PICK_OUTSTANDING = 7  # the robot has a pick it has not reported: report it first
    BUSY = 8  # (on connect) another robot is connected: this connection is closed


class Bad(enum.IntEnum):
    """`(-2,code)`: the request was not understood or not accepted; the connection stays."""

    UNKNOWN_REQUEST = 1
    BAD_ARGUMENT = 2  # pick_no missing, not a whole number, or more than one argument
    UNKNOWN_PICK = 3  # a pick_no never given to a robot
    ALREADY_REPORTED = 4  # this report (or its pick's end) came before
    OUT_OF_ORDER = 5  # PLACED before PICKED, PICKED or PLACED after MISSED
    PICK_CLOSED = 6  # the pick was closed as unknown (pick_timeout_s passed)
    NOT_TEXT = 7  # not printable ASCII
    TOO_LONG = 9  # the line is longer than max_line_bytes: the connection is closed


_NOT_NOW = {
    "starting": NotNow.NOT_READY,
    "stopping": NotNow.NOT_READY,
    "ready": NotNow.NOT_RUNNING,
    "paused": NotNow.PAUSED,
    "halted": NotNow.HALTED,
    "error": NotNow.FAULT,
    "hold": NotNow.HOLD,
}
_STATE = {
    "starting": StateNo.NOT_READY,
    "stopping": StateNo.NOT_READY,
    "ready": StateNo.READY,
    "running": StateNo.LOOKING,
    "waiting": StateNo.WAITING,
    "paused": StateNo.PAUSED,
    "halted": StateNo.HALTED,
    "error": StateNo.ERROR,
    "hold": StateNo.HOLD,
}
ENDED = frozenset({"missed", "placed", "unknown", "withdrawn"})
REPORTS = ("PICKED", "PLACED", "MISSED")
_KEEP_PAST = 1000  # ended picks remembered, so a late or repeated report gets its proper code


@dataclass
class Pick:
    """One pick offered to the robot: offered -> taken (NEXT) -> picked -> placed, or missed,
    unknown (the robot went silent), withdrawn (a stop before the robot took it)."""

    no: int
    plan: PickPlan
    class_no: int
    state: str = "offered"
    peer: str = ""
    deadline: float = math.inf  # monotonic: the robot's next report is due by then

    def answer(self) -> Answer:
        x, y, z = self.plan.pick_mm
        bx, by, bz = self.plan.bin_mm
        angle = 0.0 if self.plan.angle_deg is None else self.plan.angle_deg
        return (1, x, y, z, angle, self.class_no, self.no, bx, by, bz)


class PickBoard:
    """The protocol's meaning, under one lock: the cell offers a pick and waits; the robot takes
    it (NEXT) and reports. Every report, accepted or refused, is kept for the record."""

    def __init__(self, cfg: RobotServerConfig):
        self.cfg = cfg
        self._cond = threading.Condition()
        self._numbers = itertools.count(1)  # pick_no: unique for the server's life, never reused
        self._current: Pick | None = None
        self._past: collections.OrderedDict[int, Pick] = collections.OrderedDict()
        self._records: collections.deque[dict[str, Any]] = collections.deque(maxlen=10_000)
        self.job_open = False  # the arm is connected: a job runs
        self.status: Callable[[], CellStatus] = lambda: "running" if self.job_open else "ready"
        # called under the lock with (report, pick) once accepted: the simulated world applies it
        self.observers: list[Callable[[str, Pick], None]] = []
        self.counts: collections.Counter[str] = collections.Counter()
        # where a report made while no job runs goes (the line service records it); None: kept for the next job
        self.record_between_jobs: Callable[[dict[str, Any]], None] | None = None
        self.where = f"tcp://{cfg.host}:{cfg.port}"  # the address listened on, for messages

    # ---- the cell's side ---------------------------------------------------------------------
    def offer(self, plan: PickPlan) -> Pick:
        with self._cond:
            self._retire()
            pick = Pick(next(self._numbers), plan, self.cfg.class_numbers.get(plan.cls, plan.class_no))
            self._current = pick
            self._cond.notify_all()
            return pick

    def withdraw(self) -> None:
        """An offer the robot has not taken is withdrawn (a stop, the job's end)."""
        with self._cond:
            pick = self._current
            if pick is not None and pick.state == "offered":
                pick.state = "withdrawn"
                self._record("withdrawn", pick, accepted=True)
                self._cond.notify_all()

    def wait(self, pick: Pick, until: frozenset[str], cancelled: Callable[[], bool]) -> str:
        """Block until the pick reaches one of `until` or ends; its state. Before the robot took it,
        `cancelled()` withdraws it (PickWithdrawn); once taken, a robot silent past its deadline
        closes it as unknown (RobotSilent)."""
        with self._cond:
            while True:
                if pick.state in until or pick.state in ENDED:
                    return pick.state
                if pick.state == "offered" and cancelled():
                    pick.state = "withdrawn"
                    self._record("withdrawn", pick, accepted=True)
                    raise PickWithdrawn(f"pick {pick.no} withdrawn before the robot took it", port=self._port())
                if pick.state != "offered" and time.monotonic() >= pick.deadline:
                    waited = "PICKED or MISSED" if pick.state == "taken" else "PLACED or MISSED"
                    pick.state = "unknown"
                    self.counts["unknown"] += 1
                    self._record("unknown", pick, accepted=True, detail=f"no {waited} within the timeout")
                    x, y, z = pick.plan.pick_mm
                    raise RobotSilent(
                        f"the robot at {pick.peer} took pick {pick.no} ({pick.plan.cls} at robot "
                        f"({x:.1f}, {y:.1f}, {z:.1f}) mm) and reported no {waited} within "
                        f"{self.cfg.pick_timeout_s:g} s: where the part went is unknown",
                        port=self._port(),
                        command=f"pick {pick.no}",
                    )
                self._cond.wait(0.05)

    def take_records(self) -> list[dict[str, Any]]:
        with self._cond:
            out = list(self._records)
            self._records.clear()
            return out

    # ---- the robot's side ----------------------------------------------------------------------
    def next(self, peer: str) -> Answer:
        """NEXT: the pick offered (now taken by the robot), (0) when none comes within next_wait_s,
        (-1,code) when the cell cannot give one."""
        end = time.monotonic() + self.cfg.next_wait_s
        while True:
            with self._cond:
                pick = self._current
                if pick is not None and pick.state in ("taken", "picked"):
                    return (-1, NotNow.PICK_OUTSTANDING)
                if pick is not None and pick.state == "offered":
                    return self._take(pick, peer)
            code = _NOT_NOW.get(self.status())  # outside the lock: the service answers under its own
            if code is not None:
                return (-1, code)
            with self._cond:
                remaining = end - time.monotonic()
                pick = self._current
                if pick is not None and pick.state == "offered":
                    return self._take(pick, peer)
                if remaining <= 0:
                    return (0,)
                self._cond.wait(min(remaining, 0.1))

    def _take(self, pick: Pick, peer: str) -> Answer:
        pick.state, pick.peer = "taken", peer
        pick.deadline = time.monotonic() + self.cfg.pick_timeout_s
        self._past[pick.no] = pick
        while len(self._past) > _KEEP_PAST:
            self._past.popitem(last=False)
        self._record("given", pick, accepted=True, peer=peer)
        self._cond.notify_all()
        return pick.answer()

    def report(self, kind: str, no: int, peer: str) -> Answer:
        """PICKED, PLACED or MISSED pick_no: (1) when accepted, else (-2,code) and nothing changes."""
        with self._cond:
            pick = self._past.get(no)
            code = self._refusal(kind, pick)
            if code is not None or pick is None:
                self.counts["bad_reports"] += 1
                self._keep(
                    {"report": kind.lower(), "pick_no": no, "pick_id": "", "peer": peer, "accepted": False,
                     "code": int(code or Bad.UNKNOWN_PICK), "detail": ""}
                )  # fmt: skip
                log.warning("robot %s: %s %d refused (code %d)", peer, kind, no, int(code or Bad.UNKNOWN_PICK))
                return (-2, int(code or Bad.UNKNOWN_PICK))
            pick.state = kind.lower()
            pick.deadline = time.monotonic() + self.cfg.pick_timeout_s
            for observer in self.observers:
                observer(kind, pick)
            self._record(kind.lower(), pick, accepted=True, peer=peer)
            self._cond.notify_all()
            return (1,)

    @staticmethod
    def _refusal(kind: str, pick: Pick | None) -> Bad | None:
        if pick is None or pick.state in ("offered", "withdrawn"):
            return Bad.UNKNOWN_PICK
        state = pick.state
        if state == "unknown":
            return Bad.PICK_CLOSED
        if state == "taken":
            return Bad.OUT_OF_ORDER if kind == "PLACED" else None
        if state == "picked":
            return Bad.ALREADY_REPORTED if kind == "PICKED" else None
        if state == "missed":
            return Bad.ALREADY_REPORTED if kind == "MISSED" else Bad.OUT_OF_ORDER
        return Bad.ALREADY_REPORTED  # placed

    def state_no(self) -> int:
        with self._cond:
            pick = self._current
            if pick is not None and pick.state in ("offered", "taken", "picked"):
                return int({"offered": StateNo.OFFERED, "taken": StateNo.TAKEN, "picked": StateNo.PICKED}[pick.state])
        return int(_STATE.get(self.status(), StateNo.NOT_READY))

    def not_now_code(self) -> int:
        """The (-1,code) a NEXT would get now; 0 when it could be given a pick."""
        with self._cond:
            pick = self._current
            if pick is not None and pick.state in ("taken", "picked"):
                return int(NotNow.PICK_OUTSTANDING)
        return int(_NOT_NOW.get(self.status(), 0))

    def holding_pick(self) -> Pick | None:
        """The pick the robot has and has not ended, if any."""
        with self._cond:
            pick = self._current
            return pick if pick is not None and pick.state in ("taken", "picked") else None

    # ---- helpers ------------------------------------------------------------------------------
    def _retire(self) -> None:
        pick = self._current
        if pick is not None and pick.state == "offered":
            pick.state = "withdrawn"
            self._record("withdrawn", pick, accepted=True)
        self._current = None

    def _keep(self, record: dict[str, Any]) -> None:
        """For the record: taken by the job's runner (Arm.take_reports), or handed over at once between jobs."""
        if not self.job_open and self.record_between_jobs is not None:
            try:
                self.record_between_jobs(record)
            except Exception:  # the record's own failure is the record's to report; the robot gets its answer
                log.exception("recording a robot's report between jobs")
            return
        self._records.append(record)

    def _record(self, report: str, pick: Pick, *, accepted: bool, peer: str = "", detail: str = "") -> None:
        self._keep(
            {"report": report, "pick_no": pick.no, "pick_id": pick.plan.pick_id, "peer": peer or pick.peer,
             "accepted": accepted, "code": 0, "detail": detail}
        )  # fmt: skip

    def _port(self) -> str:
        return self.where


def format_answer(answer: Answer) -> bytes:
    """`(a,b,...)` as URScript's socket_read_ascii_float reads it, LF-terminated."""
    return ("(" + ",".join(_number(v) for v in answer) + ")\n").encode("ascii")


def _number(v: float) -> str:
    if isinstance(v, int):
        return str(int(v))
    return f"{v:.3f}"


def parse_line(line: bytes, board: PickBoard, peer: str) -> Answer:
    """One request line (without its LF; a trailing CR is dropped) to its answer."""
    try:
        text = line.rstrip(b"\r").decode("ascii")
    except UnicodeDecodeError:
        return (-2, Bad.NOT_TEXT)
    if any(not (c.isprintable() or c == "\t") for c in text):
        return (-2, Bad.NOT_TEXT)
    words = text.replace(",", " ").split()
    if not words:
        return (-2, Bad.UNKNOWN_REQUEST)
    request, args = words[0].upper(), words[1:]
    if request in ("NEXT", "STATE"):
        if args:
            return (-2, Bad.BAD_ARGUMENT)
        return board.next(peer) if request == "NEXT" else (board.state_no(),)
    if request in REPORTS:
        no = _pick_no(args)
        if no is None:
            return (-2, Bad.BAD_ARGUMENT)
        return board.report(request, no, peer)
    return (-2, Bad.UNKNOWN_REQUEST)


def _pick_no(args: list[str]) -> int | None:
    """One whole number (a robot that only has floats may send 7.0)."""
    if len(args) != 1:
        return None
    try:
        v = float(args[0])
    except ValueError:
        return None
    if not math.isfinite(v) or v != int(v) or not 0 < v < 2**31:
        return None
    return int(v)


class RobotServer:
    """The TCP text protocol: an acceptor thread and one thread for the one robot connection.
    An address outside `allow` is closed at once (counted, alarmed); a second robot gets
    (-1,8) and is closed (counted); a line over max_line_bytes gets (-2,9) and is closed."""

    def __init__(self, cfg: RobotServerConfig, board: PickBoard):
        self.cfg, self.board = cfg, board
        self._allowed = [ipaddress.ip_network(a, strict=False) for a in cfg.allow]
        self.on_refused: Callable[[str], None] = lambda why: None  # the alarm (set by the line service)
        self.address: tuple[str, int] = (cfg.host, cfg.port)
        self._listener: socket.socket | None = None
        self._threads: list[threading.Thread] = []
        self._lock = threading.Lock()
        self._active: socket.socket | None = None
        self._active_peer = ""
        self._closing = threading.Event()

    @property
    def counts(self) -> collections.Counter[str]:
        return self.board.counts

    @property
    def connected(self) -> str:
        """The connected robot's address ('' when none)."""
        with self._lock:
            return self._active_peer if self._active is not None else ""

    def start(self) -> None:
        host, port = self.cfg.host, self.cfg.port
        s = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM)
        try:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind((host, port))
            s.listen(4)
        except OSError as e:
            s.close()
            raise ConnectionLost(
                f"the robot server cannot listen on {host}:{port}: {e.strerror or e}",
                port=f"tcp://{host}:{port}",
                hint="another program holds the port, or the address is not this machine's: "
                "set robot_server.port / robot_server.host",
            ) from None
        self._listener = s
        self.address = s.getsockname()[:2]
        t = threading.Thread(target=self._accept_loop, name="robot-server", daemon=True)
        t.start()
        self._threads.append(t)
        log.info("robot server listening on %s:%d", *self.address)

    def close(self) -> None:
        self._closing.set()
        with self._lock:
            active = self._active
        if active is not None:
            with contextlib.suppress(OSError):
                active.shutdown(socket.SHUT_RDWR)
        for t in self._threads:
            t.join(5.0)
        if self._listener is not None:
            self._listener.close()

    def _accept_loop(self) -> None:
        listener = self._listener
        assert listener is not None
        with selectors.DefaultSelector() as sel:
            sel.register(listener, selectors.EVENT_READ)
            while not self._closing.is_set():
                if not sel.select(0.2):
                    continue
                try:
                    conn, addr = listener.accept()
                except OSError:
                    continue
                try:
                    self._admit(conn, str(addr[0]))
                except Exception:  # one bad connection must not end the acceptor
                    log.exception("robot server: admitting a connection")
                    conn.close()

    def allowed(self, peer: str) -> bool:
        """Whether `peer` (an IP address) is in robot_server.allow."""
        try:
            ip = ipaddress.ip_address(peer.split("%")[0])
        except ValueError:
            return False
        if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
            ip = ip.ipv4_mapped
        return any(ip.version == n.version and ip in n for n in self._allowed)

    def _admit(self, conn: socket.socket, peer: str) -> None:
        if not self.allowed(peer):
            self.counts["refused_address"] += 1
            conn.close()
            why = f"a connection from {peer}, not in robot_server.allow, was refused"
            log.warning("robot server: %s", why)
            self.on_refused(why)
            return
        with self._lock:
            busy = self._active is not None
            if not busy:
                self._active, self._active_peer = conn, peer
        if busy:
            self.counts["refused_busy"] += 1
            log.warning("robot server: a second robot connection from %s refused (one at a time)", peer)
            with contextlib.suppress(OSError):
                conn.settimeout(1.0)
                conn.sendall(format_answer((-1, NotNow.BUSY)))
            conn.close()
            return
        self.counts["connections"] += 1
        log.info("robot server: robot connected from %s", peer)
        t = threading.Thread(target=self._serve, args=(conn, peer), name="robot-connection", daemon=True)
        self._threads = [x for x in self._threads if x.is_alive()] + [t]
        t.start()

    def _serve(self, conn: socket.socket, peer: str) -> None:
        limit = self.cfg.max_line_bytes
        buf = bytearray()
        try:
            conn.settimeout(0.2)
            while not self._closing.is_set():
                try:
                    data = conn.recv(4096)
                except TimeoutError:
                    continue
                if not data:
                    break
                buf += data
                while (i := buf.find(b"\n")) >= 0:
                    line = bytes(buf[:i])
                    del buf[: i + 1]
                    if len(line) > limit:
                        self._too_long(conn, peer)
                        return
                    answer = parse_line(line, self.board, peer)
                    if answer[0] == -2 and answer[1] in (Bad.UNKNOWN_REQUEST, Bad.BAD_ARGUMENT, Bad.NOT_TEXT):
                        self.counts["malformed"] += 1
                    conn.settimeout(5.0)
                    conn.sendall(format_answer(answer))
                    conn.settimeout(0.2)
                if len(buf) > limit:
                    self._too_long(conn, peer)
                    return
        except OSError as e:
            log.info("robot server: the connection from %s ended: %s", peer, e)
        finally:
            conn.close()
            with self._lock:
                self._active, self._active_peer = None, ""
            log.info("robot server: robot %s disconnected", peer)

    def _too_long(self, conn: socket.socket, peer: str) -> None:
        self.counts["too_long"] += 1
        log.warning("robot server: a line over %d bytes from %s: connection closed", self.cfg.max_line_bytes, peer)
        with contextlib.suppress(OSError):
            conn.settimeout(1.0)
            conn.sendall(format_answer((-2, Bad.TOO_LONG)))
            conn.shutdown(socket.SHUT_WR)
            # what the robot still sends is read and dropped (for at most 2 s): closed with unread data,
            # the connection would be reset and the robot might never read its answer
            end = time.monotonic() + 2.0
            while time.monotonic() < end and conn.recv(65536):
                pass


class RobotServerArm(Arm):
    """The arm the runner holds when a robot runs its own program (arm.kind 'robot-server'):
    its motions wait for the robot's reports; home, stop and the gripper move nothing (the
    robot's controller owns its motion and its safety). `serving()` listens for the life of
    the cell, across jobs; connect/disconnect open and close a job."""

    def __init__(self, cfg: RobotServerConfig):
        self.cfg = cfg
        self.board = PickBoard(cfg)
        self.server = RobotServer(cfg, self.board)
        self.port = f"tcp://{cfg.host}:{cfg.port}"
        self._connected = False
        self._pick: Pick | None = None
        self._cancelled: Callable[[], bool] = lambda: False
        self.modbus: Any = None  # drivers.arm.robot_modbus.RobotModbus while serving with modbus_port set

    @contextlib.contextmanager
    def serving(self) -> Iterator[RobotServer]:
        """Listen until the block ends (Modbus TCP too when modbus_port is set)."""
        self.server.start()
        host, port = self.server.address
        self.port = self.board.where = f"tcp://{host}:{port}"
        modbus = None
        try:
            if self.cfg.modbus_port:
                from drivers.arm.robot_modbus import RobotModbus  # pymodbus only when configured

                modbus = RobotModbus(
                    self.cfg.host,
                    self.cfg.modbus_port,
                    self.board,
                    self.server.allowed,
                    lambda why: self.server.on_refused(why),
                )
                modbus.start()
                self.modbus = modbus
            yield self.server
        finally:
            self.board.withdraw()
            if modbus is not None:
                modbus.close()
            self.server.close()

    @property
    def is_connected(self) -> bool:
        return self._connected

    def connect(self) -> None:
        self._connected = True
        self._pick = None
        self.board.job_open = True

    def disconnect(self) -> None:
        """The job's end (after its safe stop): an offer not taken is withdrawn, the pick forgotten."""
        self.board.withdraw()
        self.board.job_open = False
        self._connected = False
        self._pick = None

    def _require(self, command: str) -> None:
        if not self._connected:
            raise NotConnected(f"{command}: the robot server's arm is not connected", port=self.port)

    def home(self) -> None:
        """Nothing: the robot homes by its own program."""
        self._require("home")

    def check_target(self, x_mm: float, y_mm: float, z_mm: float, angle_deg: float | None = None) -> None:
        """Only that the numbers are numbers: the robot's controller knows its reach (planning.workspace
        is checked by the planner before)."""
        if not all(math.isfinite(v) for v in (x_mm, y_mm, z_mm, *(() if angle_deg is None else (angle_deg,)))):
            raise OutOfReach(f"target ({x_mm}, {y_mm}, {z_mm}) mm is not a number", port=self.port)

    def announce(self, plan: PickPlan, cancelled: Callable[[], bool]) -> None:
        self._require("announce")
        self._pick = self.board.offer(plan)
        self._cancelled = cancelled

    def move_to(
        self, x_mm: float, y_mm: float, z_mm: float, angle_deg: float | None = None, *, wait: bool = True
    ) -> None:
        """A motion of the pick announced: toward the part, wait for PICKED (or MISSED); over the
        bin, for PLACED (or MISSED). Without a pick there is nothing the cell can move."""
        self._require("move_to")
        self.check_target(x_mm, y_mm, z_mm, angle_deg)
        pick = self._pick
        if pick is None:
            raise ArmError(
                f"move_to ({x_mm:.1f}, {y_mm:.1f}, {z_mm:.1f}) mm: a robot running its own program is not moved "
                "by the cell; it is offered picks",
                port=self.port,
                hint="jog or home the robot from its own pendant",
            )
        bx, by, _ = pick.plan.bin_mm
        over_bin = math.isclose(x_mm, bx, abs_tol=1e-6) and math.isclose(y_mm, by, abs_tol=1e-6)
        self.board.wait(pick, frozenset({"placed"} if over_bin else {"picked"}), self._cancelled)

    def close_gripper(self) -> None:
        self._require("close_gripper")
        if self._pick is not None:
            self.board.wait(self._pick, frozenset({"picked"}), self._cancelled)

    def open_gripper(self) -> None:
        """Nothing to do, but a pick whose outcome is unknown cannot be said to be let go."""
        self._require("open_gripper")
        if self._pick is not None and self._pick.state == "unknown":
            raise PickUnknown(
                f"pick {self._pick.no}: the robot went silent; where the part is is unknown", port=self.port
            )

    def wait_until_idle(self, timeout_s: float | None = None) -> None:
        """Wait for the robot to end the pick it has (PLACED or MISSED; unknown after pick_timeout_s); an
        offer it has not taken is withdrawn."""
        self._require("wait_until_idle")
        if self._pick is not None:
            self.board.wait(self._pick, frozenset(), lambda: True)

    def stop(self) -> None:
        """Withdraws an offer not yet taken; the robot's own controller stops the robot."""
        self.board.withdraw()

    def unlock(self) -> None:
        """Nothing: the cell never held the robot's position."""

    def status(self) -> ArmStatus:
        peer = self.server.connected
        detail = f"robot connected from {peer}" if peer else "no robot connected"
        return ArmStatus("idle" if self._connected else "disconnected", None, None, detail)

    def take_reports(self) -> list[dict[str, Any]]:
        return self.board.take_records()
