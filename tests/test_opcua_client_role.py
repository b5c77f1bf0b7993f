"""`service.machine_vision.client_role` holds on the production server (issue 28, defect 2):
`run-cell serve --dry-run` on loopback without users, the anonymous client acting with the
configured role on both the Cell object and the Machine Vision model; and deny by default: a
session without a role of the cell, or a call that is no client's request, may do nothing."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from asyncua.crypto.permission_rules import User, UserRole

from cell.core.events import Role
from cell.service.opcua_security import CellUser, caller_origin, caller_role
from tests.mv_harness import MachineVisionHarness, shared_cache_dir
from tests.serve_process import ServeProcess

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]
MV_URI = "http://opcfoundation.org/UA/MachineVision"
_T = ua.VariantType


async def outcome(call: Any) -> str:
    try:
        await call
    except ua.UaStatusCodeError as e:
        return ua.StatusCode(e.code).name
    return "Good"


def test_client_role_holds_on_the_served_cell(tmp_path: Path) -> None:
    (tmp_path / "line.toml").write_text('[service.machine_vision]\nclient_role = "operator"\n')
    serve = ServeProcess(tmp_path, "--config", str(tmp_path / "line.toml"))
    try:

        async def scenario() -> tuple[list[str], list[str]]:
            async with Client(f"opc.tcp://127.0.0.1:{serve.opcua_port}/cell", timeout=30, watchdog_intervall=15) as c:
                await c.load_data_type_definitions()
                mv = await c.get_namespace_index(MV_URI)
                app = await c.get_namespace_index("urn:pick-cell")
                vs = await c.nodes.objects.get_child([f"{app}:VisionSystem"])
                recipes = await vs.get_child([f"{mv}:RecipeManagement"])
                folder = await recipes.get_child([f"{mv}:Recipes"])
                recipe = ua.Variant(ua.RecipeIdExternalDataType(Id="kit-9"), _T.ExtensionObject)
                refused = [
                    await outcome(recipes.call_method(f"{mv}:AddRecipe", recipe, ua.Variant(None, _T.ExtensionObject))),
                    await outcome(
                        recipes.call_method(
                            f"{mv}:PrepareRecipe",
                            recipe,
                            ua.Variant(ua.RecipeIdInternalDataType(Id=""), _T.ExtensionObject),
                        )
                    ),
                ]
                listed = [d.BrowseName.Name for d in await folder.get_children_descriptions()]
                cell = await c.nodes.objects.get_child([f"{app}:Cell"])
                allowed = [await outcome(cell.call_method(f"{app}:StartSingleJob"))]  # an operator may run jobs
                return refused + listed, allowed

        refused, allowed = asyncio.run(scenario())
        assert refused == ["BadUserAccessDenied", "BadUserAccessDenied"]  # and no recipe node was added
        assert allowed == ["Good"]
        assert not (tmp_path / "recipes" / "kit-9.toml").exists()
    finally:
        assert serve.stop() == 0, "\n".join(serve.lines[-30:])


def test_the_role_of_a_session() -> None:
    engineer = Role.ENGINEER
    assert caller_role(None, secure=False, client_role=Role.OPERATOR) is Role.OPERATOR  # loopback, no users
    admin = CellUser(role=UserRole.User, name="ada", cell_role=Role.ADMIN)
    viewer = CellUser(role=UserRole.User, name="vic", cell_role=Role.VIEWER)
    assert caller_role(admin, secure=True, client_role=engineer) is Role.ENGINEER  # capped at client_role
    assert caller_role(viewer, secure=True, client_role=engineer) is Role.VIEWER
    assert caller_role(User(role=UserRole.User), secure=True, client_role=engineer) is None  # not one of ours
    assert caller_role(None, secure=True, client_role=engineer) is None
    assert caller_origin() is None  # no client's request being handled: no role at all


def test_a_call_that_is_no_clients_request_is_refused(tmp_path: Path, tmp_path_factory: pytest.TempPathFactory) -> None:
    """A method called inside the server (no client session, no GuardedProcessor) has no origin:
    refused, nothing done (before issue 28 it acted with client_role, or as the service: admin)."""
    h = MachineVisionHarness(tmp_path, shared_cache_dir(tmp_path_factory)).start()
    try:

        async def halt_from_inside() -> str:
            assert h.mv is not None and h.mv.node is not None
            vsm = await h.mv.node.get_child([f"{h.mv._ns['mv']}:VisionStateMachine"])
            return await outcome(
                vsm.call_method(f"{h.mv._ns['mv']}:Halt", ua.Variant(0, _T.Int32), ua.Variant("", _T.String))
            )

        assert asyncio.run_coroutine_threadsafe(halt_from_inside(), h._loop).result(timeout=60) == "BadUserAccessDenied"
        assert h.service.state.value == "Ready"  # not Halted
    finally:
        h.stop()
