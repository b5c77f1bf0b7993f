"""Sparkplug B 3.0 payloads and topics, encoded by `protobuf`.

The payload schema (message `Payload` and the messages inside it, proto2) is declared below
from the Sparkplug B specification's payload definition: every field's number, type and label
as published, so the bytes are the standard's. It is built into a descriptor at import and
protobuf's own runtime makes the message classes: no generated code, no protoc at build time,
and nothing tied to one protobuf release. `tests/test_sparkplug.py` checks the encoding
against payloads written by hand from the specification's wire rules.

Topics: spBv1.0/GROUP/NBIRTH|NDEATH|NDATA|NCMD/EDGE_NODE and
spBv1.0/GROUP/DBIRTH|DDEATH|DDATA|DCMD/EDGE_NODE/DEVICE.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

NAMESPACE = "spBv1.0"


class DataType(IntEnum):
    """Sparkplug B data types (the metric's `datatype` field)."""

    INT8 = 1
    INT16 = 2
    INT32 = 3
    INT64 = 4
    UINT8 = 5
    UINT16 = 6
    UINT32 = 7
    UINT64 = 8
    FLOAT = 9
    DOUBLE = 10
    BOOLEAN = 11
    STRING = 12
    DATETIME = 13
    TEXT = 14
    UUID = 15
    DATASET = 16
    BYTES = 17
    FILE = 18
    TEMPLATE = 19


# ---- the schema (field name, number, protobuf type, label, message type or oneof) -----------------
_F = descriptor_pb2.FieldDescriptorProto
OPT, REP = _F.LABEL_OPTIONAL, _F.LABEL_REPEATED
U32, U64, F32, F64, BOOL, STR, BYTES, MSG = (
    _F.TYPE_UINT32,
    _F.TYPE_UINT64,
    _F.TYPE_FLOAT,
    _F.TYPE_DOUBLE,
    _F.TYPE_BOOL,
    _F.TYPE_STRING,
    _F.TYPE_BYTES,
    _F.TYPE_MESSAGE,
)
_VALUES = [("int_value", U32), ("long_value", U64), ("float_value", F32), ("double_value", F64)]
_VALUES += [("boolean_value", BOOL), ("string_value", STR)]

# message path -> (fields, first extension number or None); a field is (name, number, type, label, type_name, oneof)
_SCHEMA: dict[str, tuple[list[tuple], int | None]] = {
    "Payload": (
        [
            ("timestamp", 1, U64, OPT, None, None),
            ("metrics", 2, MSG, REP, "Payload.Metric", None),
            ("seq", 3, U64, OPT, None, None),
            ("uuid", 4, STR, OPT, None, None),
            ("body", 5, BYTES, OPT, None, None),
        ],
        6,
    ),
    "Payload.Template": (
        [
            ("version", 1, STR, OPT, None, None),
            ("metrics", 2, MSG, REP, "Payload.Metric", None),
            ("parameters", 3, MSG, REP, "Payload.Template.Parameter", None),
            ("template_ref", 4, STR, OPT, None, None),
            ("is_definition", 5, BOOL, OPT, None, None),
        ],
        6,
    ),
    "Payload.Template.Parameter": (
        [("name", 1, STR, OPT, None, None), ("type", 2, U32, OPT, None, None)]
        + [(n, 3 + i, t, OPT, None, "value") for i, (n, t) in enumerate(_VALUES)]
        + [("extension_value", 9, MSG, OPT, "Payload.Template.Parameter.ParameterValueExtension", "value")],
        None,
    ),
    "Payload.Template.Parameter.ParameterValueExtension": ([], 1),
    "Payload.DataSet": (
        [
            ("num_of_columns", 1, U64, OPT, None, None),
            ("columns", 2, STR, REP, None, None),
            ("types", 3, U32, REP, None, None),
            ("rows", 4, MSG, REP, "Payload.DataSet.Row", None),
        ],
        5,
    ),
    "Payload.DataSet.DataSetValue": (
        [(n, 1 + i, t, OPT, None, "value") for i, (n, t) in enumerate(_VALUES)]
        + [("extension_value", 7, MSG, OPT, "Payload.DataSet.DataSetValue.DataSetValueExtension", "value")],
        None,
    ),
    "Payload.DataSet.DataSetValue.DataSetValueExtension": ([], 1),
    "Payload.DataSet.Row": ([("elements", 1, MSG, REP, "Payload.DataSet.DataSetValue", None)], 2),
    "Payload.PropertyValue": (
        [("type", 1, U32, OPT, None, None), ("is_null", 2, BOOL, OPT, None, None)]
        + [(n, 3 + i, t, OPT, None, "value") for i, (n, t) in enumerate(_VALUES)]
        + [
            ("propertyset_value", 9, MSG, OPT, "Payload.PropertySet", "value"),
            ("propertysets_value", 10, MSG, OPT, "Payload.PropertySetList", "value"),
            ("extension_value", 11, MSG, OPT, "Payload.PropertyValue.PropertyValueExtension", "value"),
        ],
        None,
    ),
    "Payload.PropertyValue.PropertyValueExtension": ([], 1),
    "Payload.PropertySet": (
        [("keys", 1, STR, REP, None, None), ("values", 2, MSG, REP, "Payload.PropertyValue", None)],
        3,
    ),
    "Payload.PropertySetList": ([("propertyset", 1, MSG, REP, "Payload.PropertySet", None)], 2),
    "Payload.MetaData": (
        [
            ("is_multi_part", 1, BOOL, OPT, None, None),
            ("content_type", 2, STR, OPT, None, None),
            ("size", 3, U64, OPT, None, None),
            ("seq", 4, U64, OPT, None, None),
            ("file_name", 5, STR, OPT, None, None),
            ("file_type", 6, STR, OPT, None, None),
            ("md5", 7, STR, OPT, None, None),
            ("description", 8, STR, OPT, None, None),
        ],
        9,
    ),
    "Payload.Metric": (
        [
            ("name", 1, STR, OPT, None, None),
            ("alias", 2, U64, OPT, None, None),
            ("timestamp", 3, U64, OPT, None, None),
            ("datatype", 4, U32, OPT, None, None),
            ("is_historical", 5, BOOL, OPT, None, None),
            ("is_transient", 6, BOOL, OPT, None, None),
            ("is_null", 7, BOOL, OPT, None, None),
            ("metadata", 8, MSG, OPT, "Payload.MetaData", None),
            ("properties", 9, MSG, OPT, "Payload.PropertySet", None),
        ]
        + [(n, 10 + i, t, OPT, None, "value") for i, (n, t) in enumerate(_VALUES)]
        + [
            ("bytes_value", 16, BYTES, OPT, None, "value"),
            ("dataset_value", 17, MSG, OPT, "Payload.DataSet", "value"),
            ("template_value", 18, MSG, OPT, "Payload.Template", "value"),
            ("extension_value", 19, MSG, OPT, "Payload.Metric.MetricValueExtension", "value"),
        ],
        None,
    ),
    "Payload.Metric.MetricValueExtension": ([], 1),
}
_PACKAGE = "org.eclipse.tahu.protobuf"  # the package the specification's schema declares


def _message(path: str) -> descriptor_pb2.DescriptorProto:
    fields, extensions_from = _SCHEMA[path]
    msg = descriptor_pb2.DescriptorProto(name=path.rsplit(".", 1)[-1])
    oneofs: list[str] = []
    for name, number, ftype, label, type_name, oneof in fields:
        field = msg.field.add(name=name, number=number, type=ftype, label=label)
        if type_name:
            field.type_name = f".{_PACKAGE}.{type_name}"
        if oneof:
            if oneof not in oneofs:
                oneofs.append(oneof)
                msg.oneof_decl.add(name=oneof)
            field.oneof_index = oneofs.index(oneof)
    if extensions_from is not None:
        msg.extension_range.add(start=extensions_from, end=536870912)  # "N to max"
    for child in _SCHEMA:
        if "." in child and child.rsplit(".", 1)[0] == path:
            msg.nested_type.append(_message(child))
    return msg


def _payload_class() -> type:
    file = descriptor_pb2.FileDescriptorProto(name="cell_sparkplug_b.proto", package=_PACKAGE, syntax="proto2")
    file.message_type.append(_message("Payload"))
    pool = descriptor_pool.DescriptorPool()
    pool.Add(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(f"{_PACKAGE}.Payload"))


Payload = _payload_class()


# ---- metrics --------------------------------------------------------------------------------
_INTS = {DataType.INT8: 8, DataType.INT16: 16, DataType.INT32: 32, DataType.INT64: 64}
_UINTS = {DataType.UINT8: 8, DataType.UINT16: 16, DataType.UINT32: 32, DataType.UINT64: 64, DataType.DATETIME: 64}
_FIELD = {DataType.FLOAT: "float_value", DataType.DOUBLE: "double_value", DataType.BOOLEAN: "boolean_value"}
_FIELD.update({DataType.STRING: "string_value", DataType.TEXT: "string_value", DataType.UUID: "string_value"})


def _int_field(dtype: DataType) -> str:
    bits = _INTS.get(dtype) or _UINTS[dtype]
    return "long_value" if bits == 64 else "int_value"


@dataclass(frozen=True)
class Metric:
    """One metric as the cell publishes it: None is sent as is_null."""

    name: str
    dtype: DataType
    value: Any
    timestamp_ms: int = 0


def now_ms() -> int:
    return int(time.time() * 1000)


def fill(pb: Any, m: Metric, *, birth: bool) -> None:
    """Set one protobuf Metric: name always (no aliases), datatype on births only (the spec's SHOULD NOT
    on DATA), signed integers as two's complement in the unsigned fields, None or NaN as is_null."""
    pb.name = m.name
    pb.timestamp = m.timestamp_ms or now_ms()
    if birth:
        pb.datatype = int(m.dtype)
    value = m.value
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        pb.is_null = True
        return
    if m.dtype in _INTS:
        bits = _INTS[m.dtype]
        setattr(pb, _int_field(m.dtype), int(value) & ((1 << (64 if bits == 64 else 32)) - 1))
    elif m.dtype in _UINTS:
        setattr(pb, _int_field(m.dtype), int(value))
    elif m.dtype in _FIELD:
        setattr(pb, _FIELD[m.dtype], value)
    else:
        raise ValueError(f"metric {m.name}: data type {m.dtype.name} is not published by this cell")


def payload(metrics: Iterable[Metric], seq: int | None, *, birth: bool = False, timestamp_ms: int = 0) -> bytes:
    """A Sparkplug B payload: timestamp, metrics, and seq (None for NDEATH, which has none)."""
    out = Payload()
    out.timestamp = timestamp_ms or now_ms()
    if seq is not None:
        out.seq = seq
    for m in metrics:
        fill(out.metrics.add(), m, birth=birth)
    return out.SerializeToString()


def decode(data: bytes) -> Any:
    """A received payload (raises google.protobuf.message.DecodeError on bytes that are not one)."""
    msg = Payload()
    msg.ParseFromString(data)
    return msg


def value_of(pb: Any, dtype: DataType | int | None = None) -> Any:
    """A received metric's value as Python (signed integers decoded by the datatype given or carried)."""
    if pb.is_null:
        return None
    which = pb.WhichOneof("value")
    if which is None:
        return None
    value = getattr(pb, which)
    kind = dtype or pb.datatype
    if kind in _INTS:  # two's complement in the unsigned field: 32 bits wide for Int8..Int32, 64 for Int64
        width = 64 if kind == DataType.INT64 else 32
        if value >= 1 << (width - 1):
            value -= 1 << width
    return value


# ---- sequence numbers ---------------------------------------------------------------------------
def next_seq(seq: int) -> int:
    """seq and bdSeq run 0..255 and wrap to 0."""
    return (seq + 1) % 256


# ---- topics ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Topics:
    group_id: str
    edge_node_id: str
    device_id: str

    def node(self, kind: str) -> str:
        return f"{NAMESPACE}/{self.group_id}/{kind}/{self.edge_node_id}"

    def device(self, kind: str) -> str:
        return f"{NAMESPACE}/{self.group_id}/{kind}/{self.edge_node_id}/{self.device_id}"


def parse_topic(topic: str) -> tuple[str, str, str, str | None] | None:
    """(group_id, message type, edge_node_id, device_id or None) of a Sparkplug B topic; None otherwise."""
    parts = topic.split("/")
    if len(parts) not in (4, 5) or parts[0] != NAMESPACE:
        return None
    return parts[1], parts[2], parts[3], parts[4] if len(parts) == 5 else None
