"""The mock arm (for --dry-run) refuses exactly what the real drivers refuse, and records the rest."""

import pytest
from dynamixel_sdk import PortHandler

from drivers.arm.config import ArmConfig
from drivers.arm.dynamixel import DynamixelArm
from drivers.arm.errors import NotConnected, OutOfReach
from drivers.arm.factory import make_arm, with_overrides
from drivers.arm.mock import MockArm, MockCommand
from drivers.arm.serial_gcode import SerialGcodeArm
from drivers.arm.serial_line import SerialLine

TARGETS = [
    (100.0, 50.0, 20.0, None),
    (250.0, 0.0, 0.0, None),
    (10.0, 10.0, 10.0, 30.0),
    (200.0, 0.0, 50.0, None),
    (390.0, 0.0, 0.0, None),
    (-150.0, 10.0, 50.0, None),
    (200.0, 100.0, 20.0, 90.0),
    (150.0, -80.0, 10.0, None),
]


def verdict(arm, target):
    try:
        arm.check_target(*target)
        return "ok"
    except OutOfReach as e:
        return str(e)


@pytest.mark.parametrize("kind", ["serial", "dynamixel"])
def test_mock_checks_targets_exactly_like_the_real_driver(kind):
    cfg = ArmConfig(kind="mock", mock_of=kind)
    real = (
        SerialGcodeArm(SerialLine("/dev/null", 115200), cfg.serial)
        if kind == "serial"
        else DynamixelArm(PortHandler("/dev/null"), cfg.dynamixel)
    )
    mock = MockArm(cfg)
    verdicts = [verdict(mock, t) for t in TARGETS]
    assert verdicts == [verdict(real, t) for t in TARGETS]
    assert "ok" in verdicts and any(v != "ok" for v in verdicts)


def test_mock_records_commands_with_their_wire_form_and_moves_nothing():
    with MockArm(ArmConfig(kind="mock", mock_of="serial")) as arm:
        arm.move_to(100.0, 50.0, 20.0)
        arm.close_gripper()
        with pytest.raises(OutOfReach):
            arm.move_to(500.0, 0.0, 0.0)
        assert arm.status().pose.x_mm == 100.0 and arm.status().gripper_closed
    assert list(arm.commands) == [
        MockCommand("connect"),
        MockCommand("move_to", (100.0, 50.0, 20.0, None), ("G1 X100.000 Y50.000 Z20.000 F3000",)),
        MockCommand("close_gripper"),
        MockCommand("disconnect"),
    ]


def test_mock_unlock_is_recorded_and_moves_nothing():
    """A mocked controller never restarts: unlock is what the real driver's would be, recorded."""
    with MockArm(ArmConfig(kind="mock", mock_of="serial")) as arm:
        arm.move_to(100.0, 50.0, 20.0)
        arm.unlock()
        assert arm.status().pose.x_mm == 100.0 and not arm.position_lost
    assert [c.name for c in arm.commands] == ["connect", "move_to", "unlock", "disconnect"]
    with pytest.raises(NotConnected):
        arm.unlock()


def test_mock_dynamixel_records_goal_ticks():
    with MockArm(ArmConfig(kind="mock", mock_of="dynamixel")) as arm:
        arm.move_to(200.0, 0.0, 50.0)
    ticks = arm.commands[1].wire
    assert len(ticks) == 4 and ticks[0] == 2048  # straight ahead: base yaw 0 rad


def test_mock_needs_connect():
    with pytest.raises(NotConnected):
        MockArm(ArmConfig()).move_to(10.0, 10.0, 10.0)


def test_factory_builds_each_kind_and_applies_overrides():
    cfg = ArmConfig()
    assert isinstance(make_arm(cfg), MockArm)
    assert isinstance(make_arm(with_overrides(cfg, kind="serial", port="socket://localhost:1")), SerialGcodeArm)
    arm = make_arm(with_overrides(cfg, kind="dynamixel", port="/dev/ttyUSB7"))
    assert isinstance(arm, DynamixelArm) and arm.port == "/dev/ttyUSB7"
    assert with_overrides(cfg) is cfg


def test_stand_in_arms_remember_only_their_last_commands():
    """A dry run or a rehearsal may run for days: the command record is bounded, newest last."""
    from cell.sim.sim_arm import SimArm
    from drivers.arm.config import Workspace
    from drivers.arm.mock import COMMANDS_KEPT
    from tests.test_simcell import NUT, world

    mock = MockArm(ArmConfig(kind="mock", mock_of="serial"))
    sim = SimArm(
        world(NUT), Workspace(x_min_mm=-300, x_max_mm=300, y_min_mm=-300, y_max_mm=300, z_min_mm=-10, z_max_mm=200)
    )
    for arm in (mock, sim):
        with arm:
            for i in range(COMMANDS_KEPT + 50):
                arm.move_to(100.0 + i % 7, 50.0, 20.0)
        assert len(arm.commands) == COMMANDS_KEPT
    assert mock.commands[-1] == MockCommand("disconnect")
    assert sim.commands[-1] == ("move_to", 106.0, 50.0, 20.0, None)  # the last of 1050 moves: i = 1049
