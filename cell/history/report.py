"""A shift's (or a day's) report from the history: picks per hour, miss and failure rates, the
faults and their reasons, downtime, mean time between faults, the top alarm reasons, a chart.

Everything is counted by the database (GROUP BY over the time index), so a report over a
million picks takes a second, not a minute of Python.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime, tzinfo
from pathlib import Path
from zoneinfo import ZoneInfo

from cell.history.db import required_time
from cell.history.query import HistoryReader
from cell.shifts import zone_line

UP_STATES = frozenset({"Ready", "SingleExecution", "ContinuousExecution"})
RUNNING_STATES = frozenset({"SingleExecution", "ContinuousExecution"})


@dataclass
class Report:
    title: str
    start_utc: datetime
    end_utc: datetime
    attempts: int = 0
    picked: int = 0
    misses: int = 0
    failed: int = 0
    rehearsed: int = 0
    by_class: dict[str, int] = field(default_factory=dict)
    # (the hour's start on the plant's clock, ISO with its offset: 2026-12-01T11:00+05:30, picked, missed)
    per_hour: list[tuple[str, int, int]] = field(default_factory=list)
    faults: list[dict] = field(default_factory=list)  # time_utc, reason, source, cleared_by
    top_alarms: list[tuple[str, int]] = field(default_factory=list)
    running_s: float = 0.0
    down_s: float = 0.0
    state_s: dict[str, float] = field(default_factory=dict)
    mean_cycle_ms: float | None = None
    time_zone: str = "UTC"  # the plant's ([shifts].time_zone): the text, per_hour and the chart speak it

    @property
    def zone(self) -> tzinfo:
        return UTC if self.time_zone == "UTC" else ZoneInfo(self.time_zone)

    def local(self, t: datetime) -> datetime:
        return t.astimezone(self.zone)

    @property
    def miss_rate(self) -> float:
        return self.misses / self.attempts if self.attempts else 0.0

    @property
    def failure_rate(self) -> float:
        parts = self.picked + self.failed
        return self.failed / parts if parts else 0.0

    @property
    def mtbf_s(self) -> float | None:
        return self.running_s / len(self.faults) if self.faults else None

    def as_json(self) -> dict:
        d = asdict(self)
        d.update(
            start_utc=self.start_utc.isoformat(),
            end_utc=self.end_utc.isoformat(),
            start=self.local(self.start_utc).isoformat(),
            end=self.local(self.end_utc).isoformat(),
            miss_rate=round(self.miss_rate, 4),
            failure_rate=round(self.failure_rate, 4),
            mtbf_s=None if self.mtbf_s is None else round(self.mtbf_s, 1),
            per_hour=[{"hour": h, "picked": p, "missed": m} for h, p, m in self.per_hour],
            top_alarms=[{"reason": r, "count": n} for r, n in self.top_alarms],
            running_s=round(self.running_s, 1),
            down_s=round(self.down_s, 1),
            state_s={k: round(v, 1) for k, v in self.state_s.items()},
        )
        return d

    def lines(self) -> list[str]:
        start, end = self.local(self.start_utc), self.local(self.end_utc)
        out = [
            f"report {self.title}: {start:%Y-%m-%d %H:%M} - {end:%Y-%m-%d %H:%M}",
            zone_line(self.zone, self.start_utc, self.end_utc),
            f"picks: {self.picked} picked ({', '.join(f'{n} {c}' for c, n in sorted(self.by_class.items())) or '-'}) "
            f"in {self.attempts} attempts; {self.misses} misses ({100 * self.miss_rate:.1f} %), "
            f"{self.failed} parts failed ({100 * self.failure_rate:.1f} %)"
            + (f"; {self.rehearsed} rehearsed" if self.rehearsed else ""),
            f"mean cycle: {'-' if self.mean_cycle_ms is None else f'{self.mean_cycle_ms:.0f} ms'}",
            f"running {_hms(self.running_s)}, downtime {_hms(self.down_s)} (neither Ready nor executing)",
            f"faults: {len(self.faults)}; mean time between faults: "
            + ("-" if self.mtbf_s is None else _hms(self.mtbf_s)),
        ]
        for f in self.faults:
            cleared = f" (reset by {f['cleared_by']})" if f.get("cleared_by") else ""
            when = f"{self.local(datetime.fromisoformat(f['time_utc'])):%Y-%m-%d %H:%M:%S}" if f["time_utc"] else "-"
            out.append(f"  {when}  {f['reason']}{cleared}")
        if self.top_alarms:
            out.append("top alarm reasons:")
            out += [f"  {n:5d}  {reason}" for reason, n in self.top_alarms]
        out.append(f"picks per hour ({self.time_zone}): " + ("none" if not self.per_hour else ""))
        out += [f"  {h[:10]} {h[11:16]}  {p:5d} picked  {m:4d} missed" for h, p, m in self.per_hour]
        return out


def _hms(s: float) -> str:
    s = int(round(s))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


def _minute_expr(dialect: str) -> str:
    """The pick's UTC minute: counted per minute by the database, summed into the plant's hours here (every
    zone's offset is whole minutes: Asia/Kolkata's +05:30 splits a UTC hour between two local ones)."""
    if dialect == "postgresql":
        return "to_char(time_utc AT TIME ZONE 'UTC', 'YYYY-MM-DD\"T\"HH24:MI')"
    return "substr(time_utc, 1, 16)"


def _local_hour(minute_utc: str, zone: tzinfo) -> datetime:
    """The start of the plant's hour a UTC minute (`2026-12-01T06:15`) falls in, as a UTC instant (two
    hours that read alike on the night the clocks go back stay apart)."""
    local = datetime.fromisoformat(minute_utc).replace(tzinfo=UTC).astimezone(zone)
    return local.replace(minute=0, second=0, microsecond=0).astimezone(UTC)


def build_report(reader: HistoryReader, title: str, start: datetime, end: datetime, zone: tzinfo = UTC) -> Report:
    """`zone`: the plant's ([shifts].time_zone): the hours counted and the times printed are its."""
    r = Report(title, start, end, time_zone=str(zone))
    cell = " AND cell = ?" if reader.cell else ""
    base = [start, end] + ([reader.cell] if reader.cell else [])
    db = reader.db
    rows = db.execute(
        f"SELECT {_minute_expr(db.dialect)} AS h, outcome, class, count(*), sum(cycle_ms) FROM picks "
        f"WHERE time_utc >= ? AND time_utc < ?{cell} GROUP BY h, outcome, class ORDER BY h",
        base,
    )
    hours: dict[datetime, list[int]] = {}
    cycle_sum, cycle_n = 0.0, 0
    for minute, outcome, cls, n, cycles in rows:
        n = int(n)
        r.attempts += n
        slot = hours.setdefault(_local_hour(str(minute), zone), [0, 0])
        if outcome == "picked":
            r.picked += n
            r.by_class[cls] = r.by_class.get(cls, 0) + n
            slot[0] += n
            cycle_sum, cycle_n = cycle_sum + float(cycles or 0), cycle_n + n
        elif outcome in ("missed", "failed"):
            r.misses += n
            r.failed += n if outcome == "failed" else 0
            slot[1] += n
        elif outcome == "rehearsed":
            r.rehearsed += n
    r.per_hour = [(r.local(h).isoformat(timespec="minutes"), p, m) for h, (p, m) in sorted(hours.items())]
    r.mean_cycle_ms = cycle_sum / cycle_n if cycle_n else None
    faults = db.execute(
        "SELECT raised_utc, reason, source, cleared_user, cleared_interface FROM alarms "
        f"WHERE severity = 'fault' AND raised_utc >= ? AND raised_utc < ?{cell} ORDER BY raised_utc",
        base,
    )
    r.faults = [
        {
            "time_utc": required_time(t, "an alarm").isoformat(timespec="seconds"),
            "reason": reason,
            "source": source,
            "cleared_by": f"{user or 'anonymous'} via {iface}" if iface else "",
        }
        for t, reason, source, user, iface in faults
    ]
    cli_faults = db.execute(
        "SELECT end_utc, reason FROM jobs WHERE outcome = 'fault' AND interface = 'cli' "
        f"AND start_utc >= ? AND start_utc < ?{cell} ORDER BY end_utc",
        base,
    )
    r.faults += [
        {
            "time_utc": required_time(t, "a job's end").isoformat(timespec="seconds") if t else "",
            "reason": why,
            "source": "job",
        }
        for t, why in cli_faults
    ]
    top = db.execute(
        f"SELECT reason, count(*) AS n FROM alarms WHERE raised_utc >= ? AND raised_utc < ?{cell} "
        "GROUP BY reason ORDER BY n DESC, reason LIMIT 5",
        base,
    )
    r.top_alarms = [(str(reason), int(n)) for reason, n in top]
    _states(reader, r, min(end, datetime.now(UTC)))
    return r


def _states(reader: HistoryReader, r: Report, until: datetime) -> None:
    """Time in each outward state over the window (the state at its start is the last before it)."""
    cell = " AND cell = ?" if reader.cell else ""
    who = [reader.cell] if reader.cell else []
    before = reader.db.execute(
        f"SELECT target FROM states WHERE time_utc < ?{cell} ORDER BY time_utc DESC LIMIT 1", [r.start_utc] + who
    )
    rows = reader.db.execute(
        f"SELECT time_utc, target FROM states WHERE time_utc >= ? AND time_utc < ?{cell} ORDER BY time_utc",
        [r.start_utc, until] + who,
    )
    state, since = (before[0][0] if before else None), r.start_utc
    for t, target in rows:
        when = required_time(t, "a state change")
        if state is not None:
            _add(r, state, (when - since).total_seconds())
        state, since = target, when
    if state is not None and until > since:
        _add(r, state, (until - since).total_seconds())


def _add(r: Report, state: str, seconds: float) -> None:
    r.state_s[state] = r.state_s.get(state, 0.0) + seconds
    if state in RUNNING_STATES:
        r.running_s += seconds
    if state not in UP_STATES:
        r.down_s += seconds


def chart(report: Report, path: Path) -> Path:
    """Picks and misses per hour (bars), and the time in each state (a bar below), as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cell.atomicfile import write_atomic

    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(9, 5.5), gridspec_kw={"height_ratios": [4, 1]})
    try:
        labels = [h[11:16] for h, _, _ in report.per_hour]
        if len(set(labels)) < len(labels):  # the night the clocks go back: an hour twice, told by its offset
            labels = [h[11:] for h, _, _ in report.per_hour]
        picked = [p for _, p, _ in report.per_hour]
        missed = [m for _, _, m in report.per_hour]
        ax.bar(labels, picked, color="#2e7d32", label="picked")
        ax.bar(labels, missed, bottom=picked, color="#c62828", label="missed")
        ax.set_ylabel("picks per hour")
        ax.set_xlabel(f"hour ({report.time_zone})")
        ax.set_title(
            f"{report.title}: {report.picked} picked, miss rate {100 * report.miss_rate:.1f} %, "
            f"{len(report.faults)} faults, downtime {_hms(report.down_s)}"
        )
        ax.legend(loc="upper right")
        colours = {
            "Ready": "#90caf9",
            "SingleExecution": "#2e7d32",
            "ContinuousExecution": "#66bb6a",
            "Off": "#9e9e9e",
            "Preoperational": "#ffb300",
            "Halted": "#ef6c00",
        }
        left = 0.0
        for state, seconds in sorted(report.state_s.items()):
            ax2.barh([0], [seconds / 3600], left=left, color=colours.get(state, "#c62828"), label=state)
            left += seconds / 3600
        ax2.set_yticks([])
        ax2.set_xlabel("hours in each state")
        if report.state_s:
            ax2.legend(loc="upper center", bbox_to_anchor=(0.5, -0.6), ncol=4, fontsize="small")
        fig.tight_layout()
        return write_atomic(path, lambda f: fig.savefig(f, format="png", dpi=100))
    finally:
        plt.close(fig)


def window(kind: str, calendar, value: str | None) -> tuple[str, datetime, datetime]:
    """(title, start, end) for --shift ID, --day DATE, or the running shift."""
    from datetime import date

    if kind == "day" and value:
        day = date.fromisoformat(value)
        start, end = calendar.day(day)
        return f"day {value}", start, end
    shift = calendar.by_id(value) if value else calendar.now()
    return f"shift {shift.id}", shift.start_utc, shift.end_utc
