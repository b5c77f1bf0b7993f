"""The robot protocol as Modbus TCP registers, for a PLC between the cell and its robot
(robot_server.modbus_port; the register map: docs/robots.md, "Modbus TCP").

The same PickBoard as the TCP text protocol answers every request: the PLC writes a request
and a new sequence number; a worker thread (never pymodbus's event loop, which only stores
what was written) asks the board, writes the answer registers, and last the answered sequence
number and the ready bit. Holding registers only (function codes 3, 6 and 16), 0-based
protocol addresses; 32-bit values are two registers, the high word first.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import logging
import queue
import struct
import threading
from collections.abc import Callable
from typing import Any

from pymodbus.constants import ExcCodes
from pymodbus.datastore import ModbusDeviceContext, ModbusSequentialDataBlock, ModbusServerContext
from pymodbus.server import ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler

from drivers.arm.errors import ConnectionLost
from drivers.arm.robot_server import Answer, Bad, PickBoard

log = logging.getLogger(__name__)


class Reg(enum.IntEnum):
    """Holding register addresses (0-based; 40001-style numbering adds 40001)."""

    REQUEST_SEQ = 0  # PLC: a new value (1-65535) takes the request; write it last (or all four in one write)
    REQUEST = 1  # PLC: 1 NEXT, 2 PICKED, 3 PLACED, 4 MISSED, 5 STATE
    REPORT_PICK_NO = 2  # PLC: 2 registers, uint32, high word first: the pick a report is about
    ANSWER_SEQ = 100  # cell: the REQUEST_SEQ answered (written last)
    READY = 101  # cell: 1 when the answer to the last REQUEST_SEQ is in place, 0 while working
    RESULT = 102  # cell: int16: 1 a pick / accepted, 0 nothing now, -1 cannot now, -2 not taken
    CODE = 103  # cell: the (-1,code) or (-2,code) code; 0 otherwise
    STATE = 104  # cell: STATE's state_no, kept current (every 0.5 s and with every answer)
    NOT_NOW = 105  # cell: the (-1,code) NEXT would get now (0: a pick can be given), kept current
    CLASS_NO = 106  # cell: the pick's class_no
    PICK_NO = 107  # cell: 2 registers, uint32, high word first
    X_MM = 110  # cell: float32 (2 registers, high word first): grip point x, robot frame
    Y_MM = 112
    Z_MM = 114
    ANGLE_DEG = 116
    BIN_X_MM = 118
    BIN_Y_MM = 120
    BIN_Z_MM = 122
    HEARTBEAT = 124  # cell: +1 at every refresh (about 2 per second): the PLC's watchdog
    END = 125


class Request(enum.IntEnum):
    NEXT = 1
    PICKED = 2
    PLACED = 3
    MISSED = 4
    STATE = 5


_FIRST_ANSWER = Reg.ANSWER_SEQ
REFRESH_S = 0.5


def float_words(v: float) -> list[int]:
    """A float32 as two registers, high word first."""
    hi, lo = struct.unpack(">HH", struct.pack(">f", v))
    return [hi, lo]


def words_float(words: list[int]) -> float:
    return float(struct.unpack(">f", struct.pack(">HH", *words))[0])


def uint32_words(v: int) -> list[int]:
    return [(v >> 16) & 0xFFFF, v & 0xFFFF]


def int16_word(v: int) -> int:
    return v & 0xFFFF


class _Registers(ModbusSequentialDataBlock):
    """The holding registers: the PLC may write only its own (0-3); a write of REQUEST_SEQ queues
    the request as written."""

    def __init__(self, requests: queue.Queue[tuple[int, int, int, str]]):
        super().__init__(1, [0] * (Reg.END + 1))  # type: ignore[no-untyped-call]  # the device context adds 1 to every protocol address
        self.requests = requests
        self.lock = threading.Lock()
        self.peer = ""

    def setValues(self, address: int, values: Any) -> None | ExcCodes:  # noqa: N802 - pymodbus's name
        values = values if isinstance(values, list) else [values]
        first = address - 1
        if first < 0 or first + len(values) > Reg.REPORT_PICK_NO + 2:
            return ExcCodes.ILLEGAL_ADDRESS  # the cell's registers are read-only
        with self.lock:
            result = super().setValues(address, values)
            if first <= Reg.REQUEST_SEQ < first + len(values):
                regs = self.values
                seq, request = regs[Reg.REQUEST_SEQ], regs[Reg.REQUEST]
                pick_no = (regs[Reg.REPORT_PICK_NO] << 16) | regs[Reg.REPORT_PICK_NO + 1]
                self.values[Reg.READY] = 0
                self.requests.put((seq, request, pick_no, self.peer))
        return result

    def put_answer(self, first: int, words: list[int]) -> None:
        with self.lock:
            self.values[first : first + len(words)] = words

    def answered(self, seq: int) -> None:
        """Last: the answer to `seq` is complete; ready unless the PLC has written a newer request."""
        with self.lock:
            self.values[Reg.ANSWER_SEQ] = seq
            self.values[Reg.READY] = int(self.values[Reg.REQUEST_SEQ] == seq)


class RobotModbus:
    """The Modbus TCP server on its own thread and event loop, and its worker thread."""

    def __init__(
        self,
        host: str,
        port: int,
        board: PickBoard,
        allowed: Callable[[str], bool],
        on_refused: Callable[[str], None],
    ):
        self.host, self.port, self.board = host, port, board
        self.allowed, self.on_refused = allowed, on_refused
        self._requests: queue.Queue[tuple[int, int, int, str]] = queue.Queue()
        self.registers = _Registers(self._requests)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._started = threading.Event()
        self._error: BaseException | None = None
        self._closing = threading.Event()
        self._threads: list[threading.Thread] = []

    def start(self) -> None:
        t = threading.Thread(target=self._serve, name="robot-modbus", daemon=True)
        t.start()
        self._started.wait(10.0)
        if self._error is not None or not self._started.is_set():
            self._closing.set()
            t.join(5.0)
            raise ConnectionLost(
                f"the robot server cannot listen for Modbus TCP on {self.host}:{self.port}: {self._error}",
                port=f"modbus://{self.host}:{self.port}",
                hint="another program holds the port, or the address is not this machine's: set "
                "robot_server.modbus_port (0 = off)",
            )
        w = threading.Thread(target=self._work, name="robot-modbus-worker", daemon=True)
        w.start()
        self._threads = [t, w]
        log.info("robot server: Modbus TCP on %s:%d", self.host, self.port)

    def close(self) -> None:
        self._closing.set()
        loop, stop = self._loop, self._stop
        if loop is not None and stop is not None:
            with contextlib.suppress(RuntimeError):  # the loop already ended
                loop.call_soon_threadsafe(stop.set)
        self._requests.put((-1, 0, 0, ""))
        for t in self._threads:
            t.join(5.0)

    # ---- pymodbus's thread ----------------------------------------------------------------------
    def _serve(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as e:  # reported by start()
            self._error = e
            self._started.set()

    async def _main(self) -> None:
        self._loop, self._stop = asyncio.get_running_loop(), asyncio.Event()
        context = ModbusServerContext(devices=ModbusDeviceContext(hr=self.registers), single=True)  # type: ignore[no-untyped-call]
        server = ModbusTcpServer(context, address=(self.host, self.port))
        owner = self

        class Handler(ServerRequestHandler):
            """Refuses an address outside robot_server.allow as soon as it connects."""

            def connection_made(self, transport: asyncio.BaseTransport) -> None:
                peer = transport.get_extra_info("peername")
                address = str(peer[0]) if peer else ""
                if not owner.allowed(address):
                    owner.board.counts["refused_address"] += 1
                    transport.close()
                    why = f"a Modbus TCP connection from {address}, not in robot_server.allow, was refused"
                    log.warning("robot server: %s", why)
                    owner.on_refused(why)
                    return
                owner.registers.peer = f"modbus {address}"
                super().connection_made(transport)

        server.callback_new_connection = lambda: Handler(server, None, None, None)  # type: ignore[method-assign,no-untyped-call]
        await server.serve_forever(background=True)
        self._started.set()
        await self._stop.wait()
        await server.shutdown()  # type: ignore[no-untyped-call]

    # ---- the worker: the board's answers into the registers -----------------------------------------
    def _work(self) -> None:
        heartbeat = 0
        while not self._closing.is_set():
            try:
                seq, request, pick_no, peer = self._requests.get(timeout=REFRESH_S)
            except queue.Empty:
                heartbeat = self._refresh(heartbeat)
                continue
            if seq < 0:
                return
            try:
                self._answer(seq, request, pick_no, peer)
            except Exception:  # the PLC gets (-2,1) rather than a server that stops answering
                log.exception("robot server: a Modbus request")
                self._write_answer(seq, (-2, Bad.UNKNOWN_REQUEST))
            heartbeat = self._refresh(heartbeat)

    def _refresh(self, heartbeat: int) -> int:
        code = self.board.not_now_code()
        self.registers.put_answer(Reg.STATE, [self.board.state_no(), int(code)])
        heartbeat = (heartbeat + 1) & 0xFFFF
        self.registers.put_answer(Reg.HEARTBEAT, [heartbeat])
        return heartbeat

    def _answer(self, seq: int, request: int, pick_no: int, peer: str) -> None:
        answer: Answer
        if request == Request.NEXT:
            answer = self.board.next(peer)
        elif request == Request.STATE:
            answer = (self.board.state_no(),)
        elif request in (Request.PICKED, Request.PLACED, Request.MISSED):
            if not 0 < pick_no < 2**31:
                answer = (-2, Bad.BAD_ARGUMENT)
            else:
                answer = self.board.report(Request(request).name, pick_no, peer)
        else:
            answer = (-2, Bad.UNKNOWN_REQUEST)
        self._write_answer(seq, answer)

    def _write_answer(self, seq: int, answer: Answer) -> None:
        result = int(answer[0])
        words = [0] * (Reg.HEARTBEAT - _FIRST_ANSWER)
        words[Reg.RESULT - _FIRST_ANSWER] = int16_word(result)
        if result in (-1, -2):
            words[Reg.CODE - _FIRST_ANSWER] = int(answer[1])
        if request_is_pick := (result == 1 and len(answer) == 10):
            _, x, y, z, angle, class_no, no, bx, by, bz = answer
            words[Reg.CLASS_NO - _FIRST_ANSWER] = int(class_no)
            words[Reg.PICK_NO - _FIRST_ANSWER : Reg.PICK_NO - _FIRST_ANSWER + 2] = uint32_words(int(no))
            for reg, v in zip(
                (Reg.X_MM, Reg.Y_MM, Reg.Z_MM, Reg.ANGLE_DEG, Reg.BIN_X_MM, Reg.BIN_Y_MM, Reg.BIN_Z_MM),
                (x, y, z, angle, bx, by, bz),
                strict=True,
            ):
                words[reg - _FIRST_ANSWER : reg - _FIRST_ANSWER + 2] = float_words(float(v))
        words[Reg.STATE - _FIRST_ANSWER] = self.board.state_no()
        words[Reg.NOT_NOW - _FIRST_ANSWER] = int(self.board.not_now_code())
        body = words[Reg.RESULT - _FIRST_ANSWER :]
        if not request_is_pick:  # a report or STATE leaves the last pick's target in place
            keep = Reg.CLASS_NO - Reg.RESULT
            with self.registers.lock:
                old = self.registers.values[Reg.CLASS_NO : Reg.HEARTBEAT]
            body[keep:] = old
        self.registers.put_answer(Reg.RESULT, body)
        self.registers.answered(seq)
