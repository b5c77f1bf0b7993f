"""The Dynamixel driver through the ROBOTIS SDK against the emulated Protocol 2.0 bus on a pty."""

import math
import threading
import time

import pytest

from cell.sim.emulated_arm import EMULATED_LATENCY_TIMER_MS
from drivers.arm.config import DynamixelArmConfig
from drivers.arm.dynamixel import DynamixelArm, ExclusivePortHandler
from drivers.arm.errors import ConnectionLost, ErrorResponse, HardwareFault, NoResponse, OutOfReach, PositionLost
from drivers.arm.kinematics import FourAxisKinematics
from drivers.sim.dxl_emulator import SYNC_WRITE, DxlBusEmulator, packet
from drivers.sim.pty_port import serve_pty
from tests.faults import bus_writes, motion_writes

pytestmark = pytest.mark.timeout(60)  # opens a pty with the emulated servo bus

CFG = DynamixelArmConfig(move_timeout_s=2.0, poll_interval_s=0.01)
KIN = FourAxisKinematics(CFG)


@pytest.fixture
def bus():
    emu = DxlBusEmulator(CFG, speed_scale=10)
    with serve_pty(emu, "ttyDXL") as path:
        yield emu, path


def wait_still(emu) -> None:
    """Arrival is within tolerance: let the emulated servos finish their last ticks (exactly on their
    goals, not only within the half tick their position register rounds to: the register and the
    emulator's own pose then agree)."""
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline:
        with emu.lock:
            if all(s.position == s.get(116, 4) or not s.torque for s in emu.servos.values()):
                return
        time.sleep(0.005)


def make_arm(path: str, cfg: DynamixelArmConfig = CFG) -> DynamixelArm:
    return DynamixelArm(ExclusivePortHandler(path, EMULATED_LATENCY_TIMER_MS), cfg)


def torques(emu) -> list[bool]:
    emu.server.settle()  # sync writes get no reply: let the emulator take them in first
    with emu.lock:
        return [s.torque for s in emu.servos.values()]


def test_move_sends_one_sync_write_and_arrives(bus):
    emu, path = bus
    with make_arm(path) as arm:
        assert torques(emu) == [True] * 5
        arm.move_to(200.0, 50.0, 30.0)
        goals = KIN.to_ticks(KIN.inverse(200.0, 50.0, 30.0))
        params = bytes([116, 0, 4, 0]) + b"".join(
            bytes([i]) + g.to_bytes(4, "little") for i, g in zip(CFG.joint_ids, goals, strict=True)
        )
        assert packet(0xFE, SYNC_WRITE, params) in emu.packets_received
        wait_still(emu)
        assert [round(emu.servos[i].position) for i in CFG.joint_ids] == goals
        x, y, z, angle = emu.tool_pose()
        assert math.dist((x, y, z), (200.0, 50.0, 30.0)) < 0.5  # one tick is 0.088 deg
        assert angle == pytest.approx(math.degrees(math.atan2(50.0, 188.0)), abs=0.1)
        status = arm.status()
        assert (
            status.state == "idle"
            and math.dist((status.pose.x_mm, status.pose.y_mm, status.pose.z_mm), (x, y, z)) < 1e-9
        )


def test_gripper_listener_and_home(bus):
    emu, path = bus
    events = []
    emu.add_tool_listener(lambda *a: events.append(a))
    with make_arm(path) as arm:
        arm.move_to(180.0, -40.0, 20.0)
        wait_still(emu)
        arm.close_gripper()
        assert arm.status().gripper_closed is True
        arm.open_gripper()
        arm.home()
        wait_still(emu)
        assert [round(emu.servos[i].position) for i in CFG.joint_ids] == KIN.to_ticks(
            [math.radians(v) for v in CFG.home_joints_deg]
        )
    (closed, x, y, z, _), (opened, *_) = events
    assert closed and not opened
    assert math.dist((x, y, z), (180.0, -40.0, 20.0)) < 0.5


def test_unreachable_target_refused_before_anything_is_sent(bus):
    emu, path = bus
    with make_arm(path) as arm:
        emu.server.settle()
        before = len(emu.packets_received)
        with pytest.raises(OutOfReach, match="beyond the arm's reach"):
            arm.move_to(390.0, 0.0, 0.0)
        with pytest.raises(OutOfReach, match="joint 1 at"):
            arm.move_to(-150.0, 10.0, 50.0)
        assert len(emu.packets_received) == before
        assert torques(emu) == [True] * 5  # a refused target is not a fault


def test_overload_mid_move_is_a_hardware_fault_with_torque_released(bus):
    emu, path = bus
    with make_arm(path) as arm:
        emu.inject("overload", id=12, after_s=0.02)
        with pytest.raises(HardwareFault, match=r"servo 12: overload error") as info:
            arm.move_to(150.0, -80.0, 10.0)
        assert info.value.reply == "12: 0x20"
        assert torques(emu) == [False] * 5
        assert arm.status().state == "fault"
        with pytest.raises(HardwareFault):  # torque stays off until the servo is cleared
            arm.move_to(200.0, 0.0, 50.0)
        assert torques(emu) == [False] * 5


def test_no_answer_names_the_servo_and_times_out(bus):
    emu, path = bus
    emu.inject("no_answer", ids=[13])
    arm = make_arm(path)
    with pytest.raises(NoResponse, match="servo 13: no status packet") as info:
        arm.connect()
    assert "run-cell ports" in str(info.value)
    assert not arm.is_connected


def test_silent_bus_mid_move_releases_torque(bus):
    emu, path = bus
    with make_arm(path) as arm:
        emu.inject("no_answer")
        with pytest.raises(NoResponse) as info:
            arm.move_to(200.0, 0.0, 50.0)
        # the bus's silence is found by the packet timeouts, not by waiting out the move timeout
        assert "no status packet" in str(info.value) and "did not arrive" not in str(info.value)
        assert torques(emu) == [False] * 5  # sync writes need no answer: the torque-off got through


@pytest.mark.parametrize("fault", ["bad_crc", "garbage"])
def test_corrupt_status_packets_fail_cleanly(bus, fault):
    emu, path = bus
    with make_arm(path) as arm:
        emu.inject(fault, count=1000)  # every status packet, past all retries
        with pytest.raises(NoResponse, match="Incorrect status packet|no status packet"):
            arm.move_to(200.0, 0.0, 50.0)
        assert torques(emu) == [False] * 5


def test_single_bad_crc_is_retried(bus):
    emu, path = bus
    with make_arm(path) as arm:
        emu.inject("bad_crc", count=1)
        arm.move_to(200.0, 0.0, 50.0)
        assert torques(emu) == [True] * 5


def test_status_error_number_becomes_error_response(bus):
    emu, path = bus
    with make_arm(path) as arm:
        # Every status packet: the SDK's sync read drops error bytes; the gripper's write answer carries it.
        emu.inject("status_error", error=6, count=1000)
        with pytest.raises(ErrorResponse, match="data limit error") as info:
            arm.close_gripper()
        assert info.value.code == 6 and info.value.command == "close gripper"
        assert torques(emu) == [False] * 5


def test_slow_servos_time_out_with_torque_released(bus):
    emu, path = bus
    slow = CFG.model_copy(update={"profile_velocity": 1, "move_timeout_s": 0.3})
    with make_arm(path, slow) as arm:
        with pytest.raises(NoResponse, match="did not arrive within 0.3 s"):
            arm.move_to(200.0, 0.0, 50.0)
        assert torques(emu) == [False] * 5


def test_cable_pulled_mid_move_then_reconnects(bus):
    emu, path = bus
    with make_arm(path) as arm:
        emu.inject("unplug", after_s=0.02)
        with pytest.raises(ConnectionLost):
            arm.move_to(150.0, -80.0, 10.0)
        assert not arm.is_connected
        emu.replug()
        arm.move_to(200.0, 0.0, 50.0)
        assert arm.is_connected
        wait_still(emu)
        assert math.dist(emu.tool_pose()[:3], (200.0, 0.0, 50.0)) < 0.5


def test_missing_port_is_connection_lost(tmp_path):
    with pytest.raises(ConnectionLost, match="cannot open the servo bus"):
        make_arm(str(tmp_path / "ttyNOPE")).connect()


def test_reconnect_waits_for_the_adapter_to_come_back(bus):
    emu, path = bus
    with make_arm(path) as arm:
        barrier(arm)  # the servos have taken the torque on before the adapter goes
        emu.unplug()
        with pytest.raises(ConnectionLost):
            arm.move_to(200.0, 0.0, 50.0)
        replug = threading.Timer(0.3, emu.replug)
        replug.start()
        try:
            arm.move_to(200.0, 0.0, 50.0)
        finally:
            replug.join()
        assert arm.is_connected and torques(emu) == [True] * 5


def reboot_and_wait(emu, **params) -> int:
    """The servos' supply dips (all of them unless ids=...); returns the packet count at the restart."""
    before = len(emu.reboots)
    emu.inject("reboot", **params)
    deadline = time.monotonic() + 10.0
    while len(emu.reboots) == before:
        assert time.monotonic() < deadline, "no reboot"
        time.sleep(0.005)
    return emu.reboots[-1]


def barrier(arm) -> None:
    """A status read: the emulator answers it only after every packet sent before it, the
    sync writes that get no answer included (allowed while the position is lost)."""
    arm.status()


def assert_motion_refused(arm, emu) -> None:
    """Every motion command raises PositionLost and nothing at all reaches the bus."""
    barrier(arm)
    sent = len(emu.packets_received)
    for command in (lambda: arm.move_to(200.0, 0.0, 50.0), arm.open_gripper, arm.close_gripper, arm.wait_until_idle):
        with pytest.raises(PositionLost, match="^controller restarted: position lost; home before moving"):
            command()
    barrier(arm)
    assert len(emu.packets_received) == sent + 1  # the barrier's own sync read


def test_servo_restart_mid_move_locks_motion_until_homed(bus):
    emu, path = bus
    with make_arm(path) as arm:
        emu.inject("reboot", after_s=0.02)
        with pytest.raises(PositionLost) as info:
            arm.move_to(150.0, -80.0, 10.0)
        e = info.value
        assert (e.port, e.command) == (path, "move to (150.0, -80.0, 10.0) mm")
        assert e.reply == "torque off on servo 11, 12, 13, 14, 15, no hardware error: the driver had it on"
        assert "`run-cell home`" in str(e)
        assert_motion_refused(arm, emu)
        status = arm.status()
        assert (status.state, status.detail) == ("alarm", PositionLost.MESSAGE)
        since = len(emu.packets_received)
        arm.home()
        assert not arm.position_lost and torques(emu) == [True] * 5  # home polled the servos after torque on
        wait_still(emu)
        assert [round(emu.servos[i].position) for i in CFG.joint_ids] == KIN.to_ticks(
            [math.radians(v) for v in CFG.home_joints_deg]
        )
        # The restart reset the profiles to 0 (no speed limit): they are written before anything moves.
        addresses = [a for a, _ in bus_writes(emu, since)]
        assert addresses.index(108) < addresses.index(64) < addresses.index(116)
        assert emu.servos[11].get(112, 4) == CFG.profile_velocity
        arm.move_to(200.0, 0.0, 50.0)


def test_servo_restart_while_idle_is_found_before_the_next_move(bus):
    emu, path = bus
    with make_arm(path) as arm:
        arm.move_to(200.0, 0.0, 50.0)
        wait_still(emu)
        at = reboot_and_wait(emu, ids=[12])
        with pytest.raises(PositionLost, match="servo 12, no hardware error"):
            arm.move_to(150.0, -80.0, 10.0)
        barrier(arm)
        assert motion_writes(emu, at) == []  # no goal reached the bus after the restart
        assert torques(emu) == [False] * 5  # the servos that kept their torque let go too


def test_unlock_after_a_restart_holds_the_pose_without_moving(bus):
    emu, path = bus
    with make_arm(path) as arm:
        arm.move_to(200.0, 0.0, 50.0)
        wait_still(emu)
        at = reboot_and_wait(emu)
        with pytest.raises(PositionLost):
            arm.status()
        held = [round(s.position) for s in emu.servos.values()]
        arm.unlock()
        barrier(arm)
        assert not arm.position_lost and torques(emu) == [True] * 5
        # Since the restart: the torque-off on finding it, then the profiles and torque on; no goal.
        (off, _), (profiles, _), (on, values) = written = bus_writes(emu, at)
        assert (off, profiles, on) == (64, 108, 64) and written[0][1][1::2] == bytes(5) and values[1::2] == b"\1" * 5
        assert [round(s.position) for s in emu.servos.values()] == held
        arm.move_to(150.0, -80.0, 10.0)
        wait_still(emu)
        assert math.dist(emu.tool_pose()[:3], (150.0, -80.0, 10.0)) < 0.5


def test_cable_pulled_while_the_servos_restarted_locks_motion(bus):
    emu, path = bus
    with make_arm(path) as arm:
        barrier(arm)  # the servos have taken the torque on
        emu.unplug()
        with pytest.raises(ConnectionLost):
            arm.move_to(200.0, 0.0, 50.0)
        emu.replug(power_cycled=True)  # the adapter came back, and the servos' supply had dipped
        with pytest.raises(PositionLost, match="torque off on servo 11, 12, 13, 14, 15"):
            arm.move_to(200.0, 0.0, 50.0)  # reconnects, then refuses
        assert arm.is_connected and motion_writes(emu, emu.reboots[-1]) == []
        assert_motion_refused(arm, emu)
        arm.home()
        assert torques(emu) == [True] * 5
