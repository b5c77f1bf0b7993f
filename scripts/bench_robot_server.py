#!/usr/bin/env python3
"""The robot server's latency: NEXT-to-answer with a frame already located, beside that frame's
locate time and an unknown request's round trip (the socket and the parser alone), in the same run; and the cell's share of a pick cycle.

The line service runs in-process on the simulated cell as a dry-run shift (arm.kind robot-server,
simulated_robot = false) and this script plays the robot over the real TCP socket, as the URScript
program in docs/robots.md does, except that before each NEXT it waits (polling STATE every 2 ms) until the
cell has located the frame, planned and offered the pick (STATE 3): the NEXT then measures the
server alone. Per pick it also measures the cell's time: from the robot's PLACED to the next pick
offered (capture, locate, verify, plan), against which the simulated arm's motion per pick (the
simulated world's distance / speed model, `sim.speed_mm_s`) stands for the robot's part.

Each round is a fresh service clearing the default table (17 picks); --rounds rounds.

    python scripts/bench_robot_server.py [--rounds 4] [--width 1920 --height 1080]
"""

from __future__ import annotations

import argparse
import contextlib
import socket
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cell.commands.serve import open_service  # noqa: E402
from cell.config import CellConfig  # noqa: E402
from cell.core.commands import Command, VisionState  # noqa: E402
from cell.service.shiftlog import read_shift  # noqa: E402
from drivers.arm.config import RobotServerConfig  # noqa: E402
from drivers.arm.robot_server import RobotServerArm, StateNo  # noqa: E402


class Robot:
    def __init__(self, address: tuple[str, int]):
        self.sock = socket.create_connection(address, timeout=30)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.file = self.sock.makefile("rb")

    def ask(self, line: str) -> list[float]:
        self.sock.sendall(line.encode() + b"\n")
        answer = self.file.readline().decode().strip()
        return [float(v) for v in answer[1:-1].split(",")]

    def timed(self, line: str) -> tuple[list[float], float]:
        t0 = time.perf_counter()
        answer = self.ask(line)
        return answer, time.perf_counter() - t0


def one_round(width: int, height: int, log_dir: Path) -> dict[str, list[float]]:
    cfg = CellConfig()
    cfg.camera.width_px, cfg.camera.height_px = width, height
    cfg.run.log_dir = log_dir
    cfg.sim.feeder = cfg.sim.feeder.model_copy(update={"parts_per_minute": 0, "clear_after_s": 0})
    cfg.arm.kind = "robot-server"
    cfg.robot_server = RobotServerConfig(port=0, simulated_robot=False)
    out: dict[str, list[float]] = {"next_s": [], "bare_s": [], "cell_s": []}
    with contextlib.ExitStack() as stack:
        service = open_service(cfg, True, stack)
        service.start()
        arm = service.cell.arm
        assert isinstance(arm, RobotServerArm)
        robot = Robot(arm.server.address)
        service.command(Command.START_SINGLE)
        placed_at = time.perf_counter()
        while True:
            state = robot.ask("STATE")
            if state[0] == StateNo.OFFERED:
                out["cell_s"].append(time.perf_counter() - placed_at)
                answer, latency = robot.timed("NEXT")
                assert answer[0] == 1, answer
                out["next_s"].append(latency)
                no = int(answer[6])
                assert robot.ask(f"PICKED {no}") == [1]
                assert robot.ask(f"PLACED {no}") == [1]
                placed_at = time.perf_counter()
                bare, rtt = robot.timed("HELLO")  # answered (-2,1) by the parser alone
                assert bare == [-2, 1]
                out["bare_s"].append(rtt)
            elif state[0] == StateNo.READY and service.snapshot().vision_state == VisionState.READY:
                break
            else:
                time.sleep(0.002)  # the robot's poll of STATE
        out["motion_s"] = [service.cell.motion_time_s() / max(len(out["next_s"]), 1)]
    events = read_shift(log_dir)
    out["locate_s"] = [e["locate_ms"] / 1e3 for e in events if e["kind"] == "frame"]
    return out


def pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, round(q * (len(s) - 1)))]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--width", type=int, default=CellConfig().camera.width_px)
    ap.add_argument("--height", type=int, default=CellConfig().camera.height_px)
    args = ap.parse_args()
    totals: dict[str, list[float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds):
            got = one_round(args.width, args.height, Path(tmp) / f"round{r}")
            for k, v in got.items():
                totals.setdefault(k, []).extend(v)
            print(f"round {r + 1}: {len(got['next_s'])} picks", flush=True)
    ms = 1e3
    print(f"camera {args.width} x {args.height}, {args.rounds} rounds, {len(totals['next_s'])} picks")
    for name, key in (
        ("NEXT to answer, pick already offered", "next_s"),
        ("unknown request round trip (socket, parser)", "bare_s"),
        ("locate, per frame (same run)", "locate_s"),
        ("cell per pick: PLACED to the next offer", "cell_s"),
    ):
        v = totals[key]
        print(f"{name:42s} median {statistics.median(v) * ms:8.3f} ms  p99 {pct(v, 0.99) * ms:8.3f} ms  (n={len(v)})")
    cell = statistics.median(totals["cell_s"])
    motion = statistics.median(totals["motion_s"])
    print(
        f"the simulated arm's motion per pick (sim.speed_mm_s model): {motion:.2f} s; "
        f"the cell's share of a pick cycle: {cell / (cell + motion):.1%}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
