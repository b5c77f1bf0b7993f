"""The cell as a Sparkplug B edge node against a real broker (Debian's mosquitto, started here on a
free port): births and every pick decoded by a listener, seq and bdSeq as the specification
says, a rebirth on request, the broker lost mid-shift while picks go on, and commands over MQTT
through the one command table. The line service runs in-process on the simulated cell."""

from __future__ import annotations

import time

import pytest

from cell.config import CellConfig
from cell.core.commands import Command, CommandRefused, VisionState
from cell.core.events import Interface, Origin, Role
from cell.service.shiftlog import read_shift
from cell.telemetry import metrics as M
from cell.telemetry.config import MqttConfig
from cell.telemetry.publisher import SparkplugPublisher
from cell.telemetry.sparkplug import DataType, Topics
from tests.mqtt_broker import (
    OPENSSL,
    Broker,
    Listener,
    Message,
    Proxy,
    make_tls,
    needs_mosquitto,
    picks_seen,
    wait_for,
)
from tests.test_service import picked, running, small_config

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240), needs_mosquitto]
V = VisionState
NO_FEEDER = CellConfig().sim.feeder.model_copy(update={"parts_per_minute": 0})


def telemetry_config(tmp_path, url: str, node: str, **mqtt) -> CellConfig:
    cfg = small_config(tmp_path)
    cfg.telemetry.mqtt = MqttConfig(
        url=url,
        edge_node_id=node,
        group_id="test-hall",
        reconnect_min_s=1.0,
        reconnect_max_s=2.0,
        keepalive_s=5,
        **mqtt,
    )
    return cfg


def births(listener: Listener, node: str, bd_seq: int | None = None, above: int | None = None) -> list[Message]:
    return [
        m
        for m in listener.of("NBIRTH", node)
        if (bd_seq is None or m.metrics["bdSeq"] == bd_seq) and (above is None or m.metrics["bdSeq"] > above)
    ]


def latest(listener: Listener, node: str, name: str):
    """The metric's value as a host holds it: the last birth or data message that carried it."""
    value = None
    for m in listener.all(node):
        if m.kind in ("DBIRTH", "DDATA") and name in m.metrics:
            value = m.metrics[name]
    return value


def wait_birth(
    listener: Listener, topics: Topics, bd_seq: int | None = None, above: int | None = None, timeout_s: float = 60.0
) -> Message:
    """An NBIRTH with this bdSeq (or one above); as a host does, ask for a rebirth (every 2 s) in case the
    listener joined after the cell's own birth."""
    asked = [0.0]

    def seen():
        found = births(listener, topics.edge_node_id, bd_seq, above)
        if not found and listener.connected.is_set() and time.monotonic() - asked[0] > 2.0:
            asked[0] = time.monotonic()
            listener.publish_metric(topics.node("NCMD"), M.REBIRTH, True)
        return found

    return wait_for(seen, timeout_s, f"NBIRTH with bdSeq {bd_seq if above is None else f'above {above}'}")[-1]


def assert_seq_in_order(listener: Listener, node: str) -> None:
    """seq: 0 at each NBIRTH, then +1 for every message (wrapping after 255); NDEATH carries none. Checked
    over what the listener saw on each of its connections (while it was away it missed messages)."""
    expected, connection = None, None
    for m in listener.all(node):
        if m.kind in ("NCMD", "DCMD"):  # a host's, not the cell's
            continue
        if m.kind == "NDEATH":
            assert m.seq is None
            continue
        if m.connection != connection:
            expected, connection = None, m.connection
        if m.kind == "NBIRTH":
            assert m.seq == 0
        elif expected is not None:
            assert m.seq == expected, f"{m.kind} seq {m.seq}, expected {expected}"
        expected = (m.seq + 1) % 256


def test_births_every_pick_rebirth_and_ndeath(tmp_path):
    with Broker(tmp_path) as broker:
        listener = Listener(broker.port)
        cfg = telemetry_config(tmp_path, broker.url, "cell-a")
        cfg.sim.feeder = NO_FEEDER
        topics = Topics("test-hall", "cell-a", "cell")
        with running(cfg) as service:
            dbirth = wait_for(lambda: listener.of("DBIRTH", "cell-a"), 30, "DBIRTH")[0]
            (nbirth,) = births(listener, "cell-a")
            assert (nbirth.seq, nbirth.metrics["bdSeq"], nbirth.metrics[M.REBIRTH]) == (0, 0, False)
            assert nbirth.datatypes == {s.name: s.dtype for s in M.NODE}
            assert nbirth.topic == "spBv1.0/test-hall/NBIRTH/cell-a" and dbirth.topic == topics.device("DBIRTH")
            assert dbirth.seq == 1 and dbirth.datatypes == {s.name: s.dtype for s in M.device_specs(False)}
            snap = service.snapshot()
            assert dbirth.metrics["Calibration/Id"] == snap.calibration.calibration_id != ""
            assert dbirth.metrics["Calibration/CV RMS mm"] == pytest.approx(snap.calibration.cv_rms_mm)
            assert wait_for(lambda: latest(listener, "cell-a", "State") == "Ready", 30, "State Ready")

            # commands are off: a DCMD is not even received; a rebirth request is (same session, same bdSeq)
            listener.publish_metric(topics.device("DCMD"), "Command/StartSingleJob", True)
            listener.publish_metric(topics.node("NCMD"), M.REBIRTH, True)
            wait_for(lambda: len(births(listener, "cell-a")) == 2, 30, "the rebirth")
            assert births(listener, "cell-a")[1].metrics["bdSeq"] == 0 and service.snapshot().vision_state == V.READY

            service.command(Command.START_SINGLE)
            wait_for(lambda: service.snapshot().vision_state == V.READY and picked(service) == 17, 120, "table cleared")
            wait_for(lambda: latest(listener, "cell-a", "Counters/Picked") == 17, 30, "the last count published")
            assert picks_seen(listener, "cell-a") == picked(service) == 17  # every pick, one DDATA each
            pick = next(m for m in listener.of("DDATA", "cell-a") if "Last Pick/Id" in m.metrics)
            assert pick.metrics["Last Pick/Class"] in ("bolt", "nut") and pick.metrics["Last Pick/Cycle ms"] > 0
            assert pick.metrics["Last Pick/Id"].startswith(snap.job_id or "")
            assert latest(listener, "cell-a", "Counters/Picked Bolts") == service.snapshot().counters.picked_of("bolt")
        ndeath = wait_for(lambda: listener.of("NDEATH", "cell-a"), 30, "NDEATH at stop")[0]
        assert ndeath.metrics == {"bdSeq": 0} and ndeath.datatypes == {"bdSeq": DataType.INT64}
        # bdSeq is kept in `data` beside the log folder: the next start continues at 1
        assert (tmp_path / "data" / "sparkplug-bdseq-test-hall-cell-a.json").read_text() == '{"bd_seq": 0}\n'
        assert all(m.qos == 0 and not m.retain for m in listener.all("cell-a") if m.kind != "NDEATH")
        assert_seq_in_order(listener, "cell-a")
        listener.close()


def test_broker_lost_mid_shift_picks_go_on_and_the_cell_rebirths(tmp_path):
    with Broker(tmp_path) as broker:
        proxy = Proxy(broker.port)  # the cell's network to the broker, which the test can cut
        host_side = Proxy(broker.port)  # the listener's way in: the broker may come back on another port
        listener = Listener(host_side.port)
        cfg = telemetry_config(tmp_path, proxy.url, "cell-b")
        topics = Topics("test-hall", "cell-b", "cell")
        with running(cfg) as service:
            wait_birth(listener, topics, bd_seq=0)
            service.command(Command.START_CONTINUOUS)
            wait_for(lambda: picked(service) >= 2, 120, "2 picks")

            proxy.cut()  # the broker sees the cell vanish: it publishes the Will
            ndeath = wait_for(lambda: listener.of("NDEATH", "cell-b"), 30, "the Will NDEATH")[0]
            assert ndeath.metrics == {"bdSeq": 0} and ndeath.seq is None
            wait_birth(listener, topics, bd_seq=1)  # reconnected: a new session, bdSeq + 1

            broker.kill()  # the whole broker gone: nothing can be published
            before = picked(service)
            wait_for(lambda: picked(service) >= before + 2, 120, "picks during the outage")
            warnings = service.snapshot().warnings
            assert any(w.source == "telemetry" and "unreachable" in w.reason for w in warnings)

            broker.start(new_port=True)
            proxy.target_port = host_side.target_port = broker.port
            wait_for(listener.connected.is_set, 30, "the listener back")
            # a new session: bdSeq + 1 for every CONNECT the cell sent meanwhile (through its network to
            # the dead broker each try's CONNECT went out and was cut)
            reborn = wait_birth(listener, topics, above=1)
            assert reborn.metrics[M.DROPPED] > 0  # updates lost while away, counted
            wait_for(lambda: not service.snapshot().warnings, 30, "the telemetry warning cleared")

            service.command(Command.STOP)
            wait_for(lambda: service.snapshot().vision_state == V.READY, 120, "Ready")
            final = picked(service)
            wait_for(lambda: latest(listener, "cell-b", "Counters/Picked") == final, 30, "the final count")
            assert final > before + 1
        listener.close()
        proxy.close()
        host_side.close()
    assert_seq_in_order(listener, "cell-b")


def test_commands_over_mqtt_through_the_command_table(tmp_path, monkeypatch):
    users = {"cell-c": "pw-cell-c", "scada": "pw-scada"}
    monkeypatch.setenv("CELL_MQTT_PASSWORD", users["cell-c"])
    with Broker(tmp_path, users=users) as broker:
        listener = Listener(broker.port, user="scada", password=users["scada"])
        cfg = telemetry_config(
            tmp_path,
            broker.url,
            "cell-c",
            user="cell-c",
            password_env="CELL_MQTT_PASSWORD",
            commands=True,
            command_role="operator",
        )
        cfg.sim.feeder = NO_FEEDER
        topics = Topics("test-hall", "cell-c", "cell")

        def answer(name: str, after: int) -> dict:
            def got():
                found = [
                    m for m in listener.of("DDATA", "cell-c")[after:] if m.metrics.get("Command/Last Name") == name
                ]
                return found[-1].metrics if found else None

            return wait_for(got, 30, f"the answer to {name}")

        def send(metric: str) -> int:
            n = len(listener.of("DDATA", "cell-c"))
            listener.publish_metric(topics.device("DCMD"), metric, True)
            return n

        with running(cfg) as service:
            dbirth = wait_for(lambda: listener.of("DBIRTH", "cell-c"), 30, "DBIRTH")[0]
            assert {s.name for s in M.COMMANDS} <= set(dbirth.metrics) and dbirth.metrics["Command/Stop"] is False
            wait_for(lambda: latest(listener, "cell-c", "State") == "Ready", 30, "Ready")

            refused = answer("Resume", send("Command/Resume"))  # not allowed in Ready: the same answer as OPC UA
            with pytest.raises(CommandRefused) as opcua:
                service.command(Command.RESUME, Origin(Interface.OPCUA, "plc", Role.OPERATOR))
            assert refused["Command/Last Accepted"] is False
            assert refused["Command/Last Refusal"] == opcua.value.reason.value == "invalid_state"
            assert refused["Command/Last Message"] == str(opcua.value)

            started = answer("StartSingleJob", send("Command/StartSingleJob"))
            assert started["Command/Last Accepted"] is True and started["Command/Last Refusal"] == ""
            assert started["Command/Last Job Id"] == service.snapshot().job_id != ""
            wait_for(lambda: picked(service) >= 1, 120, "a pick")
            stopped = answer("Stop", send("Command/Stop"))
            assert stopped["Command/Last Accepted"] is True
            wait_for(lambda: service.snapshot().vision_state == V.READY, 120, "Ready after Stop")

            # the role comes from the config: a viewer may not start the cell
            viewer_cfg = cfg.telemetry.mqtt.model_copy(
                update={"edge_node_id": "cell-c-viewer", "command_role": "viewer"}
            )
            viewer = SparkplugPublisher(viewer_cfg, service, users["cell-c"])
            viewer.start(service.bus)
            wait_for(lambda: listener.of("DBIRTH", "cell-c-viewer"), 30, "the viewer cell's DBIRTH")
            listener.publish_metric(
                Topics("test-hall", "cell-c-viewer", "cell").device("DCMD"), "Command/StartSingleJob", True
            )
            denied = wait_for(
                lambda: [m for m in listener.of("DDATA", "cell-c-viewer") if "Command/Last Refusal" in m.metrics],
                30,
                "denied",
            )[-1].metrics
            assert denied["Command/Last Accepted"] is False and denied["Command/Last Refusal"] == "access_denied"
            assert "needs the operator role" in denied["Command/Last Message"]
            viewer.close(service.bus)

            # a wrong password: the broker refuses the cell, the operator sees a warning, picking is not affected
            wrong = SparkplugPublisher(viewer_cfg.model_copy(update={"edge_node_id": "cell-c-wrong"}), service, "nope")
            wrong.start(service.bus)
            wait_for(lambda: any("refused" in w.reason for w in service.snapshot().warnings), 30, "the warning")
            wrong.close(service.bus)
            assert not listener.of("NBIRTH", "cell-c-wrong")
        commands = [
            e for e in read_shift(tmp_path / "logs") if e["kind"] == "command" and e["origin"]["interface"] == "mqtt"
        ]
        assert [(e["command"], e["accepted"], e["origin"]["user"], e["origin"]["role"]) for e in commands] == [
            ("Resume", False, "cell-c", "operator"),
            ("StartSingleJob", True, "cell-c", "operator"),
            ("Stop", True, "cell-c", "operator"),
            ("StartSingleJob", False, "cell-c", "viewer"),
        ]
        listener.close()


@pytest.mark.skipif(OPENSSL is None, reason="openssl is not installed: no test certificates can be made")
def test_tls_with_a_client_certificate_authenticates_the_cell_for_commands(tmp_path):
    tls = make_tls(tmp_path / "pki", clients=("cell-d", "scada"))
    with Broker(tmp_path, tls=tls) as broker:
        listener = Listener(broker.port, tls=(tls.ca, *tls.clients["scada"]))
        cert, key = tls.clients["cell-d"]
        cfg = telemetry_config(
            tmp_path,
            broker.url,
            "cell-d",
            ca_file=tls.ca,
            client_cert_file=cert,
            client_key_file=key,
            commands=True,
            command_role="operator",
        )
        cfg.sim.feeder = NO_FEEDER
        topics = Topics("test-hall", "cell-d", "cell")
        with running(cfg) as service:
            wait_for(lambda: listener.of("DBIRTH", "cell-d"), 30, "DBIRTH over TLS")
            wait_for(lambda: latest(listener, "cell-d", "State") == "Ready", 30, "Ready")
            listener.publish_metric(topics.device("DCMD"), "Command/StartSingleJob", True)
            wait_for(lambda: latest(listener, "cell-d", "Command/Last Accepted") is True, 30, "the start accepted")
            wait_for(lambda: service.snapshot().vision_state == V.READY and picked(service) == 17, 120, "table cleared")
            wait_for(lambda: latest(listener, "cell-d", "Counters/Picked") == 17, 30, "the count over TLS")
        commands = [
            e for e in read_shift(tmp_path / "logs") if e["kind"] == "command" and e["origin"]["interface"] == "mqtt"
        ]
        assert [(e["command"], e["accepted"], e["origin"]["user"]) for e in commands] == [
            ("StartSingleJob", True, "cell-d")
        ]
        listener.close()
