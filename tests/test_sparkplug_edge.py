"""The Sparkplug B edge node's own rules against a real broker (Debian's mosquitto on a free port),
driven by a line service stand-in whose snapshot the test moves: a command whose handling fails
unexpectedly, an MQTT command without a configured role, a birth the client could not send, a
snapshot racing a birth, and bdSeq across restarts."""

from __future__ import annotations

import logging
import select
import threading
import time
from collections.abc import Callable
from typing import Any

import pytest

from cell.core.commands import Command, CommandResult, VisionState
from cell.core.eventbus import EventBus
from cell.core.events import Origin, SnapshotChanged
from cell.core.parts import BUILT_IN_PARTS
from cell.core.records import Counters, Snapshot
from cell.telemetry.config import MqttConfig
from cell.telemetry.publisher import SparkplugPublisher
from cell.telemetry.sparkplug import Topics
from tests.mqtt_broker import Broker, Listener, Proxy, needs_mosquitto, wait_for

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240), needs_mosquitto]

GROUP = "test-hall"
USERS = {"cell-e": "pw-cell-e", "scada": "pw-scada"}


class Plant:
    """What the publisher needs of a line service (ServiceView): a snapshot whose picked count the test
    moves (`bump`, each announced on the bus as the service does), and a command handler the test sets."""

    def __init__(self) -> None:
        self.bus = EventBus()
        self.parts = BUILT_IN_PARTS
        self.picked = 0
        self.moving = False  # True: each snapshot counts one more pick (every read a change to publish)
        self.padding = 0  # characters added to the cell state (the runner's step): larger messages
        self._lock = threading.Lock()
        self.calls: list[tuple[Command, Origin]] = []
        self.on_command: Callable[[Command, Origin], CommandResult] = lambda c, o: CommandResult(c)
        self.on_snapshot: Callable[[int], None] = lambda n: None  # called with the count a snapshot read
        self.warnings: dict[str, str] = {}

    def snapshot(self) -> Snapshot:
        with self._lock:
            self.picked += self.moving
            n = self.picked
        self.on_snapshot(n)
        state = f"IDLE {n:.>{self.padding}}" if self.padding else "IDLE"  # padded: changes with the count
        return Snapshot(
            VisionState.READY, state, False, False, Counters(picked=(("bolt", n),)), 0.0, (), None, None, 0, frozenset()
        )

    def command(self, command: Command, origin: Any = None, request: Any = None) -> CommandResult:
        self.calls.append((command, origin))
        return self.on_command(command, origin)

    def raise_warning(self, key: str, reason: str, hint: str, source: str) -> None:
        self.warnings[key] = reason

    def clear_warning(self, key: str) -> None:
        self.warnings.pop(key, None)

    def bump(self) -> int:
        with self._lock:
            self.picked += 1
            n = self.picked
        self.bus.emit(SnapshotChanged(what="counters"))
        return n


def edge_config(url: str, node: str, **mqtt: Any) -> MqttConfig:
    settings: dict[str, Any] = {"reconnect_min_s": 1.0, "reconnect_max_s": 2.0, "keepalive_s": 30} | mqtt
    return MqttConfig(url=url, edge_node_id=node, group_id=GROUP, **settings)


def picked_in(listener: Listener, node: str, kind: str = "DDATA") -> list[int]:
    return [m.metrics["Counters/Picked"] for m in listener.of(kind, node) if "Counters/Picked" in m.metrics]


def answers(listener: Listener, node: str) -> list[dict[str, Any]]:
    return [m.metrics for m in listener.of("DDATA", node) if "Command/Last Name" in m.metrics]


@pytest.fixture
def plant():
    return Plant()


def test_a_command_failing_unexpectedly_is_answered_as_refused_and_telemetry_goes_on(tmp_path, plant, caplog):
    """An audit write failure, a bug: anything but a refusal escaping the command callback used to
    end paho's network thread, and with it every publish, without a word."""

    def broken(command: Command, origin: Origin) -> CommandResult:
        raise OSError(28, "No space left on device", "logs/audit.jsonl")

    plant.on_command = broken
    with Broker(tmp_path, users=USERS) as broker:
        listener = Listener(broker.port, user="scada", password=USERS["scada"])
        cfg = edge_config(
            broker.url, "cell-e", user="cell-e", password_env="CELL_PW", commands=True, command_role="operator"
        )
        topics = Topics(GROUP, "cell-e", "cell")
        publisher = SparkplugPublisher(cfg, plant, USERS["cell-e"])
        publisher.start(plant.bus)
        try:
            wait_for(lambda: listener.of("DBIRTH", "cell-e"), 30, "DBIRTH")
            with caplog.at_level(logging.ERROR, logger="cell.telemetry.publisher"):
                listener.publish_metric(topics.device("DCMD"), "Command/StartSingleJob", True)
                answer = wait_for(lambda: answers(listener, "cell-e"), 30, "the answer to StartSingleJob")[-1]
            assert answer["Command/Last Name"] == "StartSingleJob" and answer["Command/Last Accepted"] is False
            assert answer["Command/Last Refusal"] == "internal_error"
            assert "No space left on device" in answer["Command/Last Message"]
            assert any("StartSingleJob" in r.getMessage() and r.exc_info for r in caplog.records)
            assert [c for c, _ in plant.calls] == [Command.START_SINGLE]

            n = plant.bump()  # the network thread still runs: the next change is published
            wait_for(lambda: n in picked_in(listener, "cell-e"), 30, "the next DDATA")
            listener.publish_metric(topics.device("DCMD"), "Command/Stop", True)  # and commands still arrive
            wait_for(lambda: len(answers(listener, "cell-e")) == 2, 30, "the answer to Stop")
            assert answers(listener, "cell-e")[-1]["Command/Last Refusal"] == "internal_error"
            assert publisher.stats()["command_errors"] == 2
        finally:
            publisher.close(plant.bus)
        listener.close()


def test_mqtt_commands_without_a_configured_role_may_do_nothing(tmp_path, plant):
    """commands = true without command_role: every command is refused and none reaches the service."""
    with Broker(tmp_path, users=USERS) as broker:
        listener = Listener(broker.port, user="scada", password=USERS["scada"])
        cfg = edge_config(broker.url, "cell-f", user="cell-e", password_env="CELL_PW", commands=True)
        assert cfg.command_role is None
        topics = Topics(GROUP, "cell-f", "cell")
        publisher = SparkplugPublisher(cfg, plant, USERS["cell-e"])
        publisher.start(plant.bus)
        try:
            wait_for(lambda: listener.of("DBIRTH", "cell-f"), 30, "DBIRTH")
            listener.publish_metric(topics.device("DCMD"), "Command/StartContinuous", True)
            answer = wait_for(lambda: answers(listener, "cell-f"), 30, "the answer")[-1]
            assert answer["Command/Last Accepted"] is False and answer["Command/Last Refusal"] == "access_denied"
            assert "command_role" in answer["Command/Last Message"]
            assert plant.calls == []
        finally:
            publisher.close(plant.bus)
        listener.close()


def test_bd_seq_continues_across_publisher_instances_sharing_the_state_folder(tmp_path, plant):
    """Each process used to start at bdSeq 0: a host could take the new session's birth for the old one's."""
    state = tmp_path / "state"
    with Broker(tmp_path) as broker:
        listener = Listener(broker.port)
        for run, want in enumerate((0, 1, 2)):
            publisher = SparkplugPublisher(edge_config(broker.url, "cell-g"), plant, state_dir=state)
            publisher.start(plant.bus)
            try:
                wait_for(lambda: len(listener.of("NBIRTH", "cell-g")) == run + 1, 30, f"the NBIRTH of run {run}")
            finally:
                publisher.close(plant.bus)
            wait_for(lambda: len(listener.of("NDEATH", "cell-g")) == run + 1, 30, f"the NDEATH of run {run}")
            assert listener.of("NBIRTH", "cell-g")[-1].metrics["bdSeq"] == want
            assert listener.of("NDEATH", "cell-g")[-1].metrics == {"bdSeq": want}
        listener.close()
    (kept,) = state.iterdir()  # one small file, no temporary left behind
    assert kept.name == "sparkplug-bdseq-test-hall-cell-g.json"


def test_bd_seq_continues_from_the_kept_file_and_wraps_after_255(tmp_path, plant):
    state = tmp_path / "state"
    cfg = edge_config("mqtt://127.0.0.1:1", "cell-h")
    state.mkdir()
    kept = state / "sparkplug-bdseq-test-hall-cell-h.json"
    kept.write_text('{"bd_seq": 7}\n')  # the last session's
    assert SparkplugPublisher(cfg, plant, state_dir=state).bd_seq == 8
    kept.write_text('{"bd_seq": 255}\n')
    assert SparkplugPublisher(cfg, plant, state_dir=state).bd_seq == 0
    kept.write_text("not json")
    assert SparkplugPublisher(cfg, plant, state_dir=state).bd_seq == 0  # unreadable: start again, said in the log


def older_than_their_birth(listener: Listener, node: str) -> list[tuple[int, int]]:
    """(birth's count, data's count) for each DDATA whose picked count is below the DBIRTH before it."""
    born, older = None, []
    for m in listener.all(node):
        if m.kind == "DBIRTH":
            born = m.metrics["Counters/Picked"]
        elif m.kind == "DDATA" and born is not None and m.metrics.get("Counters/Picked", born) < born:
            older.append((born, m.metrics["Counters/Picked"]))
    return older


def test_no_data_after_a_birth_carries_values_older_than_the_birth(tmp_path, plant):
    """The bus thread read the snapshot, then took the lock to publish it: a birth in between (a rebirth
    request on paho's thread) went out with newer values, and the older DDATA followed it."""
    with Broker(tmp_path) as broker:
        listener = Listener(broker.port)
        topics = Topics(GROUP, "cell-i", "cell")
        publisher = SparkplugPublisher(edge_config(broker.url, "cell-i"), plant, state_dir=tmp_path / "state")
        armed, inside = threading.Event(), threading.Event()

        def slow_read(n: int) -> None:
            """The bus thread's read (armed once): give a birth up to 5 s to come between read and publish."""
            if not armed.is_set():
                return
            armed.clear()
            births = publisher.births
            inside.set()
            deadline = time.monotonic() + 5.0
            while publisher.births == births and time.monotonic() < deadline:
                time.sleep(0.01)

        plant.on_snapshot = slow_read
        publisher.start(plant.bus)
        try:
            wait_for(lambda: listener.of("DBIRTH", "cell-i"), 30, "DBIRTH")
            armed.set()
            n = plant.bump()  # the bus thread reads n ...
            assert inside.wait(30), "the bus thread's snapshot"
            with plant._lock:
                plant.picked += 1  # ... the cell moves on (announced later) ...
            listener.publish_metric(topics.node("NCMD"), "Node Control/Rebirth", True)  # ... a host asks a rebirth
            wait_for(lambda: len(listener.of("DBIRTH", "cell-i")) == 2, 30, "the rebirth")
            assert listener.of("DBIRTH", "cell-i")[-1].metrics["Counters/Picked"] == n + 1
            last = plant.bump()
            wait_for(lambda: last in picked_in(listener, "cell-i"), 30, "the next DDATA")
            assert older_than_their_birth(listener, "cell-i") == []
        finally:
            publisher.close(plant.bus)
        listener.close()


def test_a_birth_the_client_could_not_send_is_sent_again_without_a_reconnect(tmp_path, plant):
    """A stalled link fills the MQTT client's queue (unsent_max); a rebirth asked meanwhile could not be
    handed over. The node stayed unborn while connected: every DDATA dropped until a reconnect."""
    with Broker(tmp_path) as broker:
        link = Proxy(broker.port, receive_buffer=4096)  # the cell's way to the broker, which the test stalls
        listener = Listener(broker.port)
        topics = Topics(GROUP, "cell-j", "cell")
        cfg = edge_config(link.url, "cell-j", unsent_max=10, keepalive_s=120, queue_max=100_000)
        publisher = SparkplugPublisher(cfg, plant, state_dir=tmp_path / "state")
        publisher.start(plant.bus)
        try:
            wait_for(lambda: listener.of("DBIRTH", "cell-j"), 30, "DBIRTH")
            link.hold()
            # the cell goes on changing (every snapshot a new count) until its socket is full and then the
            # client's queue: the socket no longer writable (the link takes nothing), and 10,000 updates
            # dropped in a row with none handed over (paho had its turns to write and could not)
            plant.moving, plant.padding = True, 8000
            frozen = {"published": -1, "dropped": 0}

            def queue_stays_full() -> bool:
                for _ in range(2000):
                    plant.bus.emit(SnapshotChanged(what="counters"))
                s = publisher.stats()
                if s["published"] != frozen["published"]:
                    frozen.update(published=s["published"], dropped=s["dropped"])
                writable = select.select([], [publisher.client.socket()], [], 0)[1]
                return not writable and s["dropped"] - frozen["dropped"] >= 10_000

            wait_for(queue_stays_full, 120, "the client's queue full behind the stalled link")
            plant.moving = False
            listener.publish_metric(topics.node("NCMD"), "Node Control/Rebirth", True)
            wait_for(lambda: not publisher.born, 30, "the rebirth not handed over")
            assert publisher.stats()["births"] == 1  # the first one only

            link.release()  # the link flows again: the birth goes out on the same connection
            wait_for(lambda: len(listener.of("DBIRTH", "cell-j")) == 2, 30, "the birth sent again")
            n = plant.bump()
            wait_for(lambda: n in picked_in(listener, "cell-j"), 30, "data after the new birth")
            births = listener.of("NBIRTH", "cell-j")
            assert [b.metrics["bdSeq"] for b in births] == [0, 0]  # the same session: no reconnect
            assert listener.of("NDEATH", "cell-j") == [] and publisher.stats()["births"] == 2
            assert publisher.stats()["births_dropped"] >= 1
            assert older_than_their_birth(listener, "cell-j") == []
        finally:
            publisher.close(plant.bus)
            link.close()
        listener.close()
