#!/usr/bin/env python3
"""Picks per minute with misbehaving listeners beside the cell, against none, in the same run.

The line service runs in-process on the simulated cell (960 x 540 camera) as a dry-run shift: a
continuous job with the feeder dropping bolts and nuts faster than the cell picks them, and no
washers (the cell leaves washers on the table: they pile up until nothing on it can be picked, and
the cell then waits for parts, a second at a time, which measures the feeder and not the cell).
The table stays full, so the cell never waits and its own speed is what is measured; the waits
are counted and printed to show it. The set-ups take turns, forward then backward in alternate
rounds (a drift of the machine's speed over the run then falls on every set-up alike):

- none: the service's own subscribers only (ledger, history);
- slow + raising: a subscriber that sleeps 2 s on every event and one that raises on every event;
- screen, none open: the operator screen's server running (as `run-cell serve` runs it), no
  screen open;
- 1 slow screen / 30 slow screens: the screen's server with 1 or 30 event streams open, each
  read 1 KiB a second (far slower than the screen sends), from another process (as browsers
  are: readers inside the cell's process would take its interpreter lock, which no browser does).

Picks per minute is counted over --picks picks after the first --warmup (the job's start, the
screens' first frames and the feeder filling the table are left out). A shift's speed still varies
with what lies on the table and with the machine, so each set-up is compared with the shift of no
listeners in the same round (the median of those ratios over --jobs rounds, and the worst one);
its median picks per minute is printed too.

    python scripts/bench_subscribers.py [--jobs 5] [--picks 60] [--warmup 10]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path


def slow_reader(port: int, stop: threading.Event) -> None:
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        s.sendall(b"GET /api/events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        s.settimeout(2.0)
        while not stop.wait(1.0):
            with contextlib.suppress(OSError):
                if not s.recv(1024):
                    return


def readers_main(port: int, count: int) -> int:
    stop = threading.Event()
    threads = [threading.Thread(target=slow_reader, args=(port, stop), daemon=True) for _ in range(count)]
    for t in threads:
        t.start()
    sys.stdin.read()  # the bench closes it
    stop.set()
    return 0


if __name__ == "__main__" and sys.argv[1:2] == ["--readers"]:
    # the readers' process imports nothing of the cell: a browser shares nothing with it (an early
    # version imported the whole cell here, and that process's threads took a fifth of the picks)
    sys.exit(readers_main(int(sys.argv[2]), int(sys.argv[3])))

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cell.commands.serve import open_service  # noqa: E402
from cell.config import CellConfig  # noqa: E402
from cell.core.commands import Command, VisionState  # noqa: E402
from cell.core.events import PickVerified, StateChanged  # noqa: E402
from tests.ports import free_port  # noqa: E402


def config(log_dir: Path) -> CellConfig:
    cfg = CellConfig()
    cfg.camera.width_px, cfg.camera.height_px = 960, 540
    cfg.sim.reference_marks_mm = []
    cfg.sim.speed_factor = 60.0  # simulated time: the feeder's minute passes in a second
    # bolts and nuts only: washers are left on the table and would make the cell wait for parts
    cfg.sim.feeder = cfg.sim.feeder.model_copy(
        update={"parts_per_minute": 20.0, "max_on_table": 25, "washer_share": 0.0}
    )
    cfg.service.capture_interval_s = 60.0  # simulated: 1 s of wall time (only when nothing is pickable)
    cfg.run.log_dir = log_dir
    cfg.service.http_port = free_port()
    cfg.service.web.max_screens = 40
    return cfg


def slow_readers(port: int, count: int) -> subprocess.Popen:
    """`count` slow readers of the event stream in a process of their own, until its stdin closes."""
    return subprocess.Popen(
        [sys.executable, __file__, "--readers", str(port), str(count)], stdin=subprocess.PIPE, cwd=Path(__file__).parent
    )


def one_job(setup: str, work: Path, picks: int, warmup: int) -> tuple[float, int]:
    """Picks per minute of a continuous shift with `setup` beside it, over `picks` picks after `warmup`,
    and the times the cell waited for parts meanwhile."""
    cfg = config(work / setup.replace(" ", "-") / str(time.monotonic_ns()))
    stamps: list[float] = []
    waits: list[int] = []  # the picks made before each wait

    def note(e: object) -> None:
        if isinstance(e, PickVerified) and e.result == "picked":
            stamps.append(time.monotonic())
        elif isinstance(e, StateChanged) and e.target == "wait":
            waits.append(len(stamps))

    with contextlib.ExitStack() as stack:
        service = open_service(cfg, True, stack)
        service.start()
        service.subscribe("picks", note, kinds=(PickVerified, StateChanged))
        if setup == "slow + raising":
            service.subscribe("slow", lambda e: time.sleep(2.0))
            service.subscribe("raising", lambda e: 1 / 0)
        elif "screen" in setup:
            from cell.web.server import screen_server

            server = screen_server(service, cfg)
            server.start()
            stack.callback(server.stop)
            count = 0 if "none open" in setup else int(setup.split()[0])
            if count:
                readers = slow_readers(server.port, count)
                stack.callback(readers.wait, 30)
                stack.callback(readers.stdin.close)  # type: ignore[union-attr]
                while len(server.app.screen.hub.screens) < count:  # every stream open before the job starts
                    time.sleep(0.05)
        service.command(Command.START_CONTINUOUS)
        deadline = time.monotonic() + 600
        while len(stamps) < warmup + picks:
            if time.monotonic() > deadline or service.snapshot().vision_state is VisionState.ERROR:
                raise SystemExit(f"{setup}: {len(stamps)} picks, not {warmup + picks}, in 600 s (or a fault)")
            time.sleep(0.05)
        service.command(Command.STOP)
        while service.snapshot().vision_state != VisionState.READY:
            if time.monotonic() > deadline:
                raise SystemExit(f"{setup}: the shift did not stop")
            time.sleep(0.05)
    counted_waits = sum(warmup <= n < warmup + picks for n in waits)
    return 60.0 * picks / (stamps[warmup + picks - 1] - stamps[warmup - 1]), counted_waits


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--jobs", type=int, default=5, help="rounds: one shift per set-up each")
    ap.add_argument("--picks", type=int, default=60, help="picks counted per shift")
    ap.add_argument("--warmup", type=int, default=10, help="picks left out at the start of each shift")
    args = ap.parse_args()
    setups = ["none", "slow + raising", "screen, none open", "1 slow screen", "30 slow screens"]
    rates: dict[str, list[float]] = {s: [] for s in setups}
    ratios: dict[str, list[float]] = {s: [] for s in setups}  # vs the shift of no listeners in the same round
    waits = 0
    with tempfile.TemporaryDirectory() as tmp:
        for n in range(args.jobs):
            for setup in setups if n % 2 == 0 else setups[::-1]:
                rate, waited = one_job(setup, Path(tmp), args.picks, args.warmup)
                rates[setup].append(rate)
                waits += waited
                print(f"round {n + 1} {setup}: {rate:.1f} picks/min, {waited} waits for parts", flush=True)
            for setup in setups:
                ratios[setup].append(rates[setup][-1] / rates["none"][-1])
    print()
    print(f"load average at the end: {' '.join(f'{v:.2f}' for v in os.getloadavg())}; waits for parts: {waits}")
    print("| listeners beside the cell | picks/min median | vs none in the same round: median | worst round |")
    print("|---|---|---|---|")
    for setup in setups:
        med = statistics.median(rates[setup])
        r = [100.0 * (x - 1.0) for x in ratios[setup]]
        vs = f"{statistics.median(r):+.1f} % | {min(r):+.1f} %" if setup != "none" else " | "
        print(f"| {setup} | {med:.1f} | {vs} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
