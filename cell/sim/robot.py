"""The robot of the simulated cell when arm.kind is 'robot-server' (docs/robots.md).

SimulatedRobot (robot_server.simulated_robot = true) is a robot program over the real socket,
as the URScript example in docs/robots.md is: NEXT, move the simulated arm to the target,
close, report PICKED (or MISSED when nothing is held), carry to the bin, open, report PLACED.

WorldRobot (simulated_robot = false) lets an outside client play the robot: the simulated
world takes its reports as what happened, at the target the client was given (PICKED grips
there, PLACED lets go over the bin, MISSED leaves the part where it lies).
"""

from __future__ import annotations

import contextlib
import logging
import socket
import threading
from collections.abc import Callable, Iterator

from cell.sim.sim_arm import SimArm
from drivers.arm.robot_server import Pick

log = logging.getLogger(__name__)


def parse_answer(line: str) -> list[float]:
    """`(a,b,...)` to its numbers, as socket_read_ascii_float reads them."""
    body = line.strip()
    if not (body.startswith("(") and body.endswith(")")):
        raise ValueError(f"not an answer: {line!r}")
    return [float(v) for v in body[1:-1].split(",")]


class SimulatedRobot:
    """A robot program on its own thread: asks, moves the simulated arm, reports; until closed."""

    def __init__(self, address: tuple[str, int], arm: SimArm, retry_s: float = 0.2):
        self.address, self.arm, self.retry_s = address, arm, retry_s
        self.picks = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sim-robot", daemon=True)

    def __enter__(self) -> SimulatedRobot:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(10.0)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                with socket.create_connection(self.address, timeout=5.0) as s:
                    s.settimeout(90.0)  # every answer comes within next_wait_s (at most 60 s)
                    self._program(s.makefile("rw", encoding="ascii", newline="\n"))
            except OSError as e:  # the server closing, or not yet listening: try again
                log.debug("simulated robot: %s", e)
            self._stop.wait(self.retry_s)

    def _ask(self, f, request: str) -> list[float]:  # noqa: ANN001 - a socket's text file
        f.write(request + "\n")
        f.flush()
        line = f.readline()
        if not line:
            raise OSError("the cell closed the connection")
        return parse_answer(line)

    def _program(self, f) -> None:  # noqa: ANN001
        arm = self.arm
        while not self._stop.is_set():
            answer = self._ask(f, "NEXT")
            if answer[0] != 1:  # (0): nothing yet (the cell waited next_wait_s); (-1,code): not now
                if answer[0] < 0:
                    self._stop.wait(self.retry_s)
                continue
            _, x, y, z, angle, _class_no, no, bx, by, bz = answer
            approach = max(z, bz) + 20.0  # this program's own clearance
            arm.move_to(x, y, approach, angle)
            arm.move_to(x, y, z, angle)
            arm.close_gripper()
            held = arm.world.held() is not None
            arm.move_to(x, y, approach, angle)
            self._ask(f, f"{'PICKED' if held else 'MISSED'} {int(no)}")
            if not held:
                arm.open_gripper()
                continue
            arm.move_to(bx, by, approach)
            arm.move_to(bx, by, bz)
            arm.open_gripper()
            arm.move_to(bx, by, approach)
            self._ask(f, f"PLACED {int(no)}")
            self.picks += 1


class WorldRobot:
    """The simulated world's account of an outside robot's reports (PickBoard observer)."""

    def __init__(self, arm: SimArm):
        self.arm = arm

    def apply(self, report: str, pick: Pick) -> None:
        arm, plan = self.arm, pick.plan
        x, y, z = plan.pick_mm
        if report == "PICKED":
            arm.move_to(x, y, plan.approach_z_mm, plan.angle_deg)
            arm.move_to(x, y, z, plan.angle_deg)
            arm.close_gripper()
            arm.move_to(x, y, plan.approach_z_mm, plan.angle_deg)
            log.info("simulated world, robot's PICKED %d: %s", pick.no, arm.last_grip)
        elif report == "PLACED":
            bx, by, bz = plan.bin_mm
            arm.move_to(bx, by, max(bz, plan.approach_z_mm))
            arm.move_to(bx, by, bz)
            arm.open_gripper()
            arm.move_to(bx, by, max(bz, plan.approach_z_mm))
            log.info("simulated world, robot's PLACED %d: %s", pick.no, arm.last_grip)
        elif report == "MISSED" and arm.world.held() is not None:  # dropped on the way: it falls where the arm is
            arm.open_gripper()


@contextlib.contextmanager
def robot_for(
    world_arm: SimArm, address: tuple[str, int], simulated: bool, board_observers: list[Callable[[str, Pick], None]]
) -> Iterator[None]:
    """The simulated cell's robot for a `with` block: SimulatedRobot asking over the socket, or the
    world taking an outside robot's reports."""
    world_arm.connect()
    if simulated:
        with SimulatedRobot(address, world_arm):
            yield
        return
    board_observers.append(WorldRobot(world_arm).apply)
    yield
