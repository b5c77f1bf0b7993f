"""arm.kind robot-server (docs/robots.md): the cell as the vision server a robot's program asks,
over a real TCP socket. A client doing what the URScript program in docs/robots.md does clears
the dry-run table (history = counters = answers); bad input gets its documented answer and
records nothing twice; a robot that vanishes mid-pick faults the cell with the pick unknown."""

from __future__ import annotations

import contextlib
import json
import socket
import sqlite3
import threading
import time
from collections.abc import Iterator

import pytest

from cell.cli import main
from cell.commands.serve import open_service
from cell.core.commands import Command, VisionState
from cell.service.shiftlog import read_shift
from drivers.arm.base import PickPlan
from drivers.arm.config import RobotServerConfig
from drivers.arm.robot_server import Bad, NotNow, RobotServerArm, StateNo
from tests.ports import free_port
from tests.test_service import small_config, wait_for
from tests.test_taught_dry_run import BINS, KINDS, TYPES, images, recipe  # noqa: F401 (fixtures)

V = VisionState
pytestmark = pytest.mark.timeout(120)


class UrClient:
    """The URScript program's calls, one for one: socket_open, socket_send_line,
    socket_read_ascii_float (which returns [count, values...], [0] when it reads no answer)."""

    def __init__(self, address: tuple[str, int], source: str | None = None):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.settimeout(30.0)
        if source is not None:
            self.sock.bind((source, 0))
        self.sock.connect(address)
        self.file = self.sock.makefile("rb")

    def send_line(self, text: str) -> None:
        self.sock.sendall(text.encode("ascii") + b"\n")

    def read_ascii_float(self) -> list[float]:
        line = self.file.readline().decode("ascii").strip()
        if not (line.startswith("(") and line.endswith(")")):
            return [0]
        values = [float(v) for v in line[1:-1].split(",")]
        return [len(values), *values]

    def ask(self, text: str) -> list[float]:
        self.send_line(text)
        return self.read_ascii_float()[1:]

    def closed_by_server(self) -> bool:
        return self.file.readline() == b""

    def close(self) -> None:
        self.file.close()
        self.sock.close()


def robot_config(tmp_path, **server):
    cfg = small_config(tmp_path)
    cfg.sim.feeder = cfg.sim.feeder.model_copy(update={"parts_per_minute": 0, "clear_after_s": 0})
    cfg.sim.speed_factor = 600.0
    cfg.arm.kind = "robot-server"
    cfg.robot_server = RobotServerConfig(port=0, simulated_robot=False, next_wait_s=0.2, **server)
    return cfg


@contextlib.contextmanager
def serving(cfg) -> Iterator[tuple]:
    with contextlib.ExitStack() as stack:
        service = open_service(cfg, True, stack)
        service.start()
        arm = service.cell.arm
        assert isinstance(arm, RobotServerArm)
        yield service, arm.server.address


def robot_events(log_dir) -> list[dict]:
    return [e for e in read_shift(log_dir) if e["kind"] == "robot"]


def test_a_client_written_as_the_urscript_program_clears_the_dry_run_table(tmp_path):
    cfg = robot_config(tmp_path)
    with serving(cfg) as (service, address):
        robot = UrClient(address)
        assert robot.ask("STATE") == [StateNo.READY]
        assert robot.ask("NEXT") == [-1, NotNow.NOT_RUNNING]  # no job yet
        service.command(Command.START_SINGLE)
        placed, classes = [], set()
        while True:
            answer = robot.ask("NEXT")
            if answer[0] == 0:  # nothing this moment: the cell is looking
                continue
            if answer[0] == -1:
                assert answer == [-1, NotNow.NOT_RUNNING], answer  # the table is clear: the job ended
                break
            assert len(answer) == 10
            _, x_mm, y_mm, z_mm, angle_deg, class_no, pick_no, bin_x, bin_y, bin_z = answer
            classes.add(class_no)
            assert robot.ask("STATE") == [StateNo.TAKEN]
            assert robot.ask(f"PICKED {pick_no:.0f}") == [1]
            assert robot.ask("STATE") == [StateNo.PICKED]
            assert robot.ask(f"PLACED {pick_no:.0f}") == [1]
            placed.append(int(pick_no))
        robot.close()
        wait_for(lambda: service.snapshot().vision_state == V.READY, what="Ready after the job")
        counters = service.snapshot().counters
    assert classes == {1.0, 2.0}  # bolts and nuts
    assert len(placed) == len(set(placed)) == 17
    assert (counters.picked_of("bolt"), counters.picked_of("nut"), counters.unknown_left) == (9, 8, 1)
    (db_path,) = tmp_path.rglob("history.sqlite")
    with contextlib.closing(sqlite3.connect(db_path)) as db:
        history = db.execute("SELECT outcome, count(*) FROM picks GROUP BY outcome").fetchall()
    assert history == [("picked", 17)] == [("picked", counters.picked_total)]
    reports = robot_events(tmp_path / "logs")
    for kind in ("given", "picked", "placed"):
        assert sorted(e["pick_no"] for e in reports if e["report"] == kind) == sorted(placed)
    assert all(e["accepted"] for e in reports)


def taught_recipes(cfg, tmp_path, recipe_file) -> None:
    """The taught recipe (and its models) as the service's only recipe, `taught`; a perfect calibration."""
    import shutil

    cfg.sim.perfect_calibration = True
    cfg.service.machine_vision.recipes_dir = tmp_path / "recipes"
    (tmp_path / "recipes").mkdir()
    shutil.copy(recipe_file, tmp_path / "recipes" / "taught.toml")
    shutil.copytree(recipe_file.parent / "models", tmp_path / "recipes" / "models")


def start_on_taught_table(service, shapes) -> None:
    """Two of each taught type on the table, nothing else, their bins; recipe `taught` prepared, a job started."""
    from cell.core.commands import RecipeRequest
    from cell.sim.world import Bin, SimPart

    world = service.cell.sim.world
    poses = [(60.0, 60.0, 30.0), (200.0, 110.0, 200.0), (120.0, 140.0, 100.0), (230.0, 40.0, 300.0)]
    placed = [TYPES[shapes[k % 2].name].placed(*pose) for k, pose in enumerate(poses)]
    world.parts[:] = [SimPart(i + 1, p) for i, p in enumerate(placed)]
    world.bins[:0] = [Bin(name, BINS[name][:2], 40.0) for name in KINDS]
    world.version += 1
    service.command(Command.PREPARE_RECIPE, request=RecipeRequest("taught"))
    service.command(Command.START_SINGLE)


def test_a_taught_type_is_told_its_recipe_class_no_unless_class_numbers_overrides_it(tmp_path, recipe):  # noqa: F811
    """The prepared recipe's class_no reaches the robot (the planner's number, passed down in the pick): the
    L bracket its recipe's 3, written when it was taught; the plate 40, as robot_server.class_numbers says,
    over its recipe's 4. Each into its own bin."""

    from cell.recipes import load_recipe_file

    loaded, shapes = load_recipe_file(recipe)
    assert loaded.class_numbers() == {"bolt": 1, "nut": 2, "l-bracket": 3, "plate-4h": 4}
    cfg = robot_config(tmp_path, class_numbers={"bolt": 1, "nut": 2, "plate-4h": 40})
    taught_recipes(cfg, tmp_path, recipe)
    with serving(cfg) as (service, address):
        start_on_taught_table(service, shapes)
        robot = UrClient(address)
        told = []
        while (answer := robot.ask("NEXT"))[0] != -1:
            if answer[0] == 0:
                continue
            _, _, _, _, _, class_no, pick_no, bin_x, bin_y, bin_z = answer
            told.append((int(class_no), (bin_x, bin_y, bin_z)))
            assert robot.ask(f"PICKED {pick_no:.0f}") == [1]
            assert robot.ask(f"PLACED {pick_no:.0f}") == [1]
        robot.close()
        wait_for(lambda: service.snapshot().vision_state == V.READY, what="Ready after the job")
        picked = dict(service.snapshot().counters.picked)
    assert picked == {"l-bracket": 2, "plate-4h": 2}
    assert sorted(told) == sorted([(3, BINS["l-bracket"])] * 2 + [(40, BINS["plate-4h"])] * 2)


def test_a_robot_that_vanishes_mid_pick_faults_the_cell_with_the_pick_unknown(tmp_path):
    cfg = robot_config(tmp_path, pick_timeout_s=1.0, allow=["127.0.0.1"])
    with serving(cfg) as (service, address):
        stranger = UrClient(address, source="127.0.0.2")  # loopback too, but not allowed
        assert stranger.closed_by_server()
        stranger.close()
        wait_for(lambda: any(w.source == "robot server" for w in service.snapshot().warnings), what="the alarm")
        (warning,) = [w for w in service.snapshot().warnings if w.source == "robot server"]
        assert "127.0.0.2" in warning.reason
        service.command(Command.START_SINGLE)
        robot = UrClient(address)
        while (answer := robot.ask("NEXT"))[0] != 1:
            assert answer == [0], answer
        pick_no = int(answer[6])
        robot.close()  # gone with the pick
        wait_for(lambda: service.snapshot().vision_state == V.ERROR, what="the fault")
        alarm = service.snapshot().alarm
        assert alarm is not None and f"took pick {pick_no}" in alarm.reason and "unknown" in alarm.reason
        late = UrClient(address)
        assert late.ask(f"PICKED {pick_no}") == [-2, Bad.PICK_CLOSED]  # too late: nothing recorded
        assert late.ask("NEXT") == [-1, NotNow.FAULT]
        assert late.ask("STATE") == [StateNo.ERROR]
        service.command(Command.RESET)
        assert late.ask("STATE") == [StateNo.READY]
        late.close()
    events = read_shift(tmp_path / "logs")
    unknown = [e for e in events if e["kind"] == "robot" and e["report"] == "unknown"]
    assert [e["pick_no"] for e in unknown] == [pick_no]
    assert not [e for e in events if e["kind"] == "verify"]  # no verdict: where it went is unknown
    refused = [e for e in events if e["kind"] == "robot" and not e["accepted"]]
    assert [(e["report"], e["code"]) for e in refused] == [("picked", Bad.PICK_CLOSED)]


# ---- the protocol alone: the arm the runner holds, driven as the runner drives it ------------------


@contextlib.contextmanager
def lone_server(**kw) -> Iterator[RobotServerArm]:
    arm = RobotServerArm(RobotServerConfig(port=0, next_wait_s=0.1, **kw))
    with arm.serving():
        arm.connect()
        yield arm
        arm.disconnect()


PLAN = PickPlan("job-1", "nut", (120.0, 80.0, 2.0), 40.0, 15.0, (200.0, 20.0, 60.0))


def runner_pick(arm: RobotServerArm, outcome: list) -> threading.Thread:
    """The runner's PICK and PLACE motions on their own thread (as the control thread makes them)."""

    def run() -> None:
        try:
            arm.announce(PLAN, lambda: False)
            arm.move_to(120.0, 80.0, 40.0, 15.0)
            arm.close_gripper()
            arm.move_to(200.0, 20.0, 60.0)
            arm.open_gripper()
            outcome.append("done")
        except Exception as e:
            outcome.append(e)

    t = threading.Thread(target=run)
    t.start()
    return t


def test_garbage_and_half_lines_get_their_codes_and_the_connection_stays():
    with lone_server() as arm:
        robot = UrClient(arm.server.address)
        assert robot.ask("HELLO") == [-2, Bad.UNKNOWN_REQUEST]
        assert robot.ask("") == [-2, Bad.UNKNOWN_REQUEST]
        robot.sock.sendall(b"\xff\xfe\x00garbage\n")
        assert robot.read_ascii_float()[1:] == [-2, Bad.NOT_TEXT]
        assert robot.ask("PICKED") == [-2, Bad.BAD_ARGUMENT]
        assert robot.ask("PICKED seven") == [-2, Bad.BAD_ARGUMENT]
        assert robot.ask("PICKED 1.5") == [-2, Bad.BAD_ARGUMENT]
        assert robot.ask("NEXT now") == [-2, Bad.BAD_ARGUMENT]
        robot.sock.sendall(b"STA")  # half a line: nothing answered until its end comes
        robot.sock.sendall(b"TE\r\n")
        assert robot.read_ascii_float()[1:] == [StateNo.LOOKING]
        assert robot.ask("next") == [0]  # a job, nothing offered
        robot.close()
        assert arm.server.counts["malformed"] == 7


def test_a_1mb_line_closes_that_connection_and_the_server_keeps_serving():
    with lone_server() as arm:
        robot = UrClient(arm.server.address)
        with contextlib.suppress(OSError):  # the server may close before it has read it all
            robot.sock.sendall(b"N" * 1_000_000)
        assert robot.read_ascii_float()[1:] == [-2, Bad.TOO_LONG]
        assert robot.closed_by_server()
        robot.close()
        wait_for(lambda: arm.server.connected == "", what="the server to end the connection")
        again = UrClient(arm.server.address)  # the slot is free again
        assert again.ask("STATE") == [StateNo.LOOKING]
        again.close()
        assert arm.server.counts["too_long"] == 1


def test_a_second_robot_is_refused_and_counted_while_the_first_keeps_its_connection():
    with lone_server() as arm:
        first = UrClient(arm.server.address)
        assert first.ask("STATE") == [StateNo.LOOKING]
        second = UrClient(arm.server.address)
        assert second.read_ascii_float()[1:] == [-1, NotNow.BUSY]
        assert second.closed_by_server()
        second.close()
        assert first.ask("STATE") == [StateNo.LOOKING]
        first.close()
        assert arm.server.counts["refused_busy"] == 1


def test_reports_for_a_pick_never_given_twice_or_out_of_order_are_refused_and_recorded_once():
    with lone_server() as arm:
        robot = UrClient(arm.server.address)
        assert robot.ask("PICKED 1") == [-2, Bad.UNKNOWN_PICK]  # nothing given yet
        outcome: list = []
        t = runner_pick(arm, outcome)
        while (answer := robot.ask("NEXT"))[0] != 1:
            pass
        assert answer == [1, 120.0, 80.0, 2.0, 15.0, 2, answer[6], 200.0, 20.0, 60.0]
        no = int(answer[6])
        assert robot.ask("NEXT") == [-1, NotNow.PICK_OUTSTANDING]
        assert robot.ask(f"PLACED {no}") == [-2, Bad.OUT_OF_ORDER]
        assert robot.ask(f"PICKED {no + 1}") == [-2, Bad.UNKNOWN_PICK]
        assert robot.ask(f"PICKED {no}") == [1]
        assert robot.ask(f"PICKED {no}") == [-2, Bad.ALREADY_REPORTED]
        assert robot.ask(f"PLACED {no}.0") == [1]
        assert robot.ask(f"PLACED {no}") == [-2, Bad.ALREADY_REPORTED]
        assert robot.ask(f"MISSED {no}") == [-2, Bad.ALREADY_REPORTED]
        t.join(10)
        assert outcome == ["done"]
        robot.close()
        records = arm.take_reports()
        accepted = [(r["report"], r["pick_no"]) for r in records if r["accepted"]]
        assert accepted == [("given", no), ("picked", no), ("placed", no)]
        refused = [(r["report"], r["code"]) for r in records if not r["accepted"]]
        assert refused == [
            ("picked", Bad.UNKNOWN_PICK),
            ("placed", Bad.OUT_OF_ORDER),
            ("picked", Bad.UNKNOWN_PICK),
            ("picked", Bad.ALREADY_REPORTED),
            ("placed", Bad.ALREADY_REPORTED),
            ("missed", Bad.ALREADY_REPORTED),
        ]


def test_a_missed_pick_ends_it_and_the_place_waits_for_nothing():
    with lone_server() as arm:
        robot = UrClient(arm.server.address)
        outcome: list = []
        t = runner_pick(arm, outcome)
        while (answer := robot.ask("NEXT"))[0] != 1:
            pass
        assert robot.ask(f"MISSED {answer[6]:.0f}") == [1]
        t.join(10)
        assert outcome == ["done"]
        assert robot.ask(f"PLACED {answer[6]:.0f}") == [-2, Bad.OUT_OF_ORDER]
        robot.close()


def test_run_cell_dry_run_with_the_simulated_robot_clears_the_table_over_the_socket(tmp_path, capsys):
    cfg = tmp_path / "robot.toml"
    cfg.write_text(
        "[camera]\nwidth_px = 960\nheight_px = 540\n[sim]\nreference_marks_mm = []\n"
        f'[robot_server]\nport = 0\n[run]\nlog_dir = "{tmp_path / "logs"}"\n'
    )
    assert main(["--config", str(cfg), "--dry-run", "--arm", "robot-server"]) == 0
    out = capsys.readouterr().out
    assert "picked 9 bolts, 8 nuts; 0 misses" in out and "a simulated robot asks over it" in out
    events = [e for f in sorted((tmp_path / "logs").glob("run-*.jsonl")) for e in map(json.loads, f.open())]
    reports = [e["report"] for e in events if e["kind"] == "robot"]
    assert reports.count("given") == reports.count("picked") == reports.count("placed") == 17
    assert next(e for e in events if e["kind"] == "run_start")["arm"] == "RobotServerArm"


def test_docs_robots_md_lists_every_answer_code_and_state_number():
    import re
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "robots.md").read_text()

    def codes(heading: str) -> set[int]:
        section = text.split(heading, 1)[1].split("\n#", 1)[0]
        return {int(m) for m in re.findall(r"^\| (\d+) \|", section, re.M)}

    assert codes("### `(-1,code)`") == {int(c) for c in NotNow}
    assert codes("### `(-2,code)`") == {int(c) for c in Bad}
    assert codes("### STATE numbers") == {int(s) for s in StateNo}


class Plc:
    """What the structured-text PLC program in docs/robots.md does, over pymodbus: write the
    request, then a new sequence number; wait for ANSWER_SEQ = it and READY; read the answer."""

    def __init__(self, port: int):
        from pymodbus.client import ModbusTcpClient

        self.client = ModbusTcpClient("127.0.0.1", port=port, timeout=10)
        assert self.client.connect()
        self.seq = 0

    def ask(self, request: int, pick_no: int = 0) -> list[int]:
        from drivers.arm.robot_modbus import Reg

        self.seq = self.seq % 65535 + 1
        self.client.write_registers(Reg.REQUEST, [request, pick_no >> 16, pick_no & 0xFFFF])
        self.client.write_registers(Reg.REQUEST_SEQ, [self.seq])
        while True:  # the PLC's scan: read until the answer to this request is in place
            regs = self.client.read_holding_registers(Reg.ANSWER_SEQ, count=Reg.END - Reg.ANSWER_SEQ).registers
            if regs[0] == self.seq and regs[Reg.READY - Reg.ANSWER_SEQ] == 1:
                return regs
            time.sleep(0.005)  # the PLC's scan time

    def close(self) -> None:
        self.client.close()


def test_a_pymodbus_client_clears_the_dry_run_table_over_modbus_tcp(tmp_path):
    from drivers.arm.robot_modbus import Reg, Request, words_float

    def at(regs: list[int], reg: Reg) -> int:
        return regs[reg - Reg.ANSWER_SEQ]

    def signed(v: int) -> int:
        return v - 65536 if v >= 32768 else v

    cfg = robot_config(tmp_path, modbus_port=free_port())
    with serving(cfg) as (service, _):
        plc = Plc(cfg.robot_server.modbus_port)
        regs = plc.ask(Request.NEXT)
        assert (signed(at(regs, Reg.RESULT)), at(regs, Reg.CODE)) == (-1, NotNow.NOT_RUNNING)
        assert at(regs, Reg.STATE) == StateNo.READY
        refused = plc.client.write_registers(Reg.RESULT, [1])  # the cell's registers are read-only
        assert refused.isError()
        service.command(Command.START_SINGLE)
        placed = []
        while True:
            regs = plc.ask(Request.NEXT)
            result = signed(at(regs, Reg.RESULT))
            if result == 0:
                continue
            if result == -1:
                assert at(regs, Reg.CODE) == NotNow.NOT_RUNNING  # the table is clear: the job ended
                break
            assert result == 1
            no = (at(regs, Reg.PICK_NO) << 16) | at(regs, Reg.PICK_NO + 1)
            x, bin_z = (
                words_float(regs[r - Reg.ANSWER_SEQ : r - Reg.ANSWER_SEQ + 2]) for r in (Reg.X_MM, Reg.BIN_Z_MM)
            )
            assert at(regs, Reg.CLASS_NO) in (1, 2) and bin_z > 0 and x == x
            assert signed(at(plc.ask(Request.PICKED, no), Reg.RESULT)) == 1
            assert signed(at(plc.ask(Request.PLACED, no), Reg.RESULT)) == 1
            again = plc.ask(Request.PLACED, no)
            assert (signed(at(again, Reg.RESULT)), at(again, Reg.CODE)) == (-2, Bad.ALREADY_REPORTED)
            placed.append(no)
        plc.close()
        wait_for(lambda: service.snapshot().vision_state == V.READY, what="Ready after the job")
        counters = service.snapshot().counters
    assert len(placed) == len(set(placed)) == counters.picked_total == 17
    (db_path,) = tmp_path.rglob("history.sqlite")
    with contextlib.closing(sqlite3.connect(db_path)) as db:
        assert db.execute("SELECT outcome, count(*) FROM picks GROUP BY outcome").fetchall() == [("picked", 17)]
    reports = robot_events(tmp_path / "logs")
    assert sorted(e["pick_no"] for e in reports if e["report"] == "placed" and e["accepted"]) == sorted(placed)
    assert all(e["peer"].startswith("modbus ") for e in reports if e["report"] == "given")


def test_over_modbus_a_taught_type_reads_its_recipe_class_no_in_class_no(tmp_path, recipe):  # noqa: F811
    """CLASS_NO (register 106) of a pick of a taught type: the class_no its recipe gave it when it was taught
    (the L bracket 3, the plate 4), as the socket's answer says; the bin registers are the type's own."""

    from cell.recipes import load_recipe_file
    from drivers.arm.robot_modbus import Reg, Request, words_float

    def at(regs: list[int], reg: Reg) -> int:
        return regs[reg - Reg.ANSWER_SEQ]

    def signed(v: int) -> int:
        return v - 65536 if v >= 32768 else v

    loaded, shapes = load_recipe_file(recipe)
    assert loaded.class_numbers()["l-bracket"] == 3 and loaded.class_numbers()["plate-4h"] == 4
    cfg = robot_config(tmp_path, modbus_port=free_port())
    taught_recipes(cfg, tmp_path, recipe)
    with serving(cfg) as (service, _):
        start_on_taught_table(service, shapes)
        plc = Plc(cfg.robot_server.modbus_port)
        told = []
        while True:
            regs = plc.ask(Request.NEXT)
            result = signed(at(regs, Reg.RESULT))
            if result == 0:
                continue
            if result == -1:
                assert at(regs, Reg.CODE) == NotNow.NOT_RUNNING, regs  # the table is clear: the job ended
                break
            assert result == 1, regs
            no = (at(regs, Reg.PICK_NO) << 16) | at(regs, Reg.PICK_NO + 1)
            bin_mm = tuple(
                round(words_float(regs[r - Reg.ANSWER_SEQ : r - Reg.ANSWER_SEQ + 2]), 3)
                for r in (Reg.BIN_X_MM, Reg.BIN_Y_MM, Reg.BIN_Z_MM)
            )
            told.append((at(regs, Reg.CLASS_NO), bin_mm))
            assert signed(at(plc.ask(Request.PICKED, no), Reg.RESULT)) == 1
            assert signed(at(plc.ask(Request.PLACED, no), Reg.RESULT)) == 1
        plc.close()
        wait_for(lambda: service.snapshot().vision_state == V.READY, what="Ready after the job")
        picked = dict(service.snapshot().counters.picked)
    assert picked == {"l-bracket": 2, "plate-4h": 2}
    assert sorted(told) == sorted([(3, BINS["l-bracket"])] * 2 + [(4, BINS["plate-4h"])] * 2)


def test_a_halt_or_a_stop_withdraws_a_pick_no_robot_took_and_nothing_is_verified(tmp_path):
    with serving(robot_config(tmp_path)) as (service, address):
        robot = UrClient(address)
        for command, after in ((Command.HALT, V.HALTED), (Command.STOP, V.READY)):
            service.command(Command.START_SINGLE)
            wait_for(lambda: robot.ask("STATE") == [StateNo.OFFERED], what="a pick offered")
            service.command(command)  # no robot ever asked: the cell must not wait for one
            wait_for(lambda after=after: service.snapshot().vision_state == after, what=f"{after.value}")
            if after == V.HALTED:
                assert robot.ask("NEXT") == [-1, NotNow.HALTED]
                service.command(Command.RESET)
            else:
                assert robot.ask("NEXT") == [-1, NotNow.NOT_RUNNING]
        robot.close()
    events = read_shift(tmp_path / "logs")
    assert [e["report"] for e in events if e["kind"] == "robot"] == ["withdrawn", "withdrawn"]
    assert not [e for e in events if e["kind"] == "verify"]
    assert [e["outcome"] for e in events if e["kind"] == "job_end"] == ["halted", "stopped"]
