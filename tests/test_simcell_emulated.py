"""The simulated cell through the real arm drivers, from the command line: the serial G-code
driver against the emulated GRBL, the Dynamixel driver against the emulated servo bus, each
on a pseudo-terminal. The world changes only through the emulator's gripper events."""

from __future__ import annotations

import math
import threading
from pathlib import Path

import pytest

from cell.cli import main
from cell.config import load_config
from cell.summary import counts_from_log
from drivers.arm.kinematics import FourAxisKinematics
from tests.faults import capture_sim, fast_config, motion_writes
from tests.helpers import REPO, audit_of, ctrl_c_after_first_pick

pytestmark = pytest.mark.timeout(240)  # whole runs on a pty; one as a subprocess

CONFIGS = {"serial": REPO / "configs" / "sim-grbl.toml", "dynamixel": REPO / "configs" / "sim-dynamixel.toml"}
DRIVERS = {"serial": ("SerialGcodeArm", "ttyGRBL"), "dynamixel": ("DynamixelArm", "ttyDXL")}
CLEARED = {"bin:bolt": {"bolt": 9}, "bin:nut": {"nut": 8}, "table": {"washer": 1}}


def port_of(events: list[dict]) -> Path:
    return Path(next(e["arm_port"] for e in events if e["kind"] == "run_start"))


def assert_emulator_gone(events: list[dict]) -> None:
    assert not port_of(events).exists() and not port_of(events).parent.exists()
    assert not [t.name for t in threading.enumerate() if t.name.startswith("pty-")]


def moves(events: list[dict], home: tuple) -> list[tuple]:
    """Every motion command the cell gave, (x, y, z, angle) or 'home' or a gripper change."""
    out = []
    for e in events:
        if e["kind"] == "arm" and e["command"] == "move_to":
            out.append(tuple(e["args"]) + (None,) * (4 - len(e["args"])))
        elif (e["kind"] == "arm" and e["command"] == "home") or (e["kind"] == "safe_step" and e["step"] == "home"):
            out.append(home)
        elif e["kind"] == "arm" and e["command"] in ("open_gripper", "close_gripper"):
            out.append(e["command"])
    return out


def grbl_motion_s(events: list[dict]) -> float:
    """GRBL at its defaults: feed moves at the configured feed, jaw turns (G0 A) at 500 deg/min."""
    cfg = load_config(CONFIGS["serial"]).arm.serial
    at, angle, total = (0.0, 0.0, 0.0), 0.0, 0.0
    for m in moves(events, (*cfg.home_position_mm, None)):
        if isinstance(m, str):
            continue
        if m[3] is not None:
            total += abs(m[3] - angle) / (500.0 / 60.0)
            angle = m[3]
        total += math.dist(at, m[:3]) / cfg.speed_mm_s
        at = m[:3]
    return total


def dxl_motion_s(events: list[dict]) -> float:
    """Servos at profile velocity 100 (1563 ticks/s): each move lasts as long as its longest joint turn."""
    cfg = load_config(CONFIGS["dynamixel"]).arm.dynamixel
    kin = FourAxisKinematics(cfg)
    speed = cfg.profile_velocity * 0.229 / 60.0 * 4096.0
    home = kin.to_ticks([math.radians(v) for v in cfg.home_joints_deg])
    joints, gripper, total = home, cfg.gripper_open_ticks, 0.0
    for m in moves(events, "home"):
        if m in ("open_gripper", "close_gripper"):
            goal = cfg.gripper_closed_ticks if m == "close_gripper" else cfg.gripper_open_ticks
            total += abs(goal - gripper) / speed
            gripper = goal
            continue
        goal = home if m == "home" else kin.to_ticks(kin.inverse(*m[:3]))
        total += max(abs(a - b) for a, b in zip(goal, joints, strict=True)) / speed
        joints = goal
    return total


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["serial", "dynamixel"])
def test_the_pick_job_completes_through_the_real_driver_and_the_emulated_arm(kind, tmp_path, capsys):
    assert main(["--dry-run", "--arm", kind, "--log-dir", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    driver, tty = DRIVERS[kind]
    assert f"arm: the real {driver} driver against an emulated" in out
    assert "DONE: no pickable part left (0 failed, 0 unreachable)" in out
    events = audit_of(tmp_path)
    assert next(e for e in events if e["kind"] == "config")["source"] == str(CONFIGS[kind])
    assert next(e for e in events if e["kind"] == "sim_truth")["where"] == CLEARED
    summary = next(e for e in events if e["kind"] == "summary")
    assert {k: summary[k] for k in counts_from_log(events)} == counts_from_log(events)
    assert summary["picked"] == {"bolt": 9, "nut": 8} and summary["unknown_left"] == 1
    assert events[-1]["kind"] == "run_end" and events[-1]["exit_code"] == 0
    # The real driver on the emulator's pty got every command the audit log records.
    assert next(e for e in events if e["kind"] == "run_start")["arm"] == driver
    assert port_of(events).name == tty
    commands = [e["command"] for e in events if e["kind"] == "arm"]
    assert commands[:3] == ["connect", "home", "open_gripper"]
    assert commands.count("close_gripper") == summary["attempts"]
    angles = [e["args"][3] for e in events if e["kind"] == "arm" and e["command"] == "move_to" and len(e["args"]) > 3]
    assert len([a for a in angles if a is not None]) >= 3 * 9  # every bolt: approach, down, lift with the jaws turned
    # The motion time reported is the emulator's for the path commanded, at the arm's own speed.
    expected_s = grbl_motion_s(events) if kind == "serial" else dxl_motion_s(events)
    assert summary["motion_sim_s"] == pytest.approx(expected_s, rel=0.01)
    assert_emulator_gone(events)


@pytest.mark.slow
@pytest.mark.parametrize(
    "kind,reason,safe",
    [
        ("serial", "AlarmResponse: arm alarm 1: hard limit", "stopped (!)"),
        ("dynamixel", "HardwareFault: servo hardware error (servo 15: overload error)", "torque released"),
    ],
)
def test_a_fault_mid_job_ends_in_fault_with_the_arm_stopped(kind, reason, safe, tmp_path, capsys):
    text = CONFIGS[kind].read_text()
    assert "arm_fault_after_grips = 0" in text
    cfg = tmp_path / "fault.toml"
    cfg.write_text(text.replace("arm_fault_after_grips = 0", "arm_fault_after_grips = 3"))
    assert main(["--config", str(cfg), "--log-dir", str(tmp_path / "logs")]) == 3
    assert "FAULT: " + reason in capsys.readouterr().out
    events = audit_of(tmp_path / "logs")
    (fault,) = [e for e in events if e["kind"] == "fault"]
    assert fault["reason"].startswith(reason) and fault["state"] in ("pick", "place")
    assert events[-1]["kind"] == "run_end" and events[-1]["exit_code"] == 3 and events[-1]["state"] == "fault"
    steps = [(e["step"], e["ok"]) for e in events if e["kind"] == "safe_step"]
    assert steps[-1] == ("release torque", True)  # feed hold / torque off, confirmed by the arm
    assert not any(ok for step, ok in steps if step == "home")  # a faulted arm is not driven on
    (oplog,) = (tmp_path / "logs").glob("run-*.log")
    assert safe in oplog.read_text()
    where = next(e for e in events if e["kind"] == "sim_truth")["where"]
    assert sum(where.get("gripper", {}).values()) == 1  # the third part, gripped when the arm faulted
    assert sum(n for place, kinds in where.items() if place.startswith("bin:") for n in kinds.values()) == 2
    assert_emulator_gone(events)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["serial", "dynamixel"])
def test_a_controller_restart_mid_job_faults_and_nothing_moves_after_it(kind, tmp_path, capsys, monkeypatch):
    """GRBL restarts (its banner mid-run), or every servo's supply dips, as the first grip closes: the real
    driver latches PositionLost, the run faults with it, and from the restart on nothing that
    moves reaches the emulated arm: no motion line, no goal and no torque on; the safe
    stop does not home either (that is for the operator, after a look at the arm)."""
    cfg = fast_config(tmp_path, kind)
    text = cfg.read_text()
    assert "arm_fault_after_grips = 0" in text and 'arm_fault = "alarm"' in text
    cfg.write_text(
        text.replace("arm_fault_after_grips = 0", "arm_fault_after_grips = 1").replace(
            'arm_fault = "alarm"', 'arm_fault = "restart"'
        )
    )
    got = capture_sim(monkeypatch)
    assert main(["--config", str(cfg), "--log-dir", str(tmp_path / "logs")]) == 3
    reason = "PositionLost: controller restarted: position lost; home before moving"
    assert "FAULT: " + reason in capsys.readouterr().out
    events = audit_of(tmp_path / "logs")
    (fault,) = [e for e in events if e["kind"] == "fault"]
    assert fault["reason"].startswith(reason) and "`run-cell home`" in fault["reason"]
    steps = {e["step"]: e for e in events if e["kind"] == "safe_step"}
    assert "not homed: the arm's controller restarted" in steps["home"]["error"]
    assert steps["release torque"]["ok"]
    emu = got.cell.emulated.emulator
    if kind == "serial":
        (at,) = emu.restarts
        # At most the wait barrier (G4 P0, no motion) the driver sent before the banner reached it.
        assert [line for line in emu.lines_received[at:] if line != "G4 P0"] == []
    else:
        (at,) = emu.reboots
        assert motion_writes(emu, at) == []
        assert not any(s.torque for s in emu.servos.values())
    where = next(e for e in events if e["kind"] == "sim_truth")["where"]
    assert sum(where.get("gripper", {}).values()) == 0  # the restarted gripper let go of the part
    assert sum(n for place, kinds in where.items() if place.startswith("bin:") for n in kinds.values()) == 0
    assert_emulator_gone(events)


@pytest.mark.slow
def test_ctrl_c_stops_the_emulated_arm_safely_and_removes_its_pty(tmp_path):
    code, rest = ctrl_c_after_first_pick("--dry-run", "--arm", "dynamixel", "--log-dir", str(tmp_path))
    assert code == 130
    assert "STOPPED: Ctrl-C" in rest
    events = audit_of(tmp_path)
    steps = [e["step"] for e in events if e["kind"] == "safe_step" and e["ok"]]
    assert steps[-2:] == ["home", "release torque"]
    assert events[-1]["kind"] == "run_end" and events[-1]["state"] == "stopped"
    assert not port_of(events).exists() and not port_of(events).parent.exists()


def test_a_layout_out_of_the_arms_reach_is_refused_before_anything_moves(tmp_path, capsys):
    """The built-in table (robot x -132..132 mm) against a gantry's default 0..200 mm travel."""
    cfg = tmp_path / "sim-serial.toml"
    cfg.write_text(f'[arm]\nkind = "serial"\n[sim]\nperfect_calibration = true\n[run]\nlog_dir = "{tmp_path}"\n')
    assert main(["--config", str(cfg)]) == 3
    assert "bins out of reach: bolt bin: target (-200.0, 60.0, 60.0) mm: x = -200" in capsys.readouterr().out
    events = audit_of(tmp_path)
    assert [e["command"] for e in events if e["kind"] == "arm"] == ["connect"]
    assert_emulator_gone(events)


def test_a_gantry_without_a_rotation_axis_picks_the_bolts_its_fixed_jaws_grip(tmp_path, capsys):
    """A 3-axis GRBL (issue 33): no rotation command, the jaws close at arm.serial.fixed_jaw_angle_deg.
    With every bolt laid across that angle (layout paper-fixed-jaws) the table is cleared through the
    real driver and the emulated GRBL, each bolt gripped with no turn of the jaws; a bolt at another
    angle is refused before any motion, saying why (tests/test_grbl_driver.py)."""
    base = CONFIGS["serial"].read_text()
    assert 'rotate = "G0 A{angle_deg:.2f}"' in base and 'layout = "paper"' in base
    text = base.replace('rotate = "G0 A{angle_deg:.2f}"', 'rotate = ""').replace(
        'layout = "paper"', 'layout = "paper-fixed-jaws"'
    )
    text = text.replace("[arm.serial]\n", "[arm.serial]\nfixed_jaw_angle_deg = -45.0\n", 1)
    text = text.replace("width_px = 1920\nheight_px = 1080", "width_px = 1280\nheight_px = 720")  # faster
    cfg = tmp_path / "gantry-3-axis.toml"
    cfg.write_text(text)
    assert main(["--config", str(cfg), "--log-dir", str(tmp_path)]) == 0
    assert "DONE: no pickable part left (0 failed, 0 unreachable)" in capsys.readouterr().out
    events = audit_of(tmp_path)
    summary = next(e for e in events if e["kind"] == "summary")
    assert summary["picked"] == {"bolt": 9, "nut": 8} and summary["misses"] == 0
    jaws = [e["jaw_angle_deg"] for e in events if e["kind"] == "target" and e["cls"] == "bolt"]
    assert len(jaws) == 9 and all(abs((a + 45.0 + 90.0) % 180.0 - 90.0) <= 5.0 for a in jaws), jaws
    assert_emulator_gone(events)
