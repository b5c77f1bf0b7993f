"""`run-cell serve`: the cell as a long-running line service, driven over OPC UA (and the
operator screen); SIGTERM and SIGINT stop it safely (any job halted, arm safe)."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import getpass
import logging
import os
import signal
import socket
import threading
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Protocol, get_args

from cell.access.security import check_exposure, hash_password
from cell.access.throttle import Lockout, LoginThrottle
from cell.assembly import Overrides, assemble, attach_consumers, cell_config, rehearsal_config
from cell.config import CellConfig
from cell.core.commands import RUNNING, Command, CommandRefused, VisionState
from cell.core.eventbus import EventBus
from cell.core.events import SIGNAL_ORIGIN, RobotReported
from cell.errors import REPORTED_ERRORS, ConfigError
from cell.history.config import data_dir
from cell.locks import cell_lock
from cell.logretention import LogPruner
from cell.oplog import log_to_file
from cell.service.fdlimit import check_open_files
from cell.service.service import LineService
from cell.service.shiftlog import ShiftLog
from cell.shifts import ShiftCalendar
from cell.signals import STOP_SIGNALS
from drivers.arm.config import ArmKind
from drivers.arm.robot_server import CellStatus, RobotServerArm

log = logging.getLogger(__name__)


def register(sub) -> None:
    p = sub.add_parser(
        "serve",
        help="run the cell as a line service: OPC UA server, continuous mode, a whole shift",
        description="Run the cell as a line service: one process owns camera, calibration and arm; a PLC drives "
        "it over OPC UA, operators through the screen in a browser. Prints one `ready:` line with both "
        "addresses; SIGTERM or Ctrl-C halt it safely.",
    )
    # SUPPRESS: the same options given before `serve` (run-cell's own) still count.
    p.add_argument("--config", dest="run_config", type=Path, default=argparse.SUPPRESS, help="cell config (TOML)")
    p.add_argument(
        "--dry-run",
        action="store_true",
        default=argparse.SUPPRESS,
        help="a mock arm over the config's camera; with no --config, the built-in simulated shift",
    )
    p.add_argument(
        "--arm",
        choices=get_args(ArmKind),
        default=argparse.SUPPRESS,
        help="override arm.kind (with --dry-run and no --config: the emulated arm's sim config)",
    )
    p.add_argument("--log-dir", type=Path, default=argparse.SUPPRESS, help="override run.log_dir")
    p.add_argument("--opcua-port", type=int, help="override service.opcua_port")
    p.add_argument("--http-port", type=int, help="override service.http_port (the operator screen)")
    p.set_defaults(func=cmd_serve)

    h = sub.add_parser(
        "hash-password",
        help="read a password (twice, not echoed) and print its hash for service.password_hash",
        description="Read a password twice (not echoed) and print its PBKDF2 hash for service.password_hash.",
    )
    h.set_defaults(func=cmd_hash_password)


def cmd_hash_password(args: argparse.Namespace) -> int:
    first = getpass.getpass("password: ")
    if len(first) < 8 or first != getpass.getpass("again: "):
        raise ConfigError("the two passwords differ or are shorter than 8 characters: nothing printed")
    print(hash_password(first))
    return 0


def say(line: str) -> None:
    """A progress line for the operator (a closed terminal never stops the service)."""
    try:
        print(line, flush=True)
    except (OSError, ValueError):
        pass


def serve_config(args: argparse.Namespace) -> CellConfig:
    """The config `serve` runs, with the command line's overrides."""
    if args.run_config is None and not args.dry_run:
        raise ConfigError("give --config FILE to serve the cell, or --dry-run for the built-in simulated shift")
    overrides = Overrides(arm=args.arm, port=getattr(args, "port", None), log_dir=args.log_dir)
    config = cell_config(args.run_config, args.dry_run, overrides)
    for key in ("opcua_port", "http_port"):
        if getattr(args, key, None) is not None:
            if not 1 <= getattr(args, key) <= 65535:
                raise ConfigError(f"--{key.replace('_', '-')} {getattr(args, key)}: a port is 1-65535")
            setattr(config.service, key, getattr(args, key))
    return config


def open_service(
    config: CellConfig, dry_run: bool, resources: contextlib.ExitStack, progress=lambda line: None
) -> LineService:
    """The cell assembled for a shift (the simulated cell gets its feeder), the event bus with the
    shift's audit log as its record, and the service over them; everything to close goes on
    `resources` (the service first, then the record, the bus and its subscribers last). A dry run
    is a rehearsal: its history goes to a store of its own and its audit lines are marked, so
    production's counters, reports and OPC UA never count its picks (rehearsal_config)."""
    if dry_run:
        config = rehearsal_config(config)
    # one service per data folder, for as long as it runs (`run-cell restore` refuses a live cell by it)
    resources.enter_context(cell_lock(data_dir(config.history, config.run.log_dir)))
    bus = EventBus()
    resources.callback(bus.close)
    cell = assemble(config, dry_run, resources, shift=True, progress=progress)
    record = resources.enter_context(
        contextlib.closing(ShiftLog(config.run.log_dir, config.service.audit_max_bytes, rehearsal=dry_run))
    )
    consumers = contextlib.ExitStack()
    resources.callback(consumers.close)  # after the service has closed: they record its last events
    service = LineService(cell, bus, record)
    resources.callback(service.close)
    if isinstance(cell.arm, RobotServerArm):
        bind_robot_server(cell.arm, service)
        modbus = f", Modbus TCP on port {config.robot_server.modbus_port}" if config.robot_server.modbus_port else ""
        progress(f"robot server on {cell.arm.port.removeprefix('tcp://')}{modbus} (protocol: docs/robots.md)")
    attached = attach_consumers(config, bus, consumers, service, rehearsal=dry_run)
    service.history = attached.history
    if attached.history is not None:
        restore_ledger(service, config)
    # after the audit files were read back (crash recovery, the shift's counters): the oldest logs
    # beyond [logs] go now and at each roll of the audit file, never the running shift's
    pruner = LogPruner(
        config.logs,
        config.run.log_dir,
        live=lambda: (record.path,),
        shift_start=lambda: min(service.ledger.current_shift.start_utc, ShiftCalendar(config.shifts).now().start_utc),
    )
    pruner.prune()
    record.on_roll = pruner.prune
    return service


ROBOT_REFUSED = "robot-server-refused"  # the warning alarm's key after a connection from an address not allowed
_ROBOT_ALARM_S = 60.0  # how long that warning shows after the last such connection


def bind_robot_server(arm: RobotServerArm, service: LineService) -> None:
    """The robot server answers STATE and NEXT with the service's state, and a connection from an
    address not in robot_server.allow raises a warning alarm (cleared a minute after the last)."""

    def status() -> CellStatus:
        snap = service.snapshot()
        v = snap.vision_state
        if v in RUNNING:
            return "paused" if snap.paused else "waiting" if snap.waiting_for_parts else "running"
        if snap.hold:
            return "hold"
        at_rest: dict[VisionState, CellStatus] = {
            VisionState.PREOPERATIONAL: "starting",
            VisionState.HALTED: "halted",
            VisionState.ERROR: "error",
        }
        return at_rest.get(v, "ready")

    timers: list[threading.Timer] = []

    def refused(why: str) -> None:
        service.raise_warning(
            ROBOT_REFUSED,
            why,
            "only the robots in robot_server.allow may connect: if this was a robot, add its address; "
            "if not, tell the plant's IT",
            "robot server",
        )
        for t in timers:
            t.cancel()
        timer = threading.Timer(_ROBOT_ALARM_S, service.clear_warning, (ROBOT_REFUSED,))
        timer.daemon = True
        timer.start()
        timers[:] = [timer]

    def record(report: dict[str, Any]) -> None:  # a report while no job runs: recorded by the service
        service.bus.emit(RobotReported(**report))

    arm.board.status = status
    arm.board.record_between_jobs = record
    arm.server.on_refused = refused


def restore_ledger(service: LineService, config: CellConfig) -> None:
    """The running shift's counters and the last picks from the history store (after a restart);
    from the audit files where the store cannot be read (a PostgreSQL server away)."""
    from cell.history.query import open_reader

    shift = service.ledger.current_shift
    try:
        reader = open_reader(config)
    except REPORTED_ERRORS as e:
        log.warning("counters from the audit files: the history store cannot be read (%s)", e)
        service.prime_ledger_from_audit()
        return
    try:
        store = service.history  # on PostgreSQL its outbox's unsent rows count too (after an outage)
        if store is not None:
            counters, last = store.shift_view(reader, shift.start_utc, shift.end_utc)
        else:
            counters, last = reader.counters(shift.start_utc, shift.end_utc), reader.last_picks()
        service.ledger.restore(counters, last)
    except Exception as e:
        log.warning("counters from the audit files: the history store cannot be read (%s)", e)
        service.prime_ledger_from_audit()
    finally:
        reader.close()


def cmd_serve(args: argparse.Namespace) -> int:
    config = serve_config(args)
    check_exposure(config.service)
    _check_port_free(config.service.host, config.service.opcua_port, "--opcua-port")
    _check_port_free(config.service.host, config.service.http_port, "--http-port")
    stamp = datetime.now(UTC).strftime("%Y%m%d")
    if not args.verbose:
        for h in logging.getLogger().handlers:
            if type(h) is logging.StreamHandler:
                h.setLevel(logging.WARNING)
    log_to_file(config.run.log_dir / f"serve-{stamp}.log")
    check_open_files(config.service)  # issue 21: raise the soft limit, or warn (stderr and log), before clients come
    with contextlib.ExitStack() as resources:
        service = open_service(config, args.dry_run, resources, progress=say)
        service.start()
        # the service's config: a dry run's reads its own history store (rehearsal_config), as OPC UA's
        # results and the screen's history must
        return asyncio.run(_serve(service.config, service))


def _check_port_free(host: str, port: int, option: str) -> None:
    """Fail in a second, not after the devices and the calibration are up, when the port is taken."""
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as asyncio's server will
        try:
            s.bind((host, port))
        except OSError as e:
            raise ConfigError(
                f"cannot listen on {host}:{port}: {e.strerror or e}",
                hint=f"another program holds the port, or the address is not this machine's: "
                f"choose another with {option} or service.host",
            ) from None


class ServiceInterface(Protocol):
    """What `_serve` starts and stops: OPC UA, the screen."""

    @property
    def starting_text(self) -> str:
        """What is being started, said before start()."""

    @property
    def ready_text(self) -> str:
        """Where it listens, once started."""

    async def start(self) -> None: ...

    async def stop(self) -> None: ...


def lockout_alarm(service: LineService, lockout: Lockout) -> None:
    """A login lockout (screen or OPC UA) as a warning alarm, cleared when the lockout ends."""
    key = f"lockout:{lockout.kind}:{lockout.key}"
    service.raise_warning(
        key,
        f"{lockout.failures} failed logins for {lockout.kind} {lockout.key}: locked out for {lockout.lockout_s:g} s",
        "if these were not your own attempts, someone is guessing passwords: tell the plant's IT",
        "login",
    )
    timer = threading.Timer(lockout.lockout_s, service.clear_warning, (key,))
    timer.daemon = True
    timer.start()


def toggle_pause(service: LineService) -> None:
    """SIGUSR1, as for `run-cell`: Pause or Resume, through the command table like any client."""
    command = Command.RESUME if service.snapshot().pausing or service.snapshot().paused else Command.PAUSE
    try:
        service.command(command, SIGNAL_ORIGIN)
        log.info("SIGUSR1: %s", command.value)
    except CommandRefused as e:
        log.warning("SIGUSR1 ignored: %s", e)


async def _serve(config: CellConfig, service: LineService) -> int:
    """Interfaces up, one ready line, then wait for SIGTERM/SIGINT. Then, in order: no interface takes
    a command any more (each gets a clear refusal), the job halts safely, the interfaces go down.

    An interface is anything with `start()`, `stop()` (coroutines) and `ready_text`."""
    # imported here, not at the top: asyncua would cost every run-cell command 1.6-1.8 s (measured on 2 busy cores)
    from cell.service.opcua import OpcUaServer
    from cell.web.server import ScreenInterface

    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    previous = {sig: signal.getsignal(sig) for sig in (*STOP_SIGNALS, signal.SIGUSR1)}  # back afterwards
    for sig in STOP_SIGNALS:  # here a stop signal ends the service gracefully: job halted, clients told
        loop.add_signal_handler(sig, stop.set)
    loop.add_signal_handler(signal.SIGUSR1, toggle_pause, service)
    throttle = LoginThrottle(config.service.login, on_lockout=lambda lockout: lockout_alarm(service, lockout))
    interfaces: list[ServiceInterface] = [
        OpcUaServer(service, config, throttle),
        ScreenInterface(service, config, throttle),
    ]
    started: list[ServiceInterface] = []
    safe = True
    try:
        for interface in interfaces:
            say(f"starting {interface.starting_text}")
            await interface.start()
            started.append(interface)
        ready = "; ".join(i.ready_text for i in interfaces)
        print(f"ready: {ready} (pid {os.getpid()}; SIGTERM or Ctrl-C stops safely)", flush=True)
        await stop.wait()
        log.info("stop signal: refusing commands, halting the cell")
        service.refuse_commands()
        safe = await asyncio.to_thread(service.close)
    finally:
        for interface in reversed(started):
            await interface.stop()
        for sig, handler in previous.items():
            loop.remove_signal_handler(sig)
            signal.signal(sig, handler)
    if not safe:
        print(
            f"stopped: the arm's safe state could not be confirmed within {config.run.motion_timeout_s + 10:g} s "
            "(check the arm before anyone approaches it; exit 3)",
            flush=True,
        )
        return 3
    print("stopped: cell halted safely", flush=True)
    return 0
