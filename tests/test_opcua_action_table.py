"""Issue 28's "done when", the OPC UA half: a viewer is refused every OPC UA method that changes
state, with no side effect, on the server `run-cell serve` builds (users configured, so a
viewer logs in over Basic256Sha256 SignAndEncrypt).

The test walks every method a client finds under Objects (browsed, not listed by hand) and
looks each up in ACTIONS, the one table of what a viewer gets: a method without an entry
fails the test, so a new method must be placed in the table (and given its role in
cell/service/machinevision.py METHODS or the command table) before it ships. Each method is
called as the viewer; afterwards nothing has changed: the states, the SystemState (no hold),
the safety state, the Recipes folder, the recipe and calibration files' hashes."""

from __future__ import annotations

import asyncio
import hashlib
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, Node, ua

from cell.access.users import UserEntry, hash_password, write_users
from cell.core.events import Role
from tests.mv_harness import RECIPE_BOLTS
from tests.probes import Credentials, make_client_certificate, secure_client
from tests.serve_process import ServeProcess

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]

USERS = {"vera": ("vera-pass-1", Role.VIEWER), "edna": ("edna-pass-1", Role.ENGINEER)}
MV_URI = "http://opcfoundation.org/UA/MachineVision"
_T = ua.VariantType

DENIED = "BadUserAccessDenied"  # changes state: a viewer is refused before anything happens
WATCH = "viewer may: reads, or handles of its own"  # answers something other than BadUserAccessDenied
HALT = "viewer may: Halt (anyone who may see the cell may Halt)"  # not called here: test_roles_e2e
UNBOUND = "BadNothingToDo"  # the standard namespace's methods: this server binds none of them

# Every method of the cell's namespace, by its BrowseName path below Objects (a recipe's id as <recipe>).
ACTIONS: dict[str, str] = {
    "Cell/StartSingleJob": DENIED,
    "Cell/StartContinuous": DENIED,
    "Cell/Stop": DENIED,
    "Cell/Abort": DENIED,
    "Cell/Pause": DENIED,
    "Cell/Resume": DENIED,
    "Cell/Reset": DENIED,
    "Cell/Halt": HALT,
    "VisionSystem/VisionStateMachine/Halt": HALT,
    "VisionSystem/VisionStateMachine/Reset": DENIED,
    "VisionSystem/VisionStateMachine/ConfirmAll": DENIED,
    "VisionSystem/VisionStateMachine/SelectModeAutomatic": DENIED,
    "VisionSystem/VisionStateMachine/AutomaticModeStateMachine/StartSingleJob": DENIED,
    "VisionSystem/VisionStateMachine/AutomaticModeStateMachine/StartContinuous": DENIED,
    "VisionSystem/VisionStateMachine/AutomaticModeStateMachine/Stop": DENIED,
    "VisionSystem/VisionStateMachine/AutomaticModeStateMachine/Abort": DENIED,
    "VisionSystem/VisionStateMachine/AutomaticModeStateMachine/SimulationMode": DENIED,
    "VisionSystem/RecipeManagement/AddRecipe": DENIED,
    "VisionSystem/RecipeManagement/RemoveRecipe": DENIED,
    "VisionSystem/RecipeManagement/PrepareRecipe": DENIED,
    "VisionSystem/RecipeManagement/UnprepareRecipe": DENIED,
    "VisionSystem/RecipeManagement/GetRecipeListFiltered": WATCH,
    "VisionSystem/RecipeManagement/ReleaseRecipeHandle": WATCH,
    "VisionSystem/RecipeManagement/Recipes/<recipe>/Prepare": DENIED,
    "VisionSystem/RecipeManagement/Recipes/<recipe>/Unprepare": DENIED,
    "VisionSystem/RecipeManagement/Recipes/<recipe>/Handle/Open": DENIED,
    "VisionSystem/RecipeManagement/Recipes/<recipe>/Handle/Write": DENIED,
    "VisionSystem/RecipeManagement/Recipes/<recipe>/Handle/Close": DENIED,
    "VisionSystem/RecipeManagement/Recipes/<recipe>/Handle/Read": DENIED,
    "VisionSystem/RecipeManagement/Recipes/<recipe>/Handle/GetPosition": DENIED,
    "VisionSystem/RecipeManagement/Recipes/<recipe>/Handle/SetPosition": DENIED,
    "VisionSystem/ResultManagement/GetResultById": WATCH,
    "VisionSystem/ResultManagement/GetResultComponentsById": WATCH,
    "VisionSystem/ResultManagement/GetResultListFiltered": WATCH,
    "VisionSystem/ResultManagement/ReleaseResultHandle": WATCH,
    "VisionSystem/SafetyStateManagement/ReportSafetyState": DENIED,
}


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory):
    work = tmp_path_factory.mktemp("actions")
    certs = work / "certs"
    write_users(work / "users.json", [UserEntry(n, r, hash_password(pw, 1000)) for n, (pw, r) in USERS.items()])
    (work / "line.toml").write_text(f'[service]\nusers_file = "users.json"\ncertificate_dir = "{certs}"\n')
    (work / "recipes").mkdir()
    (work / "recipes" / "bolts-only.toml").write_text(RECIPE_BOLTS)  # a recipe object with its own methods
    key, cert, uri = asyncio.run(make_client_certificate(work / "client", "plc"))
    (certs / "trusted").mkdir(parents=True)
    (certs / "trusted" / "plc.der").write_bytes(cert.read_bytes())
    serve = ServeProcess(work, "--config", str(work / "line.toml"))
    yield serve, Credentials(key, cert, uri, certs / "server-cert.der"), work
    assert serve.stop() == 0, "\n".join(serve.lines[-30:])


async def methods_under(client: Client, node: Node, path: tuple[str, ...], seen: set[ua.NodeId]) -> list[Any]:
    """(path, object, method) of every method reachable from `node` by hierarchical references."""
    found = []
    for ref in await node.get_references(refs=ua.ObjectIds.HierarchicalReferences):
        if not ref.IsForward or ref.NodeId in seen:
            continue
        seen.add(ref.NodeId)
        here = (*path, ref.BrowseName.Name)
        if ref.NodeClass == ua.NodeClass.Method:
            found.append((here, node, client.get_node(ref.NodeId)))
        elif ref.NodeClass in (ua.NodeClass.Object, ua.NodeClass.Variable):
            found += await methods_under(client, client.get_node(ref.NodeId), here, seen)
    return found


def key_of(path: tuple[str, ...]) -> str:
    parts = list(path)
    if "Recipes" in parts[:-1]:
        parts[parts.index("Recipes") + 1] = "<recipe>"
    return "/".join(parts)


def files(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


async def observed(client: Client, work: Path) -> dict[str, Any]:
    """What a side effect would change: states, SystemState (a hold shows there), safety, recipes, files."""
    mv = await client.get_namespace_index(MV_URI)
    app = await client.get_namespace_index("urn:pick-cell")
    vs = await client.nodes.objects.get_child([f"{app}:VisionSystem"])
    cell = await client.nodes.objects.get_child([f"{app}:Cell"])

    async def value(node: Node, *path: str) -> Any:
        return await (await node.get_child(list(path))).read_value()

    folder = await vs.get_child([f"{mv}:RecipeManagement", f"{mv}:Recipes"])
    system = await value(vs, f"{mv}:SystemState")
    return {
        "vision_state": (await value(vs, f"{mv}:VisionStateMachine", "0:CurrentState")).Text,
        "automatic": (
            await value(vs, f"{mv}:VisionStateMachine", f"{mv}:AutomaticModeStateMachine", "0:CurrentState")
        ).Text,
        "cell": [await value(cell, f"{app}:{n}") for n in ("VisionState", "CellState", "JobId", "Paused")],
        "system_state": (system.State, system.StateDescription),
        "safety": [
            await value(vs, f"{mv}:SafetyStateManagement", f"{mv}:{n}")
            for n in ("VisionSafetyTriggered", "VisionSafetyInformation")
        ],
        "recipe_objects": sorted(d.BrowseName.Name for d in await folder.get_children_descriptions()),
        "recipe_files": files(work / "recipes"),
        "calibration_files": files(work / "calibration") if (work / "calibration").is_dir() else {},
    }


async def outcome(parent: Node, method: Node) -> str:
    try:
        await parent.call_method(method)
    except ua.UaStatusCodeError as e:
        return ua.StatusCode(e.code).name
    return "Good"


def test_a_viewer_is_refused_every_state_changing_method_with_no_side_effect(served) -> None:
    serve, credentials, work = served
    url = f"opc.tcp://127.0.0.1:{serve.opcua_port}/cell"

    async def scenario() -> None:
        engineer = await secure_client(url, credentials, user="edna", password=USERS["edna"][0])
        viewer = await secure_client(url, credentials, user="vera", password=USERS["vera"][0])
        async with engineer, viewer:
            await engineer.load_data_type_definitions()
            mv = await engineer.get_namespace_index(MV_URI)
            app = await engineer.get_namespace_index("urn:pick-cell")
            recipes = await engineer.nodes.objects.get_child([f"{app}:VisionSystem", f"{mv}:RecipeManagement"])
            # a recipe being written (AddRecipe by the engineer): its Handle's methods are in the walk too
            pending = await recipes.call_method(
                f"{mv}:AddRecipe",
                ua.Variant(ua.RecipeIdExternalDataType(Id="kit-pending"), _T.ExtensionObject),
                ua.Variant(ua.ProductIdDataType(Id=""), _T.ExtensionObject),
            )
            assert pending[3] is True  # TransferRequired

            found = await methods_under(viewer, viewer.nodes.objects, (), set())
            ours = [(p, o, m) for p, o, m in found if m.nodeid.NamespaceIndex == app]
            standard = [(p, o, m) for p, o, m in found if m.nodeid.NamespaceIndex == 0]
            assert len(ours) + len(standard) == len(found), "a method in a namespace this test does not know"
            unknown = sorted({key_of(p) for p, _, _ in ours} - set(ACTIONS))
            assert not unknown, f"methods without an entry in ACTIONS (place them, with their role): {unknown}"
            assert {key_of(p) for p, _, _ in ours} == set(ACTIONS)  # every entry still served
            assert any("kit-pending" in p for p, _, _ in ours) and any("bolts-only" in p for p, _, _ in ours)

            before = await observed(viewer, work)
            answers = {}
            for path, parent, method in ours:
                if ACTIONS[key_of(path)] != HALT:
                    answers["/".join(path)] = (ACTIONS[key_of(path)], await outcome(parent, method))
            for path, parent, method in standard:
                answers["/".join(path)] = (UNBOUND, await outcome(parent, method))
            after = await observed(viewer, work)

            wrong = {
                p: got
                for p, (want, got) in answers.items()
                if (want in (DENIED, UNBOUND) and got != want) or (want == WATCH and got == DENIED)
            }
            assert not wrong, f"a viewer got other answers than the table's: {wrong}"
            assert sum(want == DENIED for want, _ in answers.values()) >= 30
            assert after == before
            assert before["vision_state"] == "Operational" and before["automatic"] == "Ready"
            assert before["recipe_objects"] == ["bolts-only", "kit-pending"]

    asyncio.run(scenario())
