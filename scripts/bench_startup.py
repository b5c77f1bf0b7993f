"""Start-up: how long an operator waits for `run-cell`, against importing the cell's libraries.

In one run, alternating, `--repeat` rounds (default 5), each command a fresh process:

  (a) `python -c "import cv2, numpy, asyncua, starlette, uvicorn"`: wall time until it exits;
  (b) `run-cell --dry-run`: wall time until its first line (stdout or stderr), then SIGINT and wait;
  (c) `run-cell serve --dry-run` (a temporary folder, free loopback ports): wall time until its
      `ready:` line, then SIGTERM and wait for its exit.

The venv's own python and its installed `run-cell` entry point run them (what an operator
starts), from a temporary folder. Wall time is what the operator waits; on a shared machine it
is noisy, so the goals are ratios within this run: b/a <= 1 and c/a <= 3 (issue 15), taken both
from the medians and from each round's own three processes (the worst round is printed). One
`serve` runs first, uncounted, so that the OPC UA model cache (~/.cache) is as after a first start.

    .venv/bin/python scripts/bench_startup.py [--repeat 5]
"""

from __future__ import annotations

import argparse
import os
import select
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests.ports import free_port  # noqa: E402

IMPORTS = "import cv2, numpy, asyncua, starlette, uvicorn"
LINE_TIMEOUT_S = 180.0  # a start this slow is a failure, not a figure
EXIT_TIMEOUT_S = 60.0


def venv_tools(venv: Path) -> tuple[Path, Path]:
    """The venv's python and its `run-cell` entry point, or a one-line error naming what is missing."""
    python, run_cell = venv / "bin" / "python", venv / "bin" / "run-cell"
    for path in (python, run_cell):
        if not os.access(path, os.X_OK):
            raise SystemExit(f"bench_startup: {path} is missing or not executable (hint: run `make venv` first)")
    return python, run_cell


def time_to_exit(cmd: list[str], cwd: Path) -> float:
    t0 = time.monotonic()
    rc = subprocess.run(cmd, cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=LINE_TIMEOUT_S)
    wall_s = time.monotonic() - t0
    if rc.returncode != 0:
        raise SystemExit(f"bench_startup: {' '.join(cmd)} exited {rc.returncode}")
    return wall_s


def time_to_line(cmd: list[str], cwd: Path, wanted: Callable[[str], bool], stop: signal.Signals) -> tuple[float, str]:
    """Wall time from starting `cmd` to the first output line (stdout and stderr together) that
    `wanted` accepts, and that line; then `stop` is sent and the process waited for (killed, and
    the bench failed, if it does not end in EXIT_TIMEOUT_S): nothing is left behind."""
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, cwd=cwd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    assert proc.stdout is not None  # stdout=PIPE
    fd, pending, seen = proc.stdout.fileno(), b"", list[str]()
    try:
        while True:
            left = LINE_TIMEOUT_S - (time.monotonic() - t0)
            if left <= 0 or not select.select([fd], [], [], left)[0]:
                raise SystemExit(f"bench_startup: no such line from {' '.join(cmd)} in {LINE_TIMEOUT_S:g} s: {seen}")
            chunk = os.read(fd, 65536)
            if not chunk:
                raise SystemExit(f"bench_startup: {' '.join(cmd)} ended (exit {proc.wait()}) before the line: {seen}")
            pending += chunk
            *lines, pending = pending.split(b"\n")
            for raw in lines:
                line = raw.decode(errors="replace")
                seen.append(line)
                if wanted(line):
                    return time.monotonic() - t0, line
    finally:
        _stop(proc, stop)


def _stop(proc: subprocess.Popen[bytes], sig: signal.Signals) -> None:
    if proc.poll() is None:
        proc.send_signal(sig)
    try:
        proc.communicate(timeout=EXIT_TIMEOUT_S)  # drains the pipe so the process never blocks on a write
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        raise SystemExit(
            f"bench_startup: {proc.args!r} did not end within {EXIT_TIMEOUT_S:g} s of {sig.name}"
        ) from None


def serve_cmd(run_cell: Path, folder: Path) -> list[str]:
    return [
        str(run_cell),
        "serve",
        "--dry-run",
        "--log-dir",
        str(folder / "logs"),
        "--opcua-port",
        str(free_port()),
        "--http-port",
        str(free_port()),
    ]


def one_round(python: Path, run_cell: Path, tmp: Path, n: int) -> tuple[float, float, float]:
    a = time_to_exit([str(python), "-c", IMPORTS], tmp)
    job = tmp / f"job-{n}"
    job.mkdir()
    b, _ = time_to_line([str(run_cell), "--dry-run"], job, lambda line: True, signal.SIGINT)
    serve = tmp / f"serve-{n}"
    serve.mkdir()
    c, _ = time_to_line(serve_cmd(run_cell, serve), serve, lambda line: line.startswith("ready:"), signal.SIGTERM)
    return a, b, c


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5, help="rounds of (a), (b), (c), alternating (default 5)")
    ap.add_argument("--venv", type=Path, default=REPO / ".venv", help="the venv whose python and run-cell run")
    args = ap.parse_args()
    if args.repeat < 1:
        raise SystemExit(f"bench_startup: --repeat {args.repeat}: at least 1")
    python, run_cell = venv_tools(args.venv)
    load_start = os.getloadavg()
    rounds: list[tuple[float, float, float]] = []
    with tempfile.TemporaryDirectory(prefix="startup-") as tmp_name:
        tmp = Path(tmp_name)
        warm = tmp / "warm-up"
        warm.mkdir()
        w, _ = time_to_line(serve_cmd(run_cell, warm), warm, lambda line: line.startswith("ready:"), signal.SIGTERM)
        print(f"warm-up serve (not counted): ready after {w:.2f} s", flush=True)
        for n in range(args.repeat):
            a, b, c = one_round(python, run_cell, tmp, n)
            rounds.append((a, b, c))
            print(f"round {n + 1}: (a) imports {a:.2f} s, (b) first line {b:.2f} s, (c) ready {c:.2f} s", flush=True)
    load_end = os.getloadavg()
    report(rounds, load_start, load_end)
    return 0


def report(
    rounds: list[tuple[float, float, float]], load_start: tuple[float, ...], load_end: tuple[float, ...]
) -> None:
    names = (
        "(a) python -c 'import cv2, numpy, asyncua, starlette, uvicorn'",
        "(b) run-cell --dry-run, first line",
        "(c) run-cell serve --dry-run, to its ready: line",
    )
    medians = [statistics.median(r[i] for r in rounds) for i in range(3)]
    for i, name in enumerate(names):
        print(f"{name}: median {medians[i]:.2f} s, worst {max(r[i] for r in rounds):.2f} s (wall)")
    b_ratio, c_ratio = medians[1] / medians[0], medians[2] / medians[0]
    worst_b, worst_c = max(r[1] / r[0] for r in rounds), max(r[2] / r[0] for r in rounds)
    print(
        f"b/a: {b_ratio:.2f} of medians, worst round {worst_b:.2f} (goal <= 1): {'met' if b_ratio <= 1 else 'NOT met'}"
    )
    print(
        f"c/a: {c_ratio:.2f} of medians, worst round {worst_c:.2f} (goal <= 3): {'met' if c_ratio <= 3 else 'NOT met'}"
    )
    print(
        f"load average (1, 5, 15 min): at start {' '.join(f'{x:.2f}' for x in load_start)}, "
        f"at end {' '.join(f'{x:.2f}' for x in load_end)}; {os.cpu_count()} CPUs"
    )


if __name__ == "__main__":
    sys.exit(main())
