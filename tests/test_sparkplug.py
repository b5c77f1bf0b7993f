"""Sparkplug B payloads, topics and sequence numbers, and the `[telemetry.mqtt]` config: no broker.

The encoding is checked against bytes written out by hand from protobuf's wire rules and the
specification's field numbers (Payload: timestamp 1, metrics 2, seq 3; Metric: name 1,
timestamp 3, datatype 4, is_null 7, int 10, long 11, double 13, boolean 14, string 15)."""

from __future__ import annotations

import struct

import pytest

from cell.config import load_config
from cell.errors import ConfigError
from cell.telemetry.config import MqttConfig
from cell.telemetry.publisher import password_from_env
from cell.telemetry.sparkplug import DataType, Metric, Topics, decode, next_seq, parse_topic, payload, value_of

pytestmark = pytest.mark.timeout(30)


def varint(n: int) -> bytes:
    out = bytearray()
    while True:
        byte, n = n & 0x7F, n >> 7
        out.append(byte | (0x80 if n else 0))
        if not n:
            return bytes(out)


def key(field: int, wire: int) -> bytes:
    return varint(field << 3 | wire)


def length_delimited(field: int, body: bytes) -> bytes:
    return key(field, 2) + varint(len(body)) + body


def test_a_birth_payload_is_the_specification_s_bytes():
    got = payload(
        [
            Metric("bdSeq", DataType.INT64, 3, timestamp_ms=1000),
            Metric("Node Control/Rebirth", DataType.BOOLEAN, False, timestamp_ms=1000),
            Metric("Rate", DataType.DOUBLE, 2.5, timestamp_ms=1000),
            Metric("State", DataType.STRING, "Ready", timestamp_ms=1000),
            Metric("Count", DataType.UINT32, 300, timestamp_ms=1000),
        ],
        seq=0,
        birth=True,
        timestamp_ms=1234,
    )

    def metric(name: str, datatype: int, value: bytes) -> bytes:
        return length_delimited(1, name.encode()) + key(3, 0) + varint(1000) + key(4, 0) + varint(datatype) + value

    want = key(1, 0) + varint(1234)
    want += length_delimited(2, metric("bdSeq", 4, key(11, 0) + varint(3)))
    want += length_delimited(2, metric("Node Control/Rebirth", 11, key(14, 0) + varint(0)))
    want += length_delimited(2, metric("Rate", 10, key(13, 1) + struct.pack("<d", 2.5)))
    want += length_delimited(2, metric("State", 12, length_delimited(15, b"Ready")))
    want += length_delimited(2, metric("Count", 7, key(10, 0) + varint(300)))
    want += key(3, 0) + varint(0)
    assert got == want


def test_data_carries_no_datatype_death_no_seq_and_none_is_null():
    data = decode(payload([Metric("Cycle", DataType.DOUBLE, None, 5)], seq=7))
    (m,) = data.metrics
    assert data.seq == 7 and not m.HasField("datatype") and m.is_null and value_of(m) is None
    death = decode(payload([Metric("bdSeq", DataType.INT64, 0)], seq=None))
    assert not death.HasField("seq") and death.HasField("timestamp") and death.metrics[0].timestamp > 0
    nan = decode(payload([Metric("x", DataType.DOUBLE, float("nan"))], seq=1, birth=True)).metrics[0]
    assert nan.is_null and nan.datatype == DataType.DOUBLE


@pytest.mark.parametrize(
    "dtype, value, field, raw",
    [
        (DataType.INT8, -2, "int_value", 2**32 - 2),
        (DataType.INT32, -(2**31), "int_value", 2**31),
        (DataType.INT64, -1, "long_value", 2**64 - 1),
        (DataType.UINT64, 2**63, "long_value", 2**63),
        (DataType.INT16, 1234, "int_value", 1234),
    ],
)
def test_signed_integers_are_two_s_complement_in_the_unsigned_fields(dtype, value, field, raw):
    m = decode(payload([Metric("n", dtype, value)], seq=0, birth=True)).metrics[0]
    assert m.WhichOneof("value") == field and getattr(m, field) == raw
    assert value_of(m) == value


def test_seq_and_bdseq_wrap_after_255():
    assert [next_seq(s) for s in (0, 1, 254, 255)] == [1, 2, 255, 0]


def test_topics():
    t = Topics("plant-1", "line-pc-7", "cell")
    assert t.node("NBIRTH") == "spBv1.0/plant-1/NBIRTH/line-pc-7"
    assert t.device("DDATA") == "spBv1.0/plant-1/DDATA/line-pc-7/cell"
    assert parse_topic(t.device("DCMD")) == ("plant-1", "DCMD", "line-pc-7", "cell")
    assert parse_topic(t.node("NDEATH")) == ("plant-1", "NDEATH", "line-pc-7", None)
    assert parse_topic("spBv1.0/STATE/host") is None and parse_topic("other/a/b/c") is None


def test_garbage_is_not_a_payload():
    from google.protobuf.message import DecodeError

    with pytest.raises(DecodeError):
        decode(b"\xff\xff\xff")


# ---- [telemetry.mqtt] ------------------------------------------------------------------------------
def write(tmp_path, text: str):
    path = tmp_path / "cell.toml"
    path.write_text(text)
    return path


def test_off_by_default_and_edge_node_defaults_to_the_host_name():
    cfg = load_config(None).telemetry.mqtt
    assert not cfg.enabled and not cfg.commands and cfg.command_role is None  # no role: MQTT may do nothing
    assert cfg.edge_node_id and not set("+/#") & set(cfg.edge_node_id)


def test_a_full_section_loads(tmp_path):
    cfg = load_config(
        write(
            tmp_path,
            '[telemetry.mqtt]\nurl = "mqtts://broker.plant:8884"\nuser = "cell-7"\npassword_env = "CELL_MQTT_PASSWORD"\n'
            'group_id = "hall-2"\nedge_node_id = "line-pc-7"\ndevice_id = "cell"\ncommands = true\n'
            'command_role = "viewer"\n',
        )
    ).telemetry.mqtt
    assert (cfg.host, cfg.port, cfg.tls, cfg.authenticated) == ("broker.plant", 8884, True, True)
    assert MqttConfig(url="mqtt://b").port == 1883 and MqttConfig(url="mqtts://b").port == 8883


@pytest.mark.parametrize(
    "section, message",
    [
        ('url = "http://broker"', "give mqtt://HOST[:PORT] or mqtts://HOST[:PORT]"),
        ('url = "mqtt://user:secret@broker"', "no user or password in the url"),
        ('url = "mqtt://broker:99999"', "telemetry.mqtt.url"),
        ('url = "mqtt://b"\nuser = "cell"', "give both user and password_env"),
        ('url = "mqtt://b"\npassword = "secret"', "telemetry.mqtt.password: Extra inputs are not permitted"),
        ('url = "mqtt://b"\ncommands = true', "commands needs an authenticated connection"),
        ('url = "mqtt://b"\nca_file = "ca.pem"', "need an mqtts:// url"),
        ('url = "mqtt://b"\ngroup_id = "a/b"', "telemetry.mqtt.group_id"),
        ('url = "mqtt://b"\nedge_node_id = "pc#1"', "telemetry.mqtt.edge_node_id"),
        ('url = "mqtt://b"\ncommand_role = "root"', "telemetry.mqtt.command_role"),
        ('url = "mqtt://b"\npassword_env = "lower"\nuser = "x"', "telemetry.mqtt.password_env"),
    ],
)
def test_bad_sections_are_one_clear_error(tmp_path, section, message):
    with pytest.raises(ConfigError) as e:
        load_config(write(tmp_path, f"[telemetry.mqtt]\n{section}\n"))
    text = str(e.value)
    assert message in text and text.startswith(str(tmp_path / "cell.toml")) and "\n" not in text


def test_the_password_comes_from_the_environment_only():
    cfg = MqttConfig(url="mqtt://b", user="cell", password_env="CELL_MQTT_PASSWORD")
    assert password_from_env(cfg, {"CELL_MQTT_PASSWORD": "s3cret"}) == "s3cret"
    with pytest.raises(ConfigError, match="CELL_MQTT_PASSWORD is not set or empty"):
        password_from_env(cfg, {})
    assert password_from_env(MqttConfig(url="mqtt://b"), {}) is None


def test_a_run_cell_job_is_not_published_and_says_so(caplog):
    """attach_consumers builds the publisher for `run-cell serve` only (it needs the line service)."""
    import contextlib

    from cell.assembly import RunHooks, attach_consumers
    from cell.config import CellConfig
    from cell.core.eventbus import EventBus
    from cell.signals import Controls

    cfg = CellConfig()
    cfg.history.enabled = False  # this test is about telemetry alone
    cfg.telemetry.mqtt = MqttConfig(url="mqtt://127.0.0.1:1")
    bus = EventBus()
    with contextlib.ExitStack() as resources:
        consumers = attach_consumers(cfg, bus, resources, RunHooks(Controls()))
        assert consumers.telemetry is None and bus.stats() == ()
    assert "published by `run-cell serve` only" in caplog.text
