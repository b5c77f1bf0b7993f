"""Inverse and forward kinematics of a 4-axis arm with its gripper pointing straight down.

Joints, as ROBOTIS defines them on the OpenManipulator-X: 1 = base yaw about z (positive
turns x toward y), 2-4 = shoulder, elbow and wrist pitch about y (positive tips the link
down). At all zeros the upper arm stands up (offset forward), forearm and gripper point
forward. Angles in radians, lengths in mm, points in the robot base frame.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from drivers.arm.config import DynamixelArmConfig
from drivers.arm.errors import OutOfReach

TICKS_PER_RAD = 4096 / (2 * math.pi)

Joints = tuple[float, float, float, float]  # radians, base (1) to wrist (4)


@dataclass(frozen=True)
class Pose:
    """Tool point in the robot base frame, and the gripper's turn about the vertical."""

    x_mm: float
    y_mm: float
    z_mm: float
    angle_deg: float


class FourAxisKinematics:
    """IK/FK for the configured geometry and joint limits; refuses what it cannot reach."""

    def __init__(self, cfg: DynamixelArmConfig):
        g = cfg.geometry
        self.cfg = cfg
        self.g = g
        self.upper_mm = math.hypot(g.upper_arm_rise_mm, g.upper_arm_offset_mm)
        # Elevation of the upper arm above horizontal when joint 2 is at zero.
        self.upper_zero_rad = math.atan2(g.upper_arm_rise_mm, g.upper_arm_offset_mm)
        self.min_rad = [math.radians(v) for v in cfg.joint_min_deg]
        self.max_rad = [math.radians(v) for v in cfg.joint_max_deg]

    def forward(self, joints_rad: Joints) -> Pose:
        """Tool pose for joint angles; pose angle is the base yaw (no wrist roll)."""
        q1, q2, q3, q4 = joints_rad
        g = self.g
        r = (
            self.upper_mm * math.cos(self.upper_zero_rad - q2)
            + g.forearm_mm * math.cos(q2 + q3)
            + g.tool_mm * math.cos(q2 + q3 + q4)
        )
        z = (
            g.shoulder_height_mm
            + self.upper_mm * math.sin(self.upper_zero_rad - q2)
            - g.forearm_mm * math.sin(q2 + q3)
            - g.tool_mm * math.sin(q2 + q3 + q4)
        )
        return Pose(g.yaw_axis_x_mm + r * math.cos(q1), r * math.sin(q1), z, math.degrees(q1))

    def tool_pitch_rad(self, joints_rad: Joints) -> float:
        """Gripper pitch below horizontal; pi/2 is straight down."""
        return joints_rad[1] + joints_rad[2] + joints_rad[3]

    def inverse(self, x_mm: float, y_mm: float, z_mm: float, angle_deg: float | None = None) -> Joints:
        """Joint angles putting the tool point at (x, y, z), gripper down; OutOfReach if none."""
        where = f"({x_mm:.1f}, {y_mm:.1f}, {z_mm:.1f}) mm"
        if not all(math.isfinite(v) for v in (x_mm, y_mm, z_mm)):
            raise OutOfReach(f"target {where} is not a finite point")
        g = self.g
        px, py = x_mm - g.yaw_axis_x_mm, y_mm
        r = math.hypot(px, py)
        if r < g.min_radius_mm:
            raise OutOfReach(
                f"target {where} is {r:.1f} mm from the base axis, closer than "
                f"dynamixel.geometry.min_radius_mm ({g.min_radius_mm} mm)"
            )
        q1 = math.atan2(py, px)
        if angle_deg is not None:
            # A parallel gripper looks the same turned by 180 deg.
            diff = (angle_deg - math.degrees(q1) + 90.0) % 180.0 - 90.0
            if abs(diff) > self.cfg.angle_tolerance_deg:
                raise OutOfReach(
                    f"target {where} at angle {angle_deg:.1f} deg: a 4-axis arm's gripper turns with its base, "
                    f"which points at {math.degrees(q1):.1f} deg there",
                    hint="omit the angle or give the base's angle (within dynamixel.angle_tolerance_deg)",
                )
        # Wrist axis sits tool_mm straight above the tool point.
        dr, dz = r, z_mm + g.tool_mm - g.shoulder_height_mm
        d = math.hypot(dr, dz)
        l1, l2 = self.upper_mm, g.forearm_mm
        if d > l1 + l2 or d < abs(l1 - l2) or d == 0:
            raise OutOfReach(
                f"target {where} is beyond the arm's reach (wrist {d:.1f} mm from the shoulder; "
                f"reach {abs(l1 - l2):.1f} to {l1 + l2:.1f} mm)"
            )
        beta = math.atan2(dz, dr)
        gamma = math.acos(max(-1.0, min(1.0, (l1 * l1 + d * d - l2 * l2) / (2 * l1 * d))))
        refusal = ""
        for phi1 in (beta + gamma, beta - gamma):  # elbow up first, then elbow down
            er, ez = l1 * math.cos(phi1), l1 * math.sin(phi1)
            phi2 = math.atan2(dz - ez, dr - er)
            q2 = self.upper_zero_rad - phi1
            q3 = -phi2 - q2
            q4 = math.pi / 2 - q2 - q3
            joints = (_wrap(q1), _wrap(q2), _wrap(q3), _wrap(q4))
            violation = self.limit_violation(joints)
            if not violation:
                return joints
            refusal = refusal or violation  # report the preferred (elbow-up) solution's problem
        raise OutOfReach(f"target {where} needs {refusal}")

    def limit_violation(self, joints_rad: Sequence[float]) -> str:
        """Which joint leaves its limits, or '' if none."""
        for j, (q, lo, hi) in enumerate(zip(joints_rad, self.min_rad, self.max_rad, strict=True), start=1):
            if not lo - 1e-9 <= q <= hi + 1e-9:
                return (
                    f"joint {j} at {math.degrees(q):.1f} deg, outside its limits "
                    f"[{math.degrees(lo):.1f}, {math.degrees(hi):.1f}] deg"
                )
        return ""

    def to_ticks(self, joints_rad: Sequence[float]) -> list[int]:
        """Servo goal positions (2048 ticks = 0 rad by default)."""
        return [
            int(round(self.cfg.zero_ticks + d * q * TICKS_PER_RAD))
            for q, d in zip(joints_rad, self.cfg.joint_directions, strict=True)
        ]

    def from_ticks(self, ticks: Sequence[float]) -> Joints:
        """Joint angles for the four joints' servo positions (base to wrist)."""
        q = [
            (t - self.cfg.zero_ticks) / TICKS_PER_RAD * d for t, d in zip(ticks, self.cfg.joint_directions, strict=True)
        ]
        return q[0], q[1], q[2], q[3]


def _wrap(angle_rad: float) -> float:
    return (angle_rad + math.pi) % (2 * math.pi) - math.pi
