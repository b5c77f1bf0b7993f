"""One rule for every interface, end to end (issue 15): while a recalibration report waits for the
operator's answer on the screen, `run-cell serve --dry-run` refuses a start from OPC UA (the cell's
own `StartContinuous` and OPC 40100-1's) with BadInvalidState and the screen's Start with a 409, for
the same reason, recorded for each; once the report is rejected both may start again."""

from __future__ import annotations

import asyncio
import json

import httpx
import pytest
from asyncua import Client, ua

from tests.serve_process import ServeProcess

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]
MV_URI = "http://opcfoundation.org/UA/MachineVision"


async def opcua_starts(port: int) -> tuple[str, str]:
    """The status of the cell's StartContinuous and of OPC 40100-1's, each called once."""
    client = Client(f"opc.tcp://127.0.0.1:{port}/cell", timeout=30, watchdog_intervall=15)
    async with client:
        await client.load_data_type_definitions()
        own = await client.get_namespace_index("urn:pick-cell")
        mv = await client.get_namespace_index(MV_URI)
        cell = await client.nodes.objects.get_child(f"{own}:Cell")
        auto = await client.nodes.objects.get_child(
            [f"{own}:VisionSystem", f"{mv}:VisionStateMachine", f"{mv}:AutomaticModeStateMachine"]
        )
        outcomes = []
        for parent, method, args in (
            (cell, f"{own}:StartContinuous", []),
            (auto, f"{mv}:StartContinuous", _mv_start_args()),
        ):
            try:
                await parent.call_method(method, *args)
                outcomes.append("Good")
            except ua.UaStatusCodeError as e:
                outcomes.append(ua.StatusCode(e.code).name)
        return outcomes[0], outcomes[1]


def _mv_start_args() -> list[ua.Variant]:
    """MeasId, PartId, RecipeId, ProductId empty (the prepared recipe) and no Parameters."""
    ext = ua.VariantType.ExtensionObject
    return [
        ua.Variant(ua.MeasIdDataType(Id=""), ext),
        ua.Variant(ua.PartIdDataType(Id=""), ext),
        ua.Variant(ua.RecipeIdExternalDataType(Id=""), ext),
        ua.Variant(ua.ProductIdDataType(Id=""), ext),
        ua.Variant([], ext, is_array=True),
    ]


def refused_commands(serve: ServeProcess) -> list[dict[str, object]]:
    """The service's audit lines for refused commands, oldest first."""
    lines = []
    for path in sorted((serve.workdir / "logs").glob("cell-*.jsonl")):
        lines += [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return [e for e in lines if e.get("kind") == "command" and not e.get("accepted")]


def test_an_open_recalibration_report_holds_starts_on_every_interface_for_the_same_reason(tmp_path):
    serve = ServeProcess(tmp_path)
    try:
        with httpx.Client(base_url=serve.url, timeout=60) as screen:
            token = screen.get("api/session").json()["csrf"]
            headers = {"x-csrf-token": token}
            report = screen.post("api/recalibration/capture", headers=headers)
            assert report.status_code == 200, report.text
            report_id = report.json()["id"]

            own, standard = asyncio.run(opcua_starts(serve.opcua_port))
            start = screen.post("api/command/StartContinuous", headers=headers)
            assert (own, standard, start.status_code) == ("BadInvalidState", "BadInvalidState", 409)
            assert "a recalibration report" in start.json()["error"], start.json()
            refused = refused_commands(serve)
            assert [(e["command"], e["origin"]["interface"]) for e in refused] == [
                ("StartContinuous", "opcua"),
                ("StartContinuous", "opcua"),
                ("StartContinuous", "screen"),
            ]
            assert {e["message"] for e in refused} == {start.json()["error"]}, refused  # one reason for all

            assert screen.post(f"api/recalibration/{report_id}/reject", headers=headers).json()["accepted"] is False
            assert "StartContinuous" in screen.get("api/state").json()["allowed"]
    finally:
        assert serve.stop() == 0, "\n".join(serve.lines[-30:])
