"""`run-cell report`: a shift's or a day's report from the history store, with a chart."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from cell.commands.history import add_store_arguments, store_config
from cell.errors import InputError


def register(sub) -> None:
    p = sub.add_parser(
        "report",
        help="a shift's or a day's report: picks per hour, miss and failure rates, faults, downtime, a chart",
        description="Report on one shift (default: the running one) or one plant day from the history store: "
        "picks per hour, miss and failure rates, faults with their reasons, downtime (neither Ready nor "
        "executing), mean time between faults, the top alarm reasons; --png writes the chart.",
    )
    add_store_arguments(p)
    which = p.add_mutually_exclusive_group()
    which.add_argument("--shift", help="the shift, e.g. 2026-12-01/early (default: the running shift)")
    which.add_argument("--day", help="a plant day, YYYY-MM-DD (from its first shift's start)")
    p.add_argument("--png", type=Path, help="write the chart to this PNG file")
    p.add_argument("--json", action="store_true", help="the report as JSON")
    p.set_defaults(func=cmd_report)


def cmd_report(args: argparse.Namespace) -> int:
    from cell.history.query import open_reader
    from cell.history.report import build_report, chart, window
    from cell.shifts import ShiftCalendar

    config = store_config(args)
    calendar = ShiftCalendar(config.shifts)
    try:
        title, start, end = window("day" if args.day else "shift", calendar, args.day or args.shift)
    except ValueError as e:
        raise InputError(f"--{'day' if args.day else 'shift'}: {e}") from None
    if args.png is not None and args.png.suffix.lower() != ".png":
        raise InputError(f"--png {args.png}: give a file name ending in .png")
    reader = open_reader(config)
    try:
        report = build_report(reader, title, start, end, calendar.zone)
    finally:
        reader.close()
    if args.json:
        print(json.dumps(report.as_json(), indent=1))
    else:
        for line in report.lines():
            print(line)
    if args.png is not None:
        chart(report, args.png)
        if not args.json:
            print(f"chart: {args.png}")
    return 0
