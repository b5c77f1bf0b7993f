"""The arm interface the cell programs against; each driver alone knows its wire protocol."""

from __future__ import annotations

import abc
import contextlib
import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Literal

from drivers.arm.errors import ArmError, ConnectionLost, NotConnected, OutOfReach, PositionLost
from drivers.arm.kinematics import Pose
from drivers.device import Device

log = logging.getLogger(__name__)

ArmState = Literal["idle", "moving", "hold", "alarm", "fault", "disconnected"]


@dataclass(frozen=True)
class ArmStatus:
    """What the arm reports about itself: state, tool pose (None if unknown), gripper."""

    state: ArmState
    pose: Pose | None
    gripper_closed: bool | None
    detail: str = ""


@dataclass(frozen=True)
class PickPlan:
    """A whole pick as the cell planned it, robot base frame (mm, deg): told to an arm before its
    motions, for an arm that moves by its own program (a robot asking the cell, docs/robots.md)."""

    pick_id: str
    cls: str
    pick_mm: tuple[float, float, float]
    approach_z_mm: float
    angle_deg: float | None
    bin_mm: tuple[float, float, float]
    class_no: int = 0  # the number the cell gives the part's class (its recipe's); 0: none


class Arm(Device):
    """One arm. Coordinates are the robot base frame in mm; angle_deg turns the gripper about z.

    Every method raises an ArmError subclass on failure, after leaving the arm safe (motion
    stopped, servo torque released); `with arm:` connects and always disconnects.

    After a controller restart the driver detects (each says how), the position it relied on
    is void: every motion command (move_to, the gripper, wait_until_idle) raises PositionLost,
    sending nothing, until home() re-establishes the position or an operator calls unlock().
    The latch outlives disconnect/connect: a restart is not undone by reconnecting.
    """

    port: str
    _restart_evidence: str | None = None  # what showed the restart; None while the position holds
    _position_lost_hint: str | None = None  # a driver's own advice for PositionLost (None: the default)

    @abc.abstractmethod
    def home(self) -> None:
        """Run the homing cycle (or go to the configured home pose) and wait for it."""

    @abc.abstractmethod
    def check_target(self, x_mm: float, y_mm: float, z_mm: float, angle_deg: float | None = None) -> None:
        """Raise OutOfReach if the target cannot be reached; sends nothing."""

    @abc.abstractmethod
    def move_to(
        self, x_mm: float, y_mm: float, z_mm: float, angle_deg: float | None = None, *, wait: bool = True
    ) -> None:
        """Move the tool point to (x, y, z); with wait, return once it has arrived."""

    @abc.abstractmethod
    def open_gripper(self) -> None: ...

    @abc.abstractmethod
    def close_gripper(self) -> None: ...

    @abc.abstractmethod
    def wait_until_idle(self, timeout_s: float | None = None) -> None:
        """Block until all commanded motion is done; NoResponse after timeout_s."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Stop motion now and leave the arm safe; never raises."""

    @abc.abstractmethod
    def status(self) -> ArmStatus: ...

    @abc.abstractmethod
    def unlock(self) -> None:
        """Let motion resume after a controller restart without homing, moving nothing. Only for
        an operator who has checked the arm is where its controller now says it is: what that
        means, and what is sent, is each driver's (see its unlock). The cell never calls it."""

    def announce(self, plan: PickPlan, cancelled: Callable[[], bool]) -> None:  # noqa: B027 - optional hook
        """The pick the next motions carry out, before the first of them. An arm the cell moves
        ignores it; a robot running its own program is offered it (drivers.arm.robot_server), and
        `cancelled()` true before the robot took it withdraws it (PickWithdrawn: nothing moved)."""

    def take_reports(self) -> list[dict[str, Any]]:
        """What the arm's own controller reported since the last call (a robot's PICKED, PLACED,
        MISSED), oldest first, for the record; an arm the cell moves reports nothing."""
        return []

    @property
    def position_lost(self) -> bool:
        """True from a detected controller restart until the arm is homed or unlocked."""
        return self._restart_evidence is not None

    def _refuse_while_position_lost(self, command: str) -> None:
        """Refuse `command` before anything is sent while the position is lost."""
        if self._restart_evidence is not None:
            raise PositionLost(
                port=self.port, command=command, reply=self._restart_evidence, hint=self._position_lost_hint
            )

    def _restarted(self, evidence: str, command: str) -> PositionLost:
        """Latch a controller restart detected by `evidence`; the error for the command that met it."""
        if self._restart_evidence is None:
            self._restart_evidence = evidence
            log.error(
                "arm on %s: controller restarted (%s): motion locked until homed or unlocked", self.port, evidence
            )
        return PositionLost(
            port=self.port, command=command, reply=self._restart_evidence, hint=self._position_lost_hint
        )

    def _position_regained(self, how: str) -> None:
        """End the latch once the position is known again (`how`: homed, unlocked by the operator)."""
        if self._restart_evidence is not None:
            log.warning(
                "arm on %s: position regained (%s) after a restart (%s)", self.port, how, self._restart_evidence
            )
        self._restart_evidence = None

    @contextlib.contextmanager
    def _guard(self, command: str) -> Iterator[None]:
        """Leave the arm safe when `command` fails with an ArmError, then let the error through.

        A lost link is only noted (nothing can be sent); a refused target or an unconnected
        arm needs nothing; anything else makes the driver leave the device safe.
        """
        try:
            yield
        except ArmError as e:
            if isinstance(e, ConnectionLost):
                self._link_lost()
            elif not isinstance(e, (OutOfReach, NotConnected)):
                self._leave_safe(e)
            log.info("arm on %s, %s: %s", self.port, command, e)
            raise

    def _link_lost(self) -> None:  # noqa: B027 - an optional hook, empty unless the driver reconnects
        """The port is gone: forget it so the next command reconnects (drivers that reconnect)."""

    def _leave_safe(self, error: ArmError) -> None:
        """After a failed command: stop the device the way this driver knows is safe."""
        self.stop()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc_type is not None:
            log.info("stopping arm on %s after %s", getattr(self, "port", "?"), exc_type.__name__)
            self.stop()
        self.disconnect()
