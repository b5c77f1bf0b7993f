#!/usr/bin/env python3
"""Picks per minute with misbehaving listeners beside the cell, against none, in the same run.

The line service runs in-process on the simulated cell (960 x 540 camera, no feeder) and clears
the built-in table (17 parts) once per job; the three set-ups take turns, job after job:

- none: the service's own subscribers only (ledger, nothing else);
- slow + raising: a subscriber that sleeps 2 s on every event and one that raises on every event;
- 30 slow screens: the operator screen served over HTTP with 30 event streams open, each read
  1 KiB a second (far slower than the screen sends).

Picks per minute is 60 x picks / the job's wall time (JobStarted to JobEnded). Wall time on a
shared machine varies job to job, so each set-up's median over --jobs jobs is compared, and the
worst single job is reported too.

    python scripts/bench_subscribers.py [--jobs 5]
"""

from __future__ import annotations

import argparse
import contextlib
import socket
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cell.commands.serve import open_service  # noqa: E402
from cell.config import CellConfig  # noqa: E402
from cell.events import JobEnded, JobStarted, PickVerified  # noqa: E402
from cell.service.api import Command, VisionState  # noqa: E402


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def config(log_dir: Path) -> CellConfig:
    cfg = CellConfig()
    cfg.camera.width_px, cfg.camera.height_px = 960, 540
    cfg.sim.reference_marks_mm = []
    cfg.sim.feeder = cfg.sim.feeder.model_copy(update={"parts_per_minute": 0})
    cfg.run.log_dir = log_dir
    cfg.service.http_port = free_port()
    cfg.service.web.max_screens = 40
    return cfg


def slow_reader(port: int, stop: threading.Event) -> None:
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        s.sendall(b"GET /api/events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        s.settimeout(2.0)
        while not stop.wait(1.0):
            with contextlib.suppress(OSError):
                if not s.recv(1024):
                    return


def one_job(setup: str, work: Path) -> tuple[float, int]:
    """(picks per minute, picks) of one single job with `setup` beside it."""
    cfg = config(work / setup / str(time.monotonic_ns()))
    stop = threading.Event()
    times: dict[str, float] = {}
    picks = []
    with contextlib.ExitStack() as stack:
        service = open_service(cfg, True, stack)
        service.start()
        service.subscribe(
            "bench",
            lambda e: times.setdefault(e.kind, time.monotonic()) if isinstance(e, (JobStarted, JobEnded)) else None,
            kinds=(JobStarted, JobEnded),
        )
        service.subscribe("picks", picks.append, kinds=(PickVerified,))
        if setup == "slow + raising":
            service.subscribe("slow", lambda e: time.sleep(2.0))
            service.subscribe("raising", lambda e: 1 / 0)
        elif setup == "30 slow screens":
            from cell.web.server import screen_server

            server = screen_server(service, cfg)
            server.start()
            stack.callback(server.stop)
            readers = [threading.Thread(target=slow_reader, args=(server.port, stop), daemon=True) for _ in range(30)]
            for r in readers:
                r.start()
            stack.callback(stop.set)
        service.command(Command.START_SINGLE)
        deadline = time.monotonic() + 600
        while service.snapshot().vision_state != VisionState.READY or "job_end" not in times:
            if time.monotonic() > deadline:
                raise SystemExit(f"{setup}: the job did not end within 600 s")
            time.sleep(0.05)
        made = sum(p.result == "picked" for p in picks)
        wall_s = times["job_end"] - times["job_start"]
    return 60.0 * made / wall_s, made


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--jobs", type=int, default=5, help="jobs per set-up (taking turns)")
    args = ap.parse_args()
    setups = ["none", "slow + raising", "30 slow screens"]
    rates: dict[str, list[float]] = {s: [] for s in setups}
    with tempfile.TemporaryDirectory() as tmp:
        for n in range(args.jobs):
            for setup in setups:
                rate, made = one_job(setup, Path(tmp))
                if made != 17:
                    print(f"{setup}: job {n + 1} picked {made} of 17", flush=True)
                rates[setup].append(rate)
                print(f"job {n + 1} {setup}: {rate:.1f} picks/min ({made} picks)", flush=True)
    base = statistics.median(rates["none"])
    print()
    print("| listeners beside the cell | picks/min median | worst job | median vs none |")
    print("|---|---|---|---|")
    for setup in setups:
        med = statistics.median(rates[setup])
        print(f"| {setup} | {med:.1f} | {min(rates[setup]):.1f} | {100.0 * (med / base - 1.0):+.1f} % |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
