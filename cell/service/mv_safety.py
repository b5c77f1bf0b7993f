"""OPC 40100-1 SafetyStateManagement (ReportSafetyState, VisionSafetyTriggered,
VisionSafetyInformation) and the SystemState variable (SEMI E10 SystemStateDescriptionDataType),
written from the service's snapshot."""

from __future__ import annotations

from asyncua import ua

from cell.core.commands import Command, VisionState
from cell.core.records import Snapshot
from cell.service.mv_parts import MachineVisionParts
from cell.service.mv_statemachine import STATE_PLACE
from cell.service.ua_values import mv_struct

_T = ua.VariantType

# SEMI E10 state (OPC 40100-1 SystemStateDataType value) for each outward state.
SYSTEM_STATE: dict[VisionState, int] = {
    VisionState.SINGLE_EXECUTION: 1,  # PRD: production
    VisionState.CONTINUOUS_EXECUTION: 1,
    VisionState.READY: 2,  # SBY: standby, ready for a start
    VisionState.INITIALIZED: 2,
    VisionState.PREOPERATIONAL: 4,  # SDT: starting, devices opening, calibration loading
    VisionState.HALTED: 4,  # SDT: stopped on purpose (Halt, a signal) until Reset
    VisionState.ERROR: 5,  # UDT: a fault
}
ENGINEERING = 3  # ENG: a user is working on the system (a recalibration holding starts)


class SafetyStatePart(MachineVisionParts):
    """SafetyStateManagement and SystemState of MachineVisionServer."""

    # ---- safety -----------------------------------------------------------------------
    async def _report_safety(self, triggered: bool = False, information: str = "") -> list[ua.Variant]:
        """The environment reports its safety state; a trigger halts the cell (the safe stop)."""
        self._safety = (bool(triggered), str(information or ""))
        await self._write_safety()
        if triggered and self.service.snapshot().vision_state in (
            VisionState.INITIALIZED,
            VisionState.READY,
            VisionState.SINGLE_EXECUTION,
            VisionState.CONTINUOUS_EXECUTION,
        ):
            self._command(Command.HALT)
        return self._ok()

    async def _write_safety(self) -> None:
        await self._n["safety_triggered"].write_value(ua.Variant(self._safety[0], _T.Boolean))
        await self._n["safety_info"].write_value(ua.Variant(self._safety[1], _T.String))

    async def _write_values(self, s: Snapshot) -> None:
        if STATE_PLACE[s.vision_state] != self._place:  # a state change whose event was dropped
            await self._enter(s.vision_state)
        state = SYSTEM_STATE[s.vision_state]
        if s.hold and s.vision_state in (VisionState.READY, VisionState.INITIALIZED):
            state = ENGINEERING
        description = s.vision_state.value
        if s.alarm is not None:
            description = f"{description}: {s.alarm.reason}"
        elif s.hold:
            description = f"{description}: {s.hold}"
        value = mv_struct("SystemStateDescriptionDataType")(
            State=mv_struct("SystemStateDataType")(state), StateDescription=description
        )
        if self._written.get("system_state") != (state, description):
            await self._n["system_state"].write_value(ua.Variant(value, _T.ExtensionObject))
            self._written["system_state"] = (state, description)
        if self._written.get("recipe") != s.recipe:
            await self._refresh_recipe_folder()
            self._written["recipe"] = s.recipe
