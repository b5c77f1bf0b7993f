"""The transition table: every allowed transition works, everything else raises."""

from __future__ import annotations

from pathlib import Path

import pytest

from cell.statemachine import TERMINAL, TRANSITIONS, IllegalTransition, State, StateMachine, markdown, mermaid

ALLOWED = [(a, b) for a in State for b in State if b in TRANSITIONS[a]]  # in enum order: xdist workers must agree
FORBIDDEN = [(a, b) for a in State for b in State if b not in TRANSITIONS[a]]


def machine_in(state: State) -> StateMachine:
    sm = StateMachine()
    sm.state = state
    return sm


@pytest.mark.parametrize("source,target", ALLOWED, ids=lambda s: s.name)
def test_every_allowed_transition_is_taken_logged_with_its_reason(source, target):
    heard = []
    sm = machine_in(source)
    sm.listeners.append(heard.append)
    t = sm.go(target, f"because {target.name}")
    assert sm.state == target and t.source == source and t.reason == f"because {target.name}"
    assert heard == [t] and sm.history == [t]


@pytest.mark.parametrize("source,target", FORBIDDEN, ids=lambda s: s.name)
def test_every_other_transition_raises_and_changes_nothing(source, target):
    sm = machine_in(source)
    with pytest.raises(IllegalTransition):
        sm.go(target, "not allowed")
    assert sm.state == source and sm.history == []


def test_every_working_state_can_fault_and_stop_and_terminal_states_are_final():
    for s in State:
        if s in TERMINAL:
            assert TRANSITIONS[s] == frozenset()
        else:
            assert {State.FAULT, State.STOPPED} <= TRANSITIONS[s]


def test_every_state_is_reachable_from_idle_and_the_loop_reaches_done():
    seen, todo = {State.IDLE}, [State.IDLE]
    while todo:
        for t in TRANSITIONS[todo.pop()]:
            if t not in seen:
                seen.add(t)
                todo.append(t)
    assert seen == set(State)
    assert State.DONE in TRANSITIONS[State.PLAN]


def test_the_happy_path_is_allowed():
    sm = StateMachine()
    path = [
        State.HOME,
        State.CAPTURE,
        State.LOCATE,
        State.PLAN,
        State.PICK,
        State.PLACE,
        State.CAPTURE,
        State.LOCATE,
        State.VERIFY,
        State.PLAN,
        State.DONE,
    ]
    for s in path:
        sm.go(s, "test")
    assert sm.finished


def test_diagram_lists_every_working_transition():
    text = mermaid()
    for a, b in ALLOWED:
        if b not in (State.FAULT, State.STOPPED):
            assert f"{a.name} --> {b.name}" in text


def test_docs_state_machine_md_is_current():
    doc = Path(__file__).resolve().parents[1] / "docs" / "state-machine.md"
    assert doc.read_text(encoding="utf-8") == markdown(), (
        "regenerate: run-cell diagram --markdown > docs/state-machine.md"
    )
