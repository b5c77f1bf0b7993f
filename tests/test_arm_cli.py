"""`run-cell ports / jog / home` end to end: the CLI opens a real pty with emulated firmware."""

import math
import time

import pytest

from cell.cli import main
from drivers.sim.dxl_emulator import DxlBusEmulator
from drivers.sim.pty_port import serve_pty

pytestmark = pytest.mark.timeout(60)  # opens a pty with emulated firmware


def test_jog_serial_at_grbl_defaults_ends_at_the_commanded_position(grbl, capsys):
    emu, path = grbl
    assert main(["jog", "--arm", "serial", "--port", path, "--to", "100", "50", "20"]) == 0
    assert emu.tool_pose()[:3] == (100.0, 50.0, 20.0)
    assert emu.state == "Idle"
    assert "idle, x=100.00 y=50.00 z=20.00 mm" in capsys.readouterr().out


def test_arm_and_port_before_the_sub_command_count_too(grbl):
    emu, path = grbl
    assert main(["--arm", "serial", "--port", path, "jog", "--to", "10", "20", "30"]) == 0
    assert emu.tool_pose()[:3] == (10.0, 20.0, 30.0)


def test_jog_gripper(grbl, capsys):
    emu, path = grbl
    assert main(["jog", "--arm", "serial", "--port", path, "--gripper", "close"]) == 0
    assert emu.gripper_closed
    assert "gripper closed" in capsys.readouterr().out


def test_jog_dynamixel_arrives(capsys):
    emu = DxlBusEmulator(speed_scale=10)
    with serve_pty(emu, "ttyDXL") as path:
        assert main(["jog", "--arm", "dynamixel", "--port", path, "--to", "200", "0", "50"]) == 0
        deadline = time.monotonic() + 1.0  # jog returns within tolerance; the servos finish their last ticks
        while math.dist(emu.tool_pose()[:3], (200.0, 0.0, 50.0)) >= 0.5 and time.monotonic() < deadline:
            time.sleep(0.005)
    assert math.dist(emu.tool_pose()[:3], (200.0, 0.0, 50.0)) < 0.5
    assert "arm on" in capsys.readouterr().out


def test_unreachable_jog_is_refused_before_connecting(grbl, capsys):
    emu, path = grbl
    assert main(["jog", "--arm", "serial", "--port", path, "--to", "500", "0", "0"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "x = 500 mm is outside the workspace" in err
    assert emu.lines_received == []


def test_home_at_grbl_defaults_explains_disabled_homing(grbl, capsys):
    _, path = grbl
    assert main(["home", "--arm", "serial", "--port", path]) == 2
    err = capsys.readouterr().err
    assert "error:5" in err and "$22" in err and err.count("\n") == 1


def test_home_moves_to_home_position_from_config(grbl, tmp_path):
    emu, path = grbl
    cfg = tmp_path / "cell.toml"
    cfg.write_text(
        f'[arm]\nkind = "serial"\nport = "{path}"\n'
        '[arm.serial]\nhome_position_mm = [5.0, 6.0, 7.0]\n[arm.serial.commands]\nhome = ""\n'
    )
    assert main(["home", "--config", str(cfg)]) == 0
    assert emu.tool_pose()[:3] == (5.0, 6.0, 7.0)


def test_no_device_at_port_is_one_clear_line(tmp_path, capsys):
    assert main(["jog", "--arm", "serial", "--port", str(tmp_path / "ttyUSB9"), "--to", "1", "2", "3"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cannot open serial port" in err and "run-cell ports" in err


def test_real_arm_without_port_is_a_config_error(capsys):
    assert main(["jog", "--arm", "dynamixel", "--to", "200", "0", "50"]) == 2
    assert capsys.readouterr().err == (
        "run-cell jog: error: arm.port is empty but arm.kind is 'dynamixel' (hint: set "
        "arm.port in the config or pass --port; `run-cell ports` lists the serial ports)\n"
    )


@pytest.mark.parametrize(
    "toml, message",
    [
        (
            '[arm]\nkind = "serial"\n[arm.serial]\nbaud = -5\n',
            "arm.serial.baud: Input should be greater than or equal to 300",
        ),
        ('[arm]\nkind = "robot"\n', "arm.kind: Input should be 'serial', 'dynamixel', 'mock', 'sim' or 'robot-server'"),
        ("[arm.serial]\nbaudrate = 9600\n", "arm.serial.baudrate: Extra inputs are not permitted"),
        ('[arm.serial.commands]\nfeed = "G1 X{x}"\n', "arm.serial.commands.feed: unknown placeholder {x}"),
        ("[arm.dynamixel]\ngripper_id = 12\n", "must be distinct"),
        (
            "[arm.serial.workspace]\nz_min_mm = 50.0\nz_max_mm = 10.0\n",
            "z_min_mm (50 mm) must be below z_max_mm (10 mm)",
        ),
        (
            '[arm.serial]\nstatus_query = false\n[arm.serial.commands]\nwait = ""\n',
            "the end of a move could not be known",
        ),
    ],
)
def test_bad_arm_config_names_the_key(tmp_path, capsys, toml, message):
    cfg = tmp_path / "cell.toml"
    cfg.write_text(toml)
    assert main(["jog", "--config", str(cfg), "--to", "1", "2", "3"]) == 2
    assert message in capsys.readouterr().err


def test_ports_lists_or_says_none(capsys):
    assert main(["ports"]) == 0
    assert capsys.readouterr().out.strip()
