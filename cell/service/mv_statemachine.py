"""OPC 40100-1 VisionStateMachine and its AutomaticModeStateMachine: the methods that drive
them (Halt, Reset, ConfirmAll, SelectModeAutomatic, StartSingleJob, StartContinuous, Stop,
Abort, SimulationMode), entering a state along the specification's transitions, and the
state variables (CurrentState, LastTransition) with their TransitionEventType events."""

from __future__ import annotations

import contextlib
from datetime import UTC, datetime
from typing import Any

from asyncua import Node, ua
from asyncua.common.instantiate_util import instantiate

from cell.core.commands import Command, JobRequest, VisionState
from cell.service.mv_parts import MachineVisionParts, MethodError, bad_recipe_id, log, spec_id, valid_recipe_id
from cell.service.ua_values import mv_struct, node_id

_T = ua.VariantType

# Where each outward state sits in the specification's two machines: (top state, sub state).
STATE_PLACE: dict[VisionState, tuple[str, str]] = {
    VisionState.PREOPERATIONAL: ("Preoperational", ""),
    VisionState.HALTED: ("Halted", ""),
    VisionState.ERROR: ("Error", ""),
    VisionState.INITIALIZED: ("Operational", "Initialized"),
    VisionState.READY: ("Operational", "Ready"),
    VisionState.SINGLE_EXECUTION: ("Operational", "SingleExecution"),
    VisionState.CONTINUOUS_EXECUTION: ("Operational", "ContinuousExecution"),
}
_STATE_TYPES = {node_id(ua.ObjectIds.StateType), node_id(ua.ObjectIds.InitialStateType)}
_TRANSITION_TYPE = node_id(ua.ObjectIds.TransitionType)


class VisionStateMachinePart(MachineVisionParts):
    """The state machines of MachineVisionServer: their methods, states and transitions."""

    async def _state_variables(self, key: str) -> None:
        """CurrentState with its Id and Number, LastTransition with Id, Number and TransitionTime
        (the NodeSet's declarations carry only CurrentState and its Id)."""
        machine, app = self._n[key], self._ns["app"]
        base = str(machine.nodeid.Identifier)
        current = await machine.get_child(["0:CurrentState"])
        if not await _has_child(current, "0:Number"):
            await current.add_property(
                node_id(f"{base}.CurrentState.Number", app), ua.QualifiedName("Number", 0), ua.Variant(0, _T.UInt32)
            )
        if not await _has_child(machine, "0:LastTransition"):
            transition_type = self.server.get_node(node_id(ua.ObjectIds.FiniteTransitionVariableType))
            await instantiate(
                machine,
                transition_type,
                nodeid=node_id(f"{base}.LastTransition", app),
                bname=ua.QualifiedName("LastTransition", 0),
                instantiate_optional=True,
            )
        self._n[f"{key}.current"] = current
        self._n[f"{key}.last"] = await machine.get_child(["0:LastTransition"])
        for var in (current, self._n[f"{key}.last"]):  # typed from the start: writes are checked against it
            await self.server.write_attribute_value(
                (await var.get_child(["0:Id"])).nodeid, ua.DataValue(ua.Variant(ua.NodeId(), _T.NodeId))
            )

    async def _read_type_states(self) -> None:
        """The specification's states and transitions (nodes of the types) by BrowseName, with their numbers."""
        mv = self._ns["mv"]
        for type_id in (1017, 1021):  # VisionStateMachineType, VisionAutomaticModeStateMachineType
            for child in await self.server.get_node(node_id(type_id, mv)).get_children(refs=ua.ObjectIds.HasComponent):
                tdef = await child.read_type_definition()
                if tdef not in _STATE_TYPES and tdef != _TRANSITION_TYPE:
                    continue
                name = (await child.read_browse_name()).Name
                prop = "0:StateNumber" if tdef in _STATE_TYPES else "0:TransitionNumber"
                number = int(await (await child.get_child([prop])).read_value())
                (self._states if tdef in _STATE_TYPES else self._transitions)[name] = (child.nodeid, number)

    async def _halt(self, cause: int = 0, description: str = "") -> list[ua.Variant]:
        self._command(Command.HALT)
        return self._ok()

    async def _reset(self, cause: int = 0, description: str = "") -> list[ua.Variant]:
        self._command(Command.RESET)
        return self._ok()

    async def _confirm_all(self, comment: Any = None) -> list[ua.Variant]:
        """Acknowledge every condition: the cell's alarms need no acknowledgement beyond Reset,
        so this only records who confirmed (it changes no state)."""
        log.info("OPC UA ConfirmAll by %s: %s", self._origin().describe(), getattr(comment, "Text", comment))
        return []

    async def _select_automatic(self) -> list[ua.Variant]:
        return self._ok()  # the cell has only the automatic mode: always selected

    async def _start(self, command: Command, args: list[Any]) -> list[ua.Variant]:
        meas, part, recipe, product, parameters = (args + [None] * 5)[:5]
        request = JobRequest(
            recipe_id=spec_id(recipe),
            product_id=spec_id(product),
            part_id=spec_id(part),
            meas_id=spec_id(meas),
            parameters=tuple((_key(kv), _text(getattr(kv, "Value", None))) for kv in parameters or []),
        )
        if request.recipe_id and not valid_recipe_id(request.recipe_id):
            bad_recipe_id(f"RecipeId {request.recipe_id!r}")
        job_id = self._command(command, request) or ""
        return [ua.Variant(mv_struct("JobIdDataType")(Id=job_id), _T.ExtensionObject), ua.Variant(0, _T.Int32)]

    async def _start_single(self, *args: Any) -> list[ua.Variant]:
        return await self._start(Command.START_SINGLE, list(args))

    async def _start_continuous(self, *args: Any) -> list[ua.Variant]:
        return await self._start(Command.START_CONTINUOUS, list(args))

    async def _stop(self, cause: int = 0, description: str = "") -> list[ua.Variant]:
        self._command(Command.STOP)
        return self._ok()

    async def _abort(self, cause: int = 0, description: str = "") -> list[ua.Variant]:
        self._command(Command.ABORT)
        return self._ok()

    async def _simulation_mode(self, activate: bool = False, cause: int = 0, description: str = "") -> list[ua.Variant]:
        """The dry run is chosen when the service starts (`run-cell serve --dry-run`): asking for
        the mode the cell is in succeeds, asking to switch is not supported while it runs."""
        if bool(activate) != self._maker.simulated:
            raise MethodError(
                ua.StatusCodes.BadNotSupported,
                f"SimulationMode({bool(activate)}): the dry run is chosen at start (run-cell serve --dry-run)",
            )
        return self._ok()

    # ---- the state machines -----------------------------------------------------------
    async def _enter(self, state: VisionState, initial: bool = False) -> None:
        target = STATE_PLACE[state]
        if initial:
            await self._set_current(target)
            self._place = target
            return
        for machine, name, src, dst in self._path(self._place, target):
            await self._transition(machine, name, src, dst)
        await self._set_current(target)
        self._place = target
        self._last_command = None

    def _path(self, source: tuple[str, str], target: tuple[str, str]) -> list[tuple[str, str, str, str]]:
        """The specification's transitions from `source` to `target`: (machine, name, from, to)."""
        (top0, sub0), (top1, sub1) = source, target
        steps: list[tuple[str, str, str, str]] = []
        method = self._last_command
        if top0 != top1:
            if top0 in ("Halted", "Error") and top1 == "Operational":
                steps.append(
                    ("vsm", self._name(f"{top0}ToPreoperational", method is Command.RESET), top0, "Preoperational")
                )
                top0 = "Preoperational"
            if top0 != top1:
                manual = method is Command.HALT and top1 == "Halted"
                steps.append(("vsm", self._name(f"{top0}To{top1}", manual), top0, top1))
            if top1 == "Operational":
                sub0 = "Initialized"
        if top1 == "Operational" and sub1 and sub0 != sub1:
            if sub0 in ("SingleExecution", "ContinuousExecution") and sub1 == "Ready":
                kinds: dict[Command | None, str] = {Command.STOP: "Stop", Command.ABORT: "Abort"}
                kind = kinds.get(method, "Auto")
                name = f"{sub0}ToReady{kind}"
            else:
                starts = {"SingleExecution": Command.START_SINGLE, "ContinuousExecution": Command.START_CONTINUOUS}
                name = self._name(f"{sub0}To{sub1}", starts.get(sub1) is method and method is not None)
            steps.append(("auto", name, sub0, sub1))
        return [s for s in steps if s[1] in self._transitions]

    def _name(self, base: str, by_method: bool) -> str:
        if by_method and base in self._transitions:
            return base
        return f"{base}Auto" if f"{base}Auto" in self._transitions else base

    async def _set_current(self, place: tuple[str, str]) -> None:
        top, sub = place
        await self._write_state("vsm", top)
        await self._write_state("auto", sub)

    async def _write_state(self, machine: str, state: str) -> None:
        node = self._n[f"{machine}.current"]
        nid, number = self._states.get(state, (ua.NodeId(), 0))
        await node.write_value(ua.Variant(ua.LocalizedText(state), _T.LocalizedText))
        await (await node.get_child(["0:Id"])).write_value(ua.Variant(nid, _T.NodeId))
        for prop, value in (
            ("0:Number", ua.Variant(number, _T.UInt32)),
            ("0:Name", ua.Variant(ua.QualifiedName(state, self._ns["mv"]), _T.QualifiedName)),
        ):
            with contextlib.suppress(ua.UaStatusCodeError):
                await (await node.get_child([prop])).write_value(value)

    async def _transition(self, machine: str, name: str, source: str, target: str) -> None:
        now = datetime.now(UTC)
        nid, number = self._transitions[name]
        last = self._n[f"{machine}.last"]
        await last.write_value(ua.Variant(ua.LocalizedText(name), _T.LocalizedText))
        await (await last.get_child(["0:Id"])).write_value(ua.Variant(nid, _T.NodeId))
        for prop, value in (
            ("0:Number", ua.Variant(number, _T.UInt32)),
            ("0:Name", ua.Variant(ua.QualifiedName(name, self._ns["mv"]), _T.QualifiedName)),
            ("0:TransitionTime", ua.Variant(now, _T.DateTime)),
        ):
            with contextlib.suppress(ua.UaStatusCodeError):
                await (await last.get_child([prop])).write_value(value)
        gen = self._generators[machine]
        ev = gen.event
        ev.Message = ua.LocalizedText(f"{source} -> {target} ({name})")
        ev.Severity = 100
        state_id = self._states.get
        for field, field_value, vtype in (
            ("Transition", ua.LocalizedText(name), _T.LocalizedText),
            ("Transition/Id", nid, _T.NodeId),
            ("FromState", ua.LocalizedText(source), _T.LocalizedText),
            ("FromState/Id", state_id(source, (ua.NodeId(), 0))[0], _T.NodeId),
            ("ToState", ua.LocalizedText(target), _T.LocalizedText),
            ("ToState/Id", state_id(target, (ua.NodeId(), 0))[0], _T.NodeId),
        ):
            ev.add_property(field, field_value, vtype)  # the value and its type: asyncua wraps it in a Variant
        await gen.trigger(now)


async def _has_child(node: Node, name: str) -> bool:
    try:
        await node.get_child([name])
    except ua.UaStatusCodeError:
        return False
    return True


def _text(value: Any) -> str:
    """A parameter's value as text (KeyValuePair.Value is a Variant of any type)."""
    value = value.Value if isinstance(value, ua.Variant) else value
    if value is None:
        return ""
    return value.Text or "" if isinstance(value, ua.LocalizedText) else str(value)


def _key(kv: Any) -> str:
    key = getattr(kv, "Key", "")
    return str(getattr(key, "Name", key))
