"""Plain Python values into asyncua's typed structures.

asyncua annotates its structures' fields with marker subclasses of the built-in types
(ua.String, ua.Int32 and ua.Int16 in a NodeId, ua.UInt32 in a StatusCode, ua.DateTime in a
DataValue) that tell its binary encoder what to write, while it takes plain values at run
time (its own code passes them). These helpers hand it the marker type made from the plain
value: the same value (a subclass instance that compares and hashes as the plain one), so
the calls type-check without a cast.

The OPC 40100-1 structures (ResultDataType, JobIdDataType, ...) exist only once the Machine
Vision NodeSet's DataTypeDefinitions are loaded: asyncua then makes them attributes of
asyncua.ua; `mv_struct` fetches one by name, or says it is not loaded.
"""

from __future__ import annotations

from collections.abc import Callable
from datetime import datetime
from typing import Any

from asyncua import ua


def node_id(identifier: int | str, namespace: int = 0) -> ua.NodeId:
    """A numeric (an int, e.g. ua.ObjectIds.Server) or string NodeId in `namespace`."""
    ident = ua.Int32(identifier) if isinstance(identifier, int) else ua.String(identifier)
    return ua.NodeId(ident, ua.Int16(namespace))


def status(code: int) -> ua.StatusCode:
    """A StatusCode from its number (ua.StatusCodes.BadInvalidState, ...)."""
    return ua.StatusCode(ua.UInt32(code))


def data_value(value: ua.Variant, time_utc: datetime) -> ua.DataValue:
    """A value as written now: source and server timestamps both `time_utc`."""
    stamp = ua.DateTime.combine(time_utc.date(), time_utc.timetz())
    return ua.DataValue(value, SourceTimestamp=stamp, ServerTimestamp=stamp)


def mv_struct(name: str) -> Callable[..., Any]:
    """The asyncua class of an OPC 40100-1 structure (e.g. "ResultDataType"), made when the
    Machine Vision NodeSet was loaded; RuntimeError if it was not."""
    cls: object = getattr(ua, name, None)
    if not callable(cls):
        raise RuntimeError(f"OPC UA: no {name}: the Machine Vision NodeSet's data types are not loaded")
    return cls
