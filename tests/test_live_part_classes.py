"""Part classes grown while the service runs (issue 30): a type taught on the screen's Teach page, or a recipe
added with taught types new to the service, is counted by every interface at once, without a restart:
OPC UA gets its Picked<Plural> variable, Sparkplug sends its births again with the new counter, /metrics and
the screen's state show it; nothing is ever taken away. One event on the bus says so (PartClassesChanged).

The real line service in-process over the simulated cell whose table holds L brackets alone
(tests/test_teach_screen.py), its OPC UA server read by asyncua's client, Sparkplug read from a real
mosquitto, the screen's Starlette app."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any

import pytest
from asyncua import Client, ua

from cell.audit import read_events
from cell.core.commands import Command, RecipeRequest, VisionState
from cell.core.events import PartClassesChanged
from cell.service.opcua import OpcUaServer
from cell.telemetry import metrics as M
from cell.telemetry.config import MqttConfig
from cell.telemetry.sparkplug import Topics
from tests.mqtt_broker import Broker, Listener, needs_mosquitto, wait_for
from tests.ports import free_port
from tests.test_mqtt_telemetry import NO_FEEDER, births, latest
from tests.test_opcua import Cell
from tests.test_screen_action_table import served
from tests.test_service import running, small_config
from tests.test_teach_screen import USERS, learn, logged_in, teach_config

V = VisionState
NODE = "cell-live"
RECIPE = "brackets"


def kit(*types: str) -> str:
    """A recipe with taught types (AddRecipe checks the text; the models are read when it is prepared)."""
    return "".join(f'[types.{t}]\nmodel = "{t}.json"\nmodel_sha256 = "{"0" * 64}"\nheight_mm = 3.0\n' for t in types)


def grown_events(service) -> tuple[list[PartClassesChanged], Any]:
    seen: list[PartClassesChanged] = []
    sub = service.subscribe("test-grown", seen.append, kinds=(PartClassesChanged,))
    return seen, sub


def test_a_recipe_with_new_types_grows_the_registry_once_and_never_shrinks_it(tmp_path, caplog):
    cfg = small_config(tmp_path)
    cfg.service.machine_vision.recipes_dir = tmp_path / "recipes"
    with running(cfg) as service:
        assert service.parts.names == ("bolt", "nut")
        seen, sub = grown_events(service)
        service.command(Command.ADD_RECIPE, request=RecipeRequest("kit", kit("l-bracket", "spacer")))
        assert service.parts.names == ("bolt", "nut", "l-bracket", "spacer")
        # the same types again, and a type whose counter would be l-bracket's (picked_l_brackets): no new class
        service.command(Command.ADD_RECIPE, request=RecipeRequest("again", kit("spacer")))
        with caplog.at_level(logging.WARNING, logger="cell.service.service"):
            service.command(Command.ADD_RECIPE, request=RecipeRequest("clash", kit("l_bracket")))
        assert "recipe clash: the taught type l_bracket gets no counter of its own" in caplog.text
        service.command(Command.REMOVE_RECIPE, request=RecipeRequest("kit"))  # its classes stay counted
        assert service.parts.names == ("bolt", "nut", "l-bracket", "spacer")
        service.bus.wait_idle(5.0)
        assert [(e.recipe, e.added, e.parts.names) for e in seen] == [
            ("kit", ("l-bracket", "spacer"), ("bolt", "nut", "l-bracket", "spacer"))
        ]
        assert service.snapshot().counters.picked_of("spacer") == 0
        service.unsubscribe(sub)
    events = [e for f in sorted((tmp_path / "logs").glob("cell-*.jsonl")) for e in read_events(f)]
    (grown,) = [e for e in events if e["kind"] == "part_classes"]
    assert grown["recipe"] == "kit" and grown["added"] == ["l-bracket", "spacer"]
    assert grown["classes"] == ["bolt", "nut", "l-bracket", "spacer"]


def metrics_counter(text: str, key: str) -> float | None:
    found = re.search(rf'^cell_shift_parts\{{counter="{key}"\}} (\S+)$', text, re.M)
    return None if found is None else float(found.group(1))


async def until(check: Callable[[], Awaitable[Any]], what: str, timeout_s: float = 30.0) -> Any:
    """The first true value of `check()`, asked again every 50 ms."""
    end = asyncio.get_running_loop().time() + timeout_s
    while not (value := await check()):
        assert asyncio.get_running_loop().time() < end, f"timed out waiting for {what}"
        await asyncio.sleep(0.05)
    return value


async def ua_names(cell: Cell) -> list[str]:
    return [(await n.read_browse_name()).Name for n in await cell.node.get_children()]


@pytest.mark.timeout(120)
@needs_mosquitto
def test_a_type_taught_while_serving_is_counted_at_once_by_opcua_sparkplug_metrics_and_the_screen(tmp_path):
    with Broker(tmp_path) as broker:
        listener = Listener(broker.port)
        cfg = teach_config(tmp_path)
        cfg.sim.feeder = NO_FEEDER
        cfg.service.opcua_port = free_port()
        cfg.telemetry.mqtt = MqttConfig(url=broker.url, edge_node_id=NODE, group_id="test-hall", keepalive_s=5)
        topics = Topics("test-hall", NODE, "cell")
        try:
            with served(tmp_path, None, cfg, USERS) as (service, app, cfg, _users):
                asyncio.run(asyncio.wait_for(taught_while_serving(service, app, cfg, listener, topics), 100))
        finally:
            listener.close()


@contextlib.asynccontextmanager
async def loopback_client(service, cfg) -> AsyncIterator[Client]:
    """The service's OPC UA server on loopback without users (the screen's users stay the screen's),
    and a client of it."""
    loopback = cfg.model_copy(deep=True)
    loopback.service.users_file = None
    server = OpcUaServer(service, loopback)
    await server.start()
    try:
        url = f"opc.tcp://127.0.0.1:{cfg.service.opcua_port}/{cfg.service.opcua_path}"
        async with Client(url, timeout=10) as client:
            yield client
    finally:
        await server.stop()


async def taught_while_serving(service, app, cfg, listener, topics) -> None:
    async with loopback_client(service, cfg) as client:
        cell = await Cell(client).open()
        await through_every_interface(service, app, listener, topics, cell)


async def through_every_interface(service, app, listener, topics, cell: Cell) -> None:
    # the listener was there before the service: it sees the first births (no rebirth asked for)
    await asyncio.to_thread(wait_for, lambda: listener.of("DBIRTH", NODE), 30, "the first DBIRTH")
    first = births(listener, NODE)
    screen = await asyncio.to_thread(logged_in, app, "erik")
    dbirth = listener.of("DBIRTH", NODE)[-1]
    assert "Counters/Picked Brackets" not in dbirth.metrics and "PickedBrackets" not in await ua_names(cell)
    assert metrics_counter((await asyncio.to_thread(screen.get, "/metrics")).text, "picked_brackets") is None

    def teach() -> None:  # the Teach page: capture, learn, confirm into a new recipe with a bin
        session = screen.post("/api/teach/capture", json={}).json()["session"]
        assert learn(screen, session).status_code == 200
        confirmed = screen.post(
            f"/api/teach/{session}/confirm", json={"recipe_id": RECIPE, "bin_robot_mm": [200, 160.5, 60]}
        )
        assert confirmed.status_code == 200, confirmed.text

    model_changes: list[Any] = []
    handler = type("Handler", (), {"event_notification": lambda self, event: model_changes.append(event)})()
    subscription = await cell.client.create_subscription(50, handler)
    await subscription.subscribe_events(cell.node, ua.ObjectIds.GeneralModelChangeEventType)
    await asyncio.to_thread(teach)
    assert service.parts.names == ("bolt", "nut", "bracket")

    # OPC UA: a variable of its own, after Cell's other variables, reading 0
    await until(lambda: has_variable(cell, "PickedBrackets"), "PickedBrackets on OPC UA")
    assert (await ua_names(cell))[-1] == "PickedBrackets" and await cell.read("PickedBrackets") == 0
    # ... and says so: a GeneralModelChangeEvent from Cell naming the new node (NodeAdded)
    await until(lambda: asyncio.sleep(0, model_changes), "the GeneralModelChangeEvent")
    (change,) = model_changes[0].Changes
    assert change.Verb == 1 and change.Affected == (await cell.var("PickedBrackets")).nodeid
    await subscription.delete()
    # Sparkplug: the births again, same session (bdSeq), the new counter in the DBIRTH with its type
    reborn = await until(
        lambda: asyncio.to_thread(
            lambda: [m for m in listener.of("DBIRTH", NODE) if "Counters/Picked Brackets" in m.metrics]
        ),
        "a DBIRTH with Counters/Picked Brackets",
    )
    assert reborn[0].metrics["Counters/Picked Brackets"] == 0
    assert reborn[0].datatypes["Counters/Picked Brackets"] == M.D.UINT64
    born = births(listener, NODE)
    assert len(born) == len(first) + 1 and {b.metrics["bdSeq"] for b in born} == {first[0].metrics["bdSeq"]}
    # /metrics and the screen's state
    text = (await asyncio.to_thread(screen.get, "/metrics")).text
    assert metrics_counter(text, "picked_brackets") == 0
    state = (await asyncio.to_thread(screen.get, "/api/state")).json()
    assert {"key": "picked_brackets", "label": "Brackets"} in state["part_classes"]
    assert state["counters"]["picked_brackets"] == 0

    # prepared and run: the brackets counted everywhere (the table holds three)
    await asyncio.to_thread(service.command, Command.PREPARE_RECIPE, request=RecipeRequest(RECIPE))
    await asyncio.to_thread(service.command, Command.START_SINGLE)
    await asyncio.to_thread(
        wait_for,
        lambda: service.snapshot().vision_state == V.READY and service.snapshot().counters.picked_of("bracket") == 3,
        60,
        "three brackets picked",
    )
    await until(lambda: read_is(cell, "PickedBrackets", 3), "PickedBrackets 3 on OPC UA")
    await asyncio.to_thread(
        wait_for, lambda: latest(listener, NODE, "Counters/Picked Brackets") == 3, 30, "Sparkplug's count"
    )
    assert metrics_counter((await asyncio.to_thread(screen.get, "/metrics")).text, "picked_brackets") == 3
    assert (await asyncio.to_thread(screen.get, "/api/state")).json()["counters"]["picked_brackets"] == 3
    assert len(births(listener, NODE)) == len(born)  # preparing the recipe grew nothing: no birth more
    ddata = [m for m in listener.all(NODE) if m.kind in ("DBIRTH", "DDATA") and "Counters/Picked Brackets" in m.metrics]
    assert ddata[0].kind == "DBIRTH"  # no DDATA names the counter before the birth that announced it
    screen.close()


async def has_variable(cell: Cell, name: str) -> bool:
    return name in await ua_names(cell)


async def read_is(cell: Cell, name: str, value: int) -> bool:
    return bool(await cell.read(name) == value)


@pytest.mark.timeout(120)
def test_prepare_recipe_over_opcua_of_a_type_without_a_bin_says_so_in_a_vision_information_event(tmp_path):
    """OPC 40100-1's PrepareRecipe answers InternalId, IsCompleted and Error (an Int32, 0 for OK): no words.
    The recipe is prepared (Error 0); that its taught type has no bin goes out as a VisionInformationEvent
    from the VisionSystem, in the words the service's log has."""
    from tests.test_mv_opcua import Events, SpecClient, ext

    cfg = teach_config(tmp_path)
    cfg.service.opcua_port = free_port()
    with served(tmp_path, None, cfg, USERS) as (service, app, cfg, _users):
        with logged_in(app, "erik") as screen:
            session = screen.post("/api/teach/capture", json={}).json()["session"]
            assert learn(screen, session).status_code == 200
            later = screen.post(f"/api/teach/{session}/confirm", json={"recipe_id": "later", "bin_robot_mm": None})
            assert later.status_code == 200, later.text

        async def prepare_over_opcua() -> None:
            async with loopback_client(service, cfg) as client:
                s = await SpecClient(client).setup()
                handler = Events()
                sub = await client.create_subscription(50, handler)
                info_type = await client.nodes.base_event_type.get_child(
                    [f"{s.mv}:VisionEventType", f"{s.mv}:VisionInformationEventType"]
                )
                await sub.subscribe_events(s.vs, info_type)
                prepare = (ext(ua.RecipeIdExternalDataType(Id="later")), ext(ua.RecipeIdInternalDataType(Id="")))
                internal, completed, error = await s.call(s.recipes, "PrepareRecipe", *prepare)
                assert (internal.Id, completed, error) == ("later", True, 0)
                (said,) = await handler.wait(lambda e: "no bin" in e.Message.Text, 1)
                assert said.Message.Text == (
                    "recipe later: bracket has no bin: found and counted but left on the table "
                    "(give types.NAME.bin_robot_mm, or teach again with --bin-robot-mm X Y Z or --bin-of TYPE)"
                )
                assert said.Severity <= 300  # low: nothing to acknowledge
                await sub.delete()

        asyncio.run(asyncio.wait_for(prepare_over_opcua(), 100))
        assert service.snapshot().recipe == "later"
