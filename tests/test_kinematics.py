"""IK/FK of the 4-axis arm (OpenManipulator-X geometry): round trips and refusals."""

import math

import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from drivers.arm.config import DynamixelArmConfig
from drivers.arm.errors import OutOfReach
from drivers.arm.kinematics import FourAxisKinematics

CFG = DynamixelArmConfig()
K = FourAxisKinematics(CFG)
TOL_MM = 0.01


def joint(i):
    return st.floats(math.radians(CFG.joint_min_deg[i]), math.radians(CFG.joint_max_deg[i]))


def test_zero_pose_matches_robotis_geometry():
    p = K.forward((0.0, 0.0, 0.0, 0.0))
    # 12 (base to yaw axis) + 24 + 124 + 126 forward; 76.5 + 128 up, gripper horizontal.
    assert (p.x_mm, p.y_mm, p.z_mm, p.angle_deg) == pytest.approx((286.0, 0.0, 204.5, 0.0))


def test_ticks_follow_robotis_convention():
    assert K.to_ticks((0.0, 0.0, 0.0, 0.0)) == [2048, 2048, 2048, 2048]
    assert K.to_ticks((math.pi / 2, -math.pi / 2, 0.0, math.pi / 4)) == [3072, 1024, 2048, 2560]
    assert K.from_ticks([3072, 1024, 2048, 2560]) == pytest.approx((math.pi / 2, -math.pi / 2, 0.0, math.pi / 4))


@settings(max_examples=400, deadline=None)
@given(joint(0), joint(1), joint(2))
def test_round_trip_over_reachable_workspace(q1, q2, q3):
    q4 = math.pi / 2 - q2 - q3  # gripper pointing down
    assume(not K.limit_violation((q1, q2, q3, q4)))
    p = K.forward((q1, q2, q3, q4))
    assume(math.hypot(p.x_mm - CFG.geometry.yaw_axis_x_mm, p.y_mm) >= CFG.geometry.min_radius_mm)
    q = K.inverse(p.x_mm, p.y_mm, p.z_mm)
    back = K.forward(q)
    assert math.dist((back.x_mm, back.y_mm, back.z_mm), (p.x_mm, p.y_mm, p.z_mm)) < TOL_MM
    assert K.tool_pitch_rad(q) == pytest.approx(math.pi / 2)
    assert K.limit_violation(q) == ""


@settings(max_examples=400, deadline=None)
@given(st.floats(-400, 400), st.floats(-400, 400), st.floats(-150, 400))
def test_any_point_is_either_reached_exactly_or_refused(x, y, z):
    try:
        q = K.inverse(x, y, z)
    except OutOfReach:
        return
    back = K.forward(q)
    assert math.dist((back.x_mm, back.y_mm, back.z_mm), (x, y, z)) < TOL_MM
    assert K.limit_violation(q) == ""


@pytest.mark.parametrize(
    "target, reason",
    [
        ((600.0, 0.0, 0.0), "beyond the arm's reach"),
        ((12.0, 10.0, 50.0), "closer than dynamixel.geometry.min_radius_mm"),
        ((-150.0, 10.0, 50.0), r"joint 1 at 176.5 deg, outside its limits \[-162.0, 162.0\] deg"),
        ((80.0, 0.0, 150.0), "joint 4 at 126.2 deg"),
        ((float("nan"), 0.0, 0.0), "not a finite point"),
    ],
)
def test_unreachable_points_are_refused(target, reason):
    with pytest.raises(OutOfReach, match=reason):
        K.inverse(*target)


def test_angle_must_match_the_base_yaw_modulo_half_a_turn():
    q = K.inverse(200.0, 100.0, 20.0, angle_deg=math.degrees(math.atan2(100.0, 188.0)) + 180.0)
    assert math.degrees(q[0]) == pytest.approx(math.degrees(math.atan2(100.0, 188.0)))
    with pytest.raises(OutOfReach, match="gripper turns with its base"):
        K.inverse(200.0, 100.0, 20.0, angle_deg=90.0)
