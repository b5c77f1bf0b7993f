"""Shifts as the plant defines them: a local time zone and the times shifts start.

`[shifts]` gives an IANA time zone (zoneinfo: "Europe/Berlin", "America/Chicago", "UTC") and
the local start times ("06:00", "14:00", "22:00"), optionally with names ("early", "late",
"night"). A shift's id is the local date it started on and its name, `2026-12-01/early`, or
its start time when the shifts have no names, `2026-12-01T06:00`. A night shift that starts
at 22:00 on the 1st and ends at 06:00 on the 2nd is `2026-12-01/night`.

Daylight saving: a start time is taken on the local clock; on the night the clocks change
a shift is an hour longer or shorter, as the plant's own is. A start time the clocks skip
(02:30 on a spring-forward night) begins when the clocks jump.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from datetime import UTC, date, datetime, time, timedelta, tzinfo
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

from pydantic import Field, field_validator, model_validator

from drivers.config import Strict

_HHMM = re.compile(r"^([01]\d|2[0-3]):([0-5]\d)$")
_NAME = re.compile(r"^[a-z][a-z0-9_-]{0,23}$")


class ShiftsConfig(Strict):
    """`[shifts]`: the plant's shift calendar; the counters, OPC UA, the screen and reports count per shift."""

    time_zone: str = Field("UTC", description="IANA time zone of the plant's clocks, e.g. Europe/Berlin")
    starts: list[str] = Field(
        default_factory=lambda: ["06:00", "14:00", "22:00"], description="local start times, HH:MM, in day order"
    )
    names: list[str] = Field(
        default_factory=lambda: ["early", "late", "night"],
        description="one name per start time (ids 2026-12-01/early); empty: ids by start time (2026-12-01T06:00)",
    )

    @field_validator("time_zone")
    @classmethod
    def _known_zone(cls, v: str) -> str:
        try:
            ZoneInfo(v)
        except (ZoneInfoNotFoundError, ValueError):
            raise ValueError(f"{v!r} is not an IANA time zone (e.g. 'Europe/Berlin', 'UTC')") from None
        return v

    @model_validator(mode="after")
    def _starts_and_names(self) -> ShiftsConfig:
        if not self.starts:
            raise ValueError("shifts.starts: give at least one start time (HH:MM)")
        for s in self.starts:
            if not _HHMM.match(s):
                raise ValueError(f"shifts.starts: {s!r} is not a time HH:MM (00:00-23:59)")
        if sorted(self.starts) != self.starts or len(set(self.starts)) != len(self.starts):
            raise ValueError(f"shifts.starts {self.starts}: give each time once, in day order")
        if self.names:
            if len(self.names) != len(self.starts):
                raise ValueError(f"shifts.names: {len(self.names)} names for {len(self.starts)} start times")
            for n in self.names:
                if not _NAME.match(n):
                    raise ValueError(f"shifts.names: {n!r}: lower-case letters, digits, - and _, at most 24")
            if len(set(self.names)) != len(self.names):
                raise ValueError(f"shifts.names {self.names}: each name once")
        return self


@dataclass(frozen=True)
class Shift:
    id: str
    start_utc: datetime
    end_utc: datetime

    def contains(self, t: datetime) -> bool:
        return self.start_utc <= t < self.end_utc


class ShiftCalendar:
    """Which shift a moment belongs to, and a shift's bounds from its id."""

    def __init__(self, config: ShiftsConfig | None = None):
        c = config or ShiftsConfig()
        self.zone = ZoneInfo(c.time_zone)
        self.starts = [time(int(s[:2]), int(s[3:])) for s in c.starts]
        self.names = list(c.names)

    def _label(self, i: int) -> str:
        return self.names[i] if self.names else f"{self.starts[i]:%H:%M}"

    def _id(self, day: date, i: int) -> str:
        return f"{day.isoformat()}/{self.names[i]}" if self.names else f"{day.isoformat()}T{self.starts[i]:%H:%M}"

    def _start(self, day: date, i: int) -> datetime:
        local = datetime.combine(day, self.starts[i], tzinfo=self.zone)
        return local.astimezone(UTC)

    def _next(self, day: date, i: int) -> tuple[date, int]:
        return (day, i + 1) if i + 1 < len(self.starts) else (day + timedelta(days=1), 0)

    def _make(self, day: date, i: int) -> Shift:
        nday, ni = self._next(day, i)
        return Shift(self._id(day, i), self._start(day, i), self._start(nday, ni))

    def at(self, t: datetime) -> Shift:
        """The shift running at `t` (an aware datetime)."""
        local_day = t.astimezone(self.zone).date()
        for day in (local_day - timedelta(days=1), local_day):
            for i in range(len(self.starts)):
                shift = self._make(day, i)
                if shift.contains(t):
                    return shift
        return self._make(local_day, len(self.starts) - 1)  # unreachable for a sane zone; the day's last

    def now(self) -> Shift:
        return self.at(datetime.now(UTC))

    def by_id(self, shift_id: str) -> Shift:
        """A shift from its id (`2026-12-01/early` or `2026-12-01T06:00`); ValueError saying what is wrong."""
        if self.names:
            day_text, _, label = shift_id.partition("/")
            known = self.names
        else:
            day_text, _, label = shift_id.partition("T")
            known = [f"{s:%H:%M}" for s in self.starts]
        try:
            day = date.fromisoformat(day_text)
        except ValueError:
            raise ValueError(f"shift {shift_id!r}: expected DATE/NAME like {self._id(date(2026, 12, 1), 0)}") from None
        if label not in known:
            raise ValueError(f"shift {shift_id!r}: no shift {label!r} (the shifts are {', '.join(known)})")
        return self._make(day, known.index(label))

    def day(self, day: date) -> tuple[datetime, datetime]:
        """A plant day: from its first shift's start to the next day's first shift's start, UTC."""
        return self._start(day, 0), self._start(day + timedelta(days=1), 0)

    def shifts_between(self, start: datetime, end: datetime) -> list[Shift]:
        out, shift = [], self.at(start)
        while shift.start_utc < end:
            out.append(shift)
            shift = self.at(shift.end_utc)
        return out


def utc_offset(zone: tzinfo, at: datetime) -> str:
    """`UTC+05:30`: the zone's offset at a moment."""
    offset = at.astimezone(zone).utcoffset() or timedelta()
    sign = "-" if offset < timedelta() else "+"
    minutes = abs(int(offset.total_seconds())) // 60
    return f"UTC{sign}{minutes // 60:02d}:{minutes % 60:02d}"


def zone_line(zone: tzinfo, start: datetime, end: datetime | None = None) -> str:
    """`times in Asia/Kolkata (UTC+05:30)`: the zone times are printed in, with its offset over a span
    (both offsets when the clocks change inside it)."""
    first = utc_offset(zone, start)
    last = first if end is None else utc_offset(zone, end)
    return f"times in {zone} ({first if first == last else f'{first}, then {last}'})"
