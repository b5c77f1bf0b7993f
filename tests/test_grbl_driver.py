"""The serial G-code driver against the GRBL emulator on a real pseudo-terminal, via pyserial."""

import math
import threading
import time
from pathlib import Path

import pytest

from cell.config import load_config
from drivers.arm.config import SerialArmConfig, SerialCommands
from drivers.arm.errors import AlarmResponse, ConnectionLost, ErrorResponse, NoResponse, OutOfReach, PositionLost
from drivers.arm.serial_gcode import SerialGcodeArm, expected_move_s
from drivers.arm.serial_line import SerialLine
from drivers.sim.grbl_emulator import GrblEmulator
from drivers.sim.pty_port import serve_pty

pytestmark = pytest.mark.timeout(60)  # opens a pty with the emulated GRBL

FAST = dict(  # a fast emulator; the waits for an answer stay generous (the emulator's thread may wait for a core)
    command_timeout_s=5.0,
    motion_timeout_s=3.0,
    connect_timeout_s=5.0,
    reconnect_timeout_s=2.0,
    poll_interval_s=0.02,
    speed_mm_s=100.0,
)


def make_arm(path: str, **overrides) -> SerialGcodeArm:
    return SerialGcodeArm(SerialLine(path, 115200), SerialArmConfig(**{**FAST, **overrides}))


def assert_at(emu, x, y, z):
    assert emu.tool_pose()[:3] == pytest.approx((x, y, z), abs=1e-9)


def wait_for(condition, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "condition not met in time"
        time.sleep(0.01)


def restart_and_wait(emu) -> None:
    """The controller restarts at once (a power dip); return once it has."""
    before = len(emu.restarts)
    emu.inject("restart")
    wait_for(lambda: len(emu.restarts) > before)


def assert_motion_refused(arm, emu) -> None:
    """Every motion command raises PositionLost and nothing at all reaches the controller."""
    sent = list(emu.lines_received)
    for command in (
        lambda: arm.move_to(10, 10, 10),
        arm.open_gripper,
        arm.close_gripper,
        arm.wait_until_idle,
        lambda: (arm.wait_until_idle(), arm.move_to(10, 10, 10)),
    ):
        with pytest.raises(PositionLost, match="^controller restarted: position lost; home before moving"):
            command()
    emu.server.settle()
    assert emu.lines_received == sent


def test_move_ends_at_commanded_position_with_grbl_lines(grbl):
    emu, path = grbl
    with make_arm(path) as arm:
        assert arm.firmware == "Grbl 1.1h"
        arm.move_to(120.5, 40.25, 15.0)
        assert_at(emu, 120.5, 40.25, 15.0)
        assert emu.state == "Idle"
        status = arm.status()
        assert status.state == "idle"
        assert (status.pose.x_mm, status.pose.y_mm, status.pose.z_mm) == (120.5, 40.25, 15.0)
    assert emu.lines_received == ["G21", "G90", "G1 X120.500 Y40.250 Z15.000 F6000", "G4 P0"]


def test_gripper_close_and_open_reach_the_listener_at_the_tool_pose(grbl):
    emu, path = grbl
    events = []
    emu.add_tool_listener(lambda *a: events.append(a))
    with make_arm(path) as arm:
        arm.move_to(50, 60, 10)
        arm.close_gripper()
        arm.move_to(80, 20, 30)
        arm.open_gripper()
        assert arm.status().gripper_closed is False
    assert events == [(True, 50.0, 60.0, 10.0, 0.0), (False, 80.0, 20.0, 30.0, 0.0)]


def test_unreachable_target_refused_before_anything_is_sent(grbl):
    emu, path = grbl
    with make_arm(path) as arm:
        sent = list(emu.lines_received)
        with pytest.raises(OutOfReach, match=r"x = 250 mm is outside the workspace \[0, 200\] mm"):
            arm.move_to(250, 10, 10)
        with pytest.raises(OutOfReach, match=r"jaws at 30.0 deg, and this arm has no rotation axis: .* 30.0 deg off"):
            arm.move_to(10, 10, 10, angle_deg=30)
        assert emu.lines_received == sent


def test_an_arm_without_rotation_grips_at_its_fixed_jaw_angle_and_refuses_the_rest(grbl):
    """A 3-axis GRBL (issue 33): a grip within fixed_jaw_tolerance_deg of the fixed angle (jaw angles
    repeat every 180 deg) is made at that angle, no rotation line sent; any other is refused before
    anything is sent, saying what the jaws can do."""
    emu, path = grbl
    with make_arm(path, fixed_jaw_angle_deg=20.0, fixed_jaw_tolerance_deg=10.0) as arm:
        for angle in (25.0, 11.0, -165.0, 199.0):  # 5, 9, 5 and 1 deg off
            arm.move_to(40, 50, 10, angle_deg=angle)
            assert arm.status().pose.x_mm == pytest.approx(40.0)
            arm.move_to(60, 50, 10)
        sent = list(emu.lines_received)
        for angle in (31.0, -75.0, 110.0):  # 11, 85 and 90 deg off
            with pytest.raises(OutOfReach, match=r"its jaws close at 20.0 deg \(arm.serial.fixed_jaw_angle_deg\)"):
                arm.move_to(40, 50, 10, angle_deg=angle)
        assert emu.lines_received == sent
    assert not any(line.startswith(("G0 A", "G1 A")) for line in emu.lines_received)


def test_rotary_axis_by_configuration():
    emu = GrblEmulator(speed_scale=20, rotary_axis=True)
    with serve_pty(emu) as path:
        cmds = SerialCommands(rotate="G0 A{angle_deg:.2f}")
        with make_arm(path, commands=cmds) as arm:
            arm.move_to(30, 40, 5, angle_deg=45)
            assert arm.status().pose.angle_deg == 45.0
    assert emu.tool_pose() == (30.0, 40.0, 5.0, 45.0)


def test_error_reply_carries_code_meaning_port_and_command_and_holds(grbl):
    emu, path = grbl
    with make_arm(path) as arm:
        emu.inject("error", code=33)
        with pytest.raises(ErrorResponse) as info:
            arm.move_to(10, 10, 10)
        e = info.value
        assert (e.code, e.port, e.command, e.reply) == (33, path, "G1 X10.000 Y10.000 Z10.000 F6000", "error:33")
        assert "motion command has an invalid target" in str(e)
        assert emu.state in ("Hold:0", "Idle")
        # The next command flushes the held queue with a soft reset and works.
        arm.move_to(20, 20, 20)
        assert_at(emu, 20, 20, 20)


def test_alarm_mid_move_is_reported_and_never_unlocked(grbl):
    emu, path = grbl
    with make_arm(path) as arm:
        emu.inject("alarm", code=1, after_s=0.05)
        with pytest.raises(AlarmResponse) as info:
            arm.move_to(190, 190, 100)
        assert info.value.code == 1 and "hard limit" in str(info.value)
        assert "run-cell home" in str(info.value)
        assert emu.state == "Alarm"
        stopped_at = emu.tool_pose()
        sent = len(emu.lines_received)
        with pytest.raises(AlarmResponse, match="locked"):
            arm.move_to(10, 10, 10)
        assert len(emu.lines_received) == sent
        assert arm.status().state == "alarm"
    assert emu.tool_pose() == stopped_at
    assert "$X" not in emu.lines_received


def test_homing_required_at_start_up_then_home_unlocks_by_homing():
    emu = GrblEmulator(speed_scale=20, homing_enabled=True, start_mm=(30.0, 30.0, 30.0))
    with serve_pty(emu) as path, make_arm(path) as arm:
        assert arm.status().state == "alarm"
        with pytest.raises(AlarmResponse):
            arm.move_to(10, 10, 10)
        arm.home()
        assert_at(emu, 0, 0, 0)
        arm.move_to(10, 10, 10)
        assert_at(emu, 10, 10, 10)
    assert "$X" not in emu.lines_received


def test_home_with_homing_disabled_says_how_to_fix(grbl):
    _, path = grbl
    with make_arm(path) as arm:
        with pytest.raises(ErrorResponse, match=r"\$22"):
            arm.home()


def test_home_by_moving_when_no_homing_command(grbl):
    emu, path = grbl
    with make_arm(path, commands=SerialCommands(home=""), home_position_mm=(5.0, 6.0, 7.0)) as arm:
        arm.home()
    assert_at(emu, 5, 6, 7)


def test_no_answer_times_out_as_no_response(grbl):
    emu, path = grbl
    with make_arm(path, command_timeout_s=0.5) as arm:
        emu.inject("no_answer")
        with pytest.raises(NoResponse) as info:
            arm.move_to(10, 10, 10)
        # The configured command timeout (0.5 s here; 2 s by default) is the wait that gave up, not a wall time
        # read off a loaded machine; a wait that never gave up would end in pytest's timeout.
        assert "no reply within 0.5 s" in str(info.value)
        assert info.value.command.startswith("G1 X10.000") and info.value.port == path


def test_garbage_reply_is_an_error_naming_the_bytes(grbl):
    emu, path = grbl
    with make_arm(path) as arm:
        emu.inject("garbage")
        with pytest.raises(NoResponse, match="unreadable reply") as info:
            arm.move_to(10, 10, 10)
        assert "baud" in str(info.value)
        assert "\\x" in info.value.reply
        assert emu.state in ("Hold:0", "Idle")  # feed hold sent once the reply made no sense


def test_controller_restart_locks_motion_until_homed():
    emu = GrblEmulator(speed_scale=20, homing_enabled=True)
    with serve_pty(emu) as path, make_arm(path) as arm:
        arm.home()
        arm.move_to(50, 50, 50)
        arm.close_gripper()
        restart_and_wait(emu)
        with pytest.raises(PositionLost) as info:
            arm.move_to(60, 60, 60)
        e = info.value
        assert str(e).startswith("controller restarted: position lost; home before moving [")
        assert (e.port, e.command) == (path, "G1 X60.000 Y60.000 Z60.000 F6000")
        assert "Grbl 1.1h" in e.reply and "`run-cell home`" in str(e)
        assert arm.position_lost and emu.state == "Alarm"
        assert_motion_refused(arm, emu)
        status = arm.status()
        assert (status.state, status.detail) == ("alarm", PositionLost.MESSAGE)
        assert status.gripper_closed is False and not emu.gripper_closed  # the restart let go of the part
        assert_at(emu, 50, 50, 50)  # the tool stayed put; the controller counts from 0 again
        arm.home()  # the handshake again, then the homing cycle finds the physical zero
        assert not arm.position_lost
        assert_at(emu, 0, 0, 0)
        arm.move_to(10, 10, 10)
        assert_at(emu, 10, 10, 10)
    assert "$X" not in emu.lines_received


@pytest.mark.parametrize("homing_enabled", [True, False])
def test_unlock_trusts_the_restarted_controllers_position_and_sends_x_only_then(homing_enabled):
    emu = GrblEmulator(speed_scale=20, homing_enabled=homing_enabled)
    with serve_pty(emu) as path, make_arm(path, commands=SerialCommands(home="")) as arm:
        if homing_enabled:
            arm.unlock()  # at start-up GRBL waits for homing: the operator's unlock sends $X
            assert emu.lines_received.count("$X") == 1
        arm.move_to(20, 20, 20)
        restart_and_wait(emu)
        with pytest.raises(PositionLost):
            arm.wait_until_idle()
        with pytest.raises(PositionLost, match="no homing cycle") as info:
            arm.home()  # a move to home_position_mm would trust the restarted controller
        assert "unlock" in info.value.hint
        assert_motion_refused(arm, emu)
        arm.unlock()
        assert not arm.position_lost and emu.tool_pose()[:3] == (20.0, 20.0, 20.0)  # nothing moved
        # From now on the controller's count is the truth: it restarted at 0 with the tool at 20 mm.
        arm.move_to(10, 10, 10)
        assert emu.machine_position()[:3] == (10.0, 10.0, 10.0)
        assert_at(emu, 30, 30, 30)
    assert emu.lines_received.count("$X") == (2 if homing_enabled else 0)


def test_silent_device_at_connect_is_no_banner(grbl):
    emu, path = grbl
    emu.inject("no_answer")
    arm = make_arm(path, connect_timeout_s=0.5)
    with pytest.raises(NoResponse, match="no GRBL start-up banner"):
        arm.connect()
    assert not arm.is_connected


def test_missing_port_is_connection_lost_with_hint(tmp_path):
    arm = make_arm(str(tmp_path / "ttyNOPE"))
    with pytest.raises(ConnectionLost, match="cannot open serial port") as info:
        arm.connect()
    assert "run-cell ports" in str(info.value)


def test_cable_pulled_mid_move_then_reconnect_on_next_command(grbl):
    emu, path = grbl
    with make_arm(path) as arm:
        emu.inject("unplug", after_s=0.05)
        with pytest.raises(ConnectionLost):
            arm.move_to(190, 190, 100)
        assert not arm.is_connected
        wait_for(lambda: emu.state == "Idle")  # the controller ran its queue to the end meanwhile
        emu.replug()  # only the link comes back: the controller kept running
        arm.move_to(10, 20, 30)
        assert arm.is_connected and not arm.position_lost
        assert_at(emu, 10, 20, 30)


def test_cable_pulled_while_the_controller_restarted_locks_motion_until_homed():
    emu = GrblEmulator(speed_scale=20, homing_enabled=True)
    with serve_pty(emu) as path, make_arm(path) as arm:
        arm.home()
        arm.move_to(40, 30, 20)
        emu.unplug()
        with pytest.raises(ConnectionLost):
            arm.move_to(10, 10, 10)
        emu.replug(power_cycled=True)  # the adapter came back and the controller restarted meanwhile
        sent = list(emu.lines_received)
        with pytest.raises(PositionLost) as info:
            arm.move_to(10, 10, 10)  # reconnects, then refuses
        assert info.value.reply == (  # where it stood, or the end of the move that met the pulled cable
            "MPos (0.000, 0.000, 0.000) mm after reconnecting, where it was (40.000, 30.000, 20.000) mm"
            " or (10.000, 10.000, 10.000) mm"
        )
        assert arm.is_connected and emu.lines_received == sent  # only Ctrl-X and '?', no line
        assert_motion_refused(arm, emu)
        arm.home()
        arm.move_to(10, 10, 10)
        assert_at(emu, 10, 10, 10)


def test_stop_holds_the_feed_mid_move(grbl):
    emu, path = grbl
    with make_arm(path, speed_mm_s=5.0) as arm:
        arm.move_to(100, 0, 0, wait=False)
        deadline = time.monotonic() + 30
        while emu.tool_pose()[0] <= 0:  # under way
            assert time.monotonic() < deadline, "the move never started"
            time.sleep(0.01)
        arm.stop()
        assert emu.state == "Hold:0"
        x = emu.tool_pose()[0]
        assert 0 < x < 100
        time.sleep(0.1)
        assert emu.tool_pose()[0] == x


def test_spy_url_opens_through_serial_for_url(grbl, tmp_path):
    emu, path = grbl
    log_file = tmp_path / "spy.txt"
    with make_arm(f"spy://{path}?file={log_file}") as arm:
        arm.move_to(1, 2, 3)
    assert_at(emu, 1, 2, 3)
    assert "G1 X1.000" in log_file.read_text()


def test_reconnect_waits_for_the_cable_to_come_back(grbl):
    emu, path = grbl
    with make_arm(path) as arm:
        emu.unplug()
        with pytest.raises(ConnectionLost):
            arm.move_to(10, 10, 10)
        replug = threading.Timer(0.3, emu.replug)
        replug.start()
        try:
            arm.move_to(10, 20, 30)  # waits up to reconnect_timeout_s for the port to reappear
        finally:
            replug.join()
        assert_at(emu, 10, 20, 30)


def test_reconnect_gives_up_after_its_timeout(grbl):
    emu, path = grbl
    with make_arm(path, reconnect_timeout_s=0.2) as arm:
        emu.unplug()
        with pytest.raises(ConnectionLost):
            arm.move_to(10, 10, 10)
        with pytest.raises(ConnectionLost, match="cannot open serial port"):
            arm.move_to(10, 10, 10)


def test_firmware_without_status_reports_or_reset_by_configuration(grbl):
    emu, path = grbl
    with make_arm(path, status_query=False, soft_reset_on_connect=False) as arm:
        arm.move_to(40, 30, 20)  # the end of motion is known from the G4 P0 barrier alone
        assert_at(emu, 40, 30, 20)
        emu.unplug()
        with pytest.raises(ConnectionLost):
            arm.move_to(10, 10, 10)
        emu.replug()
        # Nothing can vouch for the position of a controller that does not report it.
        with pytest.raises(PositionLost, match="cannot be read back"):
            arm.move_to(10, 10, 10)
        assert_at(emu, 40, 30, 20)
    assert "?" not in "".join(emu.lines_received)


def shipped_grbl_config() -> SerialArmConfig:
    return load_config(Path("configs/arm-grbl.toml")).arm.serial


def test_shipped_grbl_config_moves_corner_to_corner_within_its_timeout():
    """The workspace's diagonal takes 37.5 s at the shipped feed (8 mm/s): more than the fixed
    30 s the timeout once was. The emulator runs 400 times faster than the machine; its own
    motion clock says how long the machine took, and the driver waits for longer than that."""
    cfg = shipped_grbl_config()
    ws = cfg.workspace
    far, near = (ws.x_max_mm, ws.y_max_mm, ws.z_max_mm), (ws.x_min_mm, ws.y_min_mm, ws.z_min_mm)
    emu = GrblEmulator(speed_scale=400)
    with serve_pty(emu) as path, SerialGcodeArm(SerialLine(path, cfg.baud), cfg) as arm:
        for corner in (far, near):
            before_s = emu.motion_time_s
            arm.move_to(*corner)
            assert_at(emu, *corner)
            machine_s = emu.motion_time_s - before_s
            assert machine_s == pytest.approx(37.5)  # 300 mm at 480 mm/min, in the emulator's time
            # GRBL also accelerates (the emulator does not): 8 mm/s at 10 * 300 / 200 mm/s^2 along the path.
            assert expected_move_s(cfg, near, far) == pytest.approx(37.5 + 8 / 15)
            assert arm.last_motion_timeout_s >= 1.5 * expected_move_s(cfg, near, far) + 2.0


def test_expected_move_time_follows_grbl_axis_limits():
    cfg = SerialArmConfig(speed_mm_s=100.0, acceleration_mm_s2=(1e9, 1e9, 1e9))
    # A feed above an axis' $110 is capped at it: 100 mm along X at 500 mm/min.
    assert expected_move_s(cfg, (0, 0, 0), (100, 0, 0)) == pytest.approx(12.0, rel=1e-6)
    # On a diagonal each axis may run at its own top rate: 100 mm/s along the path is 70.7 mm/s per axis.
    slow = cfg.model_copy(update=dict(max_rate_mm_min=(6000.0, 6000.0, 500.0)))
    assert expected_move_s(slow, (0, 0, 0), (100, 100, 0)) == pytest.approx(math.hypot(100, 100) / 100, rel=1e-6)
    rapid = slow.model_copy(update=dict(rapid_moves=True))
    assert expected_move_s(rapid, (0, 0, 0), (0, 0, 50)) == pytest.approx(6.0, rel=1e-6)  # Z's 500 mm/min
    assert expected_move_s(cfg, (5, 5, 5), (5, 5, 5)) == 0.0


def test_a_stalled_move_times_out_naming_its_expected_time():
    """The feed-hold input trips mid-move: the controller answers but nothing moves; the wait
    gives up after the move's own timeout and says what it expected."""
    emu = GrblEmulator(speed_scale=20)
    quick = dict(
        speed_mm_s=100.0,
        acceleration_mm_s2=(1000.0, 1000.0, 1000.0),
        max_rate_mm_min=(6000.0, 6000.0, 6000.0),
        motion_margin_factor=1.0,
        motion_margin_s=0.2,
        motion_timeout_s=0.5,
    )
    with serve_pty(emu) as path, make_arm(path, **quick) as arm:
        emu.inject("hold", after_s=0.001)
        with pytest.raises(NoResponse) as info:
            arm.move_to(100, 0, 0)  # 1 s at 100 mm/s, plus 0.1 s to reach the speed
        message = str(info.value)
        assert "motion not finished within 1.3 s (expected 1.1 s for the moves sent" in message
        assert "motion_margin_factor" in message and "$110-$112" in info.value.hint
        assert emu.state == "Hold:0"
        assert emu.motion_time_s < 1.0 and emu.tool_pose()[0] < 100  # it really stalled
