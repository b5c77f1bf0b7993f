"""The cell's states and the transitions allowed between them; no side effects here.

The runner (cell/runner.py) does the work of each state and asks this machine to move on;
a transition that is not in TRANSITIONS is a programming error and raises. Every
transition carries the reason it was taken, which the runner logs.

The loop: Idle -> Home -> Capture -> Locate -> Plan -> Pick -> Place -> Capture ->
Locate -> Verify -> Plan -> ... -> Done; in continuous mode Plan with nothing to pick goes
to Wait -> Capture instead of Done, until a stop. The frame captured after a place is the one
Verify checks and the next Plan uses, so each pick costs one frame.
"""

from __future__ import annotations

import ast
import inspect
import itertools
import time
from collections.abc import Callable, MutableSequence
from dataclasses import dataclass
from enum import Enum


class State(Enum):
    IDLE = "idle"
    """Configured and connected; nothing has moved yet."""
    HOME = "home"
    """Homing the arm and opening the gripper, so the first move starts from a known pose."""
    CAPTURE = "capture"
    """Taking one frame of the table (the arm is parked clear of the camera's view)."""
    LOCATE = "locate"
    """Finding and classifying the parts in the frame; table mm through the calibration."""
    VERIFY = "verify"
    """Checking, on the new frame, that the part just placed is gone from where it was."""
    PLAN = "plan"
    """Choosing the next part and its robot target; refusing unreachable targets before motion."""
    PICK = "pick"
    """Approach, descend, close the gripper, lift."""
    PLACE = "place"
    """Carry to the class's bin, open the gripper, lift."""
    WAIT = "wait"
    """Continuous mode: nothing pickable on the table; the arm stays parked while the cell waits
    one capture interval (no busy loop), then captures again."""
    PAUSED = "paused"
    """Operator pause at a safe point (no part in the gripper, or before the first motion);
    resumes with a fresh frame (or by homing, if the pause came before it)."""
    DONE = "done"
    """No pickable part left that has not been picked, failed or found unreachable."""
    FAULT = "fault"
    """A device or input failed; the arm was made safe. The reason is in the log."""
    STOPPED = "stopped"
    """Stopped on request (Ctrl-C): motion ended, gripper opened, arm homed, torque released."""


S = State
TERMINAL = frozenset({S.DONE, S.FAULT, S.STOPPED})

# Every state may fail (-> FAULT) or be stopped (-> STOPPED) except the terminal ones;
# those two are added below so the table lists only the working transitions.
_WORK: dict[State, frozenset[State]] = {
    S.IDLE: frozenset({S.HOME}),
    S.HOME: frozenset({S.CAPTURE, S.PAUSED}),
    S.CAPTURE: frozenset({S.LOCATE, S.PAUSED}),
    S.LOCATE: frozenset({S.PLAN, S.VERIFY, S.PAUSED}),
    S.VERIFY: frozenset({S.PLAN, S.PAUSED}),
    S.PLAN: frozenset({S.PICK, S.DONE, S.WAIT, S.PAUSED}),
    S.PICK: frozenset({S.PLACE}),
    S.PLACE: frozenset({S.CAPTURE}),
    S.WAIT: frozenset({S.CAPTURE, S.PAUSED}),
    S.PAUSED: frozenset({S.CAPTURE, S.HOME}),
}
TRANSITIONS: dict[State, frozenset[State]] = {
    **{s: targets | {S.FAULT, S.STOPPED} for s, targets in _WORK.items()},
    **{s: frozenset() for s in TERMINAL},
}


class IllegalTransition(RuntimeError):
    """A transition not in TRANSITIONS: a bug in the runner, never an operator error."""


@dataclass(frozen=True)
class Transition:
    source: State
    target: State
    reason: str
    time_s: float  # time.monotonic() when taken


class StateMachine:
    """Current state plus the history of transitions; listeners hear each one (the audit log)."""

    def __init__(self, listeners: list[Callable[[Transition], None]] | None = None):
        self.state = S.IDLE
        self.history: MutableSequence[Transition] = []  # a runner may bound it (a deque)
        self.listeners = list(listeners or [])

    @property
    def finished(self) -> bool:
        return self.state in TERMINAL

    def go(self, target: State, reason: str) -> Transition:
        if target not in TRANSITIONS[self.state]:
            raise IllegalTransition(f"{self.state.name} -> {target.name} is not allowed ({reason})")
        t = Transition(self.state, target, reason, time.monotonic())
        self.state = target
        self.history.append(t)
        for listener in self.listeners:
            listener(t)
        return t


def mermaid() -> str:
    """The transition table as a Mermaid state diagram (FAULT/STOPPED edges folded into a note)."""
    lines = ["stateDiagram-v2", "    [*] --> IDLE"]
    for source, targets in _WORK.items():
        for target in sorted(targets, key=lambda s: list(State).index(s)):
            lines.append(f"    {source.name} --> {target.name}")
    for s in sorted(TERMINAL, key=lambda s: list(State).index(s)):
        lines.append(f"    {s.name} --> [*]")
    lines.append("    note right of FAULT: any non-terminal state may go to FAULT or STOPPED")
    return "\n".join(lines) + "\n"


def markdown() -> str:
    """docs/state-machine.md: the diagram plus each state's docstring."""
    rows = "\n".join(f"| {s.name} | {_DOCS[s]} |" for s in State)
    return (
        "# The cell's state machine\n\n"
        "Generated from `cell/statemachine.py` by `run-cell diagram --markdown`; "
        "a test checks it is current.\n\n"
        f"```mermaid\n{mermaid()}```\n\n| State | Meaning |\n|---|---|\n{rows}\n"
    )


def _state_docs() -> dict[State, str]:
    """Enum members cannot carry docstrings; read the string after each member from the source."""
    tree = ast.parse(inspect.getsource(State))
    cls = tree.body[0]
    assert isinstance(cls, ast.ClassDef)
    docs = {}
    for stmt, nxt in itertools.pairwise(cls.body):
        if (
            isinstance(stmt, ast.Assign)
            and isinstance(name := stmt.targets[0], ast.Name)
            and isinstance(nxt, ast.Expr)
            and isinstance(nxt.value, ast.Constant)
            and isinstance(doc := nxt.value.value, str)
        ):
            docs[State[name.id]] = doc
    return docs


_DOCS = _state_docs()
