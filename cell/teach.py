"""Teaching the table -> robot frame: the gripper is jogged onto known plate circles, each
pair (circle's table mm, gripper's robot mm) recorded, and a rigid transform fitted.

A fit is refused when its largest residual exceeds planning.teach_max_residual_mm: one
badly jogged circle must not silently tilt every target.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from cell.config import CellConfig
from cell.errors import InputError
from cell.planning import TableToRobot, TeachRejected, fit_table_to_robot, load_taught
from drivers.arm.base import Arm
from drivers.arm.errors import OutOfReach

JOG_HELP = (
    "commands: 'x 1.5', 'y -0.5', 'z -10' (relative mm), 'to X Y Z' (absolute), "
    "'ok' to record this circle, 'skip', 'quit'"
)


@dataclass(frozen=True)
class TaughtPoint:
    circle: int
    table_mm: tuple[float, float]
    robot_mm: tuple[float, float]

    def to_dict(self) -> dict:
        return {"circle": self.circle, "table_mm": list(self.table_mm), "robot_mm": list(self.robot_mm)}


def circle_table_mm(number: int, config: CellConfig) -> tuple[float, float]:
    """Table position of plate circle `number` (1 = point 1, numbered row by row)."""
    plate = config.plate
    if not 1 <= number <= plate.count:
        raise InputError(f"circle {number} does not exist: the plate has circles 1 to {plate.count}")
    row, col = divmod(number - 1, plate.columns)
    return col * plate.pitch_x_mm, row * plate.pitch_y_mm


def expected_frame(config: CellConfig) -> tuple[TableToRobot, str]:
    """Where the circles should be before teaching: the taught frame if there is one (teaching
    again), else planning.offset_x_mm / offset_y_mm; and words saying which."""
    cfg = config.planning
    if cfg.frame == "taught" and cfg.taught_path.exists():
        return load_taught(cfg.taught_path), f"the taught frame {cfg.taught_path}"
    offset = f"planning.offset_x_mm {cfg.offset_x_mm:g} mm, offset_y_mm {cfg.offset_y_mm:g} mm"
    return TableToRobot.from_offset(cfg), offset


def check_circles_reachable(arm: Arm, circles: list[int], config: CellConfig) -> None:
    """InputError, before anything moves, naming every chosen circle whose expected robot
    position (expected_frame, at the table's height) the arm refuses: outside its workspace
    or reach. A jog towards one would stop at the arm's limit, half-way through the session."""
    frame, source = expected_frame(config)
    z_mm = config.planning.table_z_mm

    def refusal(circle: int) -> str | None:
        rx, ry = frame.to_robot([circle_table_mm(circle, config)])[0]
        try:
            arm.check_target(float(rx), float(ry), z_mm)
        except OutOfReach as e:
            return f"circle {circle} at robot ({rx:.1f}, {ry:.1f}) mm: {e.args[0]}"
        return None

    for circle in circles:
        circle_table_mm(circle, config)  # the circle exists
    refused = [(c, why) for c in circles if (why := refusal(c)) is not None]
    if not refused:
        return
    inside = [n for n in range(1, config.plate.count + 1) if refusal(n) is None]
    names = ", ".join(str(c) for c, _ in refused)
    raise InputError(
        (f"circles {names} lie" if len(refused) > 1 else f"circle {names} lies")
        + f" outside the arm's reach by {source}; "
        f"nothing moved: " + "; ".join(why for _, why in refused),
        hint=_circles_hint(inside, config),
    )


def _circles_hint(inside: list[int], config: CellConfig) -> str:
    """Circles far apart that the arm reaches, or what to correct when it reaches too few."""
    fix = "or set planning.offset_x_mm / offset_y_mm to where circle 1 lies on the machine"
    if len(inside) < 3:
        return f"the arm reaches {len(inside)} of the plate's circles: move the plate into its workspace, {fix}"
    table = {n: circle_table_mm(n, config) for n in inside}
    corners = sorted(
        {
            min(inside, key=lambda n: table[n][0] + table[n][1]),
            max(inside, key=lambda n: table[n][0] - table[n][1]),
            max(inside, key=lambda n: table[n][1] - table[n][0]),
            max(inside, key=lambda n: table[n][0] + table[n][1]),
        }
    )
    return f"choose circles inside it, e.g. --circles {' '.join(map(str, corners))}, {fix}"


def fit_points(points: list[TaughtPoint], config: CellConfig) -> tuple[TableToRobot, np.ndarray]:
    """The fit and each point's residual, mm; refused unless the points can determine it."""
    check_points(points)
    cfg = config.planning
    return fit_table_to_robot(
        np.array([p.table_mm for p in points]),
        np.array([p.robot_mm for p in points]),
        cfg.table_z_mm,
        cfg.teach_fit_scale,
    )


def check_points(points: list[TaughtPoint]) -> None:
    """Three or more distinct circles not on one line, every robot position a finite number:
    the same circle three times (or three in a row) cannot fix a rotation."""
    hint = "--point CIRCLE X_MM Y_MM for three circles not in one row or column, e.g. --circles 1 9 144 153"
    for p in points:
        if not np.all(np.isfinite(p.robot_mm)):
            raise InputError(f"circle {p.circle}: robot position {p.robot_mm} is not a finite number")
    circles = [p.circle for p in points]
    if len(set(circles)) < 3:
        raise InputError(f"teaching needs 3 or more distinct circles, got {sorted(set(circles))}", hint=hint)
    if len(set(circles)) < len(circles):
        raise InputError(
            f"circle(s) {sorted({c for c in circles if circles.count(c) > 1})} given more than once", hint=hint
        )
    table = np.array([p.table_mm for p in points], dtype=np.float64)
    centred = table - table.mean(axis=0)
    spread = np.linalg.svd(centred, compute_uv=False)
    if spread[1] < 1e-6 * max(spread[0], 1.0):
        raise InputError(f"circles {circles} lie on one line: they cannot fix the rotation", hint=hint)


def check_fit(points: list[TaughtPoint], residuals: np.ndarray, config: CellConfig) -> None:
    """TeachRejected when the largest residual exceeds planning.teach_max_residual_mm."""
    limit = config.planning.teach_max_residual_mm
    if residuals.max() > limit:
        worst = points[int(np.argmax(residuals))].circle
        raise TeachRejected(
            f"largest residual {residuals.max():.3f} mm (circle {worst}) exceeds planning.teach_max_residual_mm "
            f"{limit:g} mm; nothing written",
            hint="re-jog that circle, or check the circle numbers",
        )


def jog_session(
    arm: Arm, circles: list[int], config: CellConfig, ask: Callable[[str], str], tell: Callable[[str], None]
) -> list[TaughtPoint]:
    """Walk the operator through each circle on a connected arm; the pose at 'ok' is recorded."""
    points = []
    for circle in circles:
        table = circle_table_mm(circle, config)
        tell(f"circle {circle} at table ({table[0]:.1f}, {table[1]:.1f}) mm: jog the jaws' centre onto it. {JOG_HELP}")
        while True:
            pose = arm.status().pose
            if pose is None:
                raise InputError("the arm does not report its pose; give --point CIRCLE X Y instead")
            words = ask(f"[{pose.x_mm:.2f} {pose.y_mm:.2f} {pose.z_mm:.2f}] > ").split()
            if not words:
                continue
            cmd, values = words[0].lower(), words[1:]
            if cmd == "ok":
                points.append(TaughtPoint(circle, table, (pose.x_mm, pose.y_mm)))
                break
            if cmd == "skip":
                break
            if cmd == "quit":
                return points
            try:
                numbers = [float(v) for v in values]
            except ValueError:
                tell(f"not a number in {' '.join(values)!r}; {JOG_HELP}")
                continue
            target = [pose.x_mm, pose.y_mm, pose.z_mm]
            if cmd in ("x", "y", "z") and len(numbers) == 1:
                target["xyz".index(cmd)] += numbers[0]
            elif cmd == "to" and len(numbers) == 3:
                target = numbers
            else:
                tell(JOG_HELP)
                continue
            arm.move_to(*target)
    return points
