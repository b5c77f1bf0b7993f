"""Fault injection for the simulated cell run in-process: a full disk at the Nth audit write,
a signal when the run reaches a given point, and the emulated arm's state afterwards.

Fast settings (the perfect calibration, the emulator at its fastest) keep each run short;
the drivers, emulators, audit log and runner are the real ones.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
from dataclasses import dataclass
from pathlib import Path

import cell.sim.cell
from cell.audit import read_events
from cell.recordfile import RecordFile
from drivers.sim.dxl_emulator import SYNC_WRITE, WRITE, DxlBusEmulator, unstuff

REPO = Path(__file__).resolve().parents[1]
SIM_CONFIGS = {"serial": REPO / "configs" / "sim-grbl.toml", "dynamixel": REPO / "configs" / "sim-dynamixel.toml"}


def fast_config(tmp_path: Path, kind: str, max_attempts: int | None = None, speed_scale: float = 10000.0) -> Path:
    """The shipped simulated cell for `kind`, with the camera model as its calibration and fast motion;
    `max_attempts` > 0 ends the run with a fault (run.max_attempts_total) that leaves the arm working."""
    text = SIM_CONFIGS[kind].read_text()
    text = re.sub(r"emulator_speed_scale = [0-9.]+", f"emulator_speed_scale = {speed_scale}", text)
    if max_attempts:
        text = text.replace("[run]\n", f"[run]\nmax_attempts_total = {max_attempts}\n", 1)
    text = text.replace("[sim]\n", "[sim]\nperfect_calibration = true\n", 1)
    tmp_path.mkdir(parents=True, exist_ok=True)
    path = tmp_path / f"fast-{kind}.toml"
    path.write_text(text)
    return path


class FullDiskAt:
    """Audit-log files whose write number `n` (1-based, counted over the run) fails with ENOSPC,
    as do all later ones; `hook(n, line)` may act after each write instead (send a signal)."""

    def __init__(self, n: int | None = None, hook=None):
        self.n, self.hook, self.count, self.failed_line = n, hook, 0, None
        injector = self

        class Injected(RecordFile):
            def _write(self, data: bytes) -> int:
                injector.count += 1
                if injector.n is not None and injector.count >= injector.n:
                    if injector.failed_line is None:
                        injector.failed_line = data.decode()
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                written = super()._write(data)
                if injector.hook is not None:  # after the line is written: a signal does not lose it
                    injector.hook(injector.count, data)
                return written

        self.record_file = Injected

    def install(self, monkeypatch) -> FullDiskAt:
        monkeypatch.setattr("cell.audit.RecordFile", self.record_file)
        return self


@dataclass
class Captured:
    cell: object = None  # the SimCell of the last run


def capture_sim(monkeypatch) -> Captured:
    """Keep the simulated cell (world and emulator) of the run, to inspect after it ended."""
    got = Captured()
    real = cell.sim.cell.sim_cell

    @contextlib.contextmanager
    def keeping(config, *args, **kwargs):
        with real(config, *args, **kwargs) as sim:
            got.cell = sim
            yield sim

    monkeypatch.setattr(cell.sim.cell, "sim_cell", keeping)
    return got


def assert_arm_safe(sim, log_dir: Path) -> None:
    """Gripper open, no part held in the simulated world, and the arm's power per its policy:
    every servo's torque released (Dynamixel); the gantry not moving (GRBL holds its steppers).
    On failure the message carries the end of the run's operator log."""
    emu = sim.emulated.emulator
    logs = list(log_dir.glob("run-*.log"))
    tail = logs[0].read_text()[-4000:] if logs else "(no operator log)"
    with emu.lock:
        assert not emu.gripper_closed, "gripper left closed\n" + tail
        if isinstance(emu, DxlBusEmulator):
            assert not any(s.torque for s in emu.servos.values()), "a servo kept its torque\n" + tail
        else:
            assert emu.state.split(":")[0] in ("Idle", "Hold"), f"GRBL left in {emu.state}\n" + tail
    assert sim.world.held() is None, f"part {sim.world.held()} left in the gripper\n" + tail
    assert not Path(sim.emulated.port).parent.exists(), "the emulator's pty folder was left behind"


def audit_events(log_dir: Path) -> list[dict]:
    (path,) = log_dir.glob("run-*.jsonl")
    return read_events(path)


def bus_writes(emu: DxlBusEmulator, since: int = 0) -> list[tuple[int, bytes]]:
    """(address, data) of every write and sync write the bus received from packet `since` on."""
    emu.server.settle()
    out = []
    for frame in emu.packets_received[since:]:
        body = unstuff(frame[7:-2])
        if body[0] in (WRITE, SYNC_WRITE):
            out.append((int.from_bytes(body[1:3], "little"), bytes(body[3:] if body[0] == WRITE else body[5:])))
    return out


def motion_writes(emu: DxlBusEmulator, since: int) -> list[tuple[int, bytes]]:
    """Goal positions, and torque turned on, since packet `since`: what makes a servo move.
    A write's data is the value; a sync write's is (id, value) per servo."""

    def torque_on(data: bytes) -> bool:
        return any(data if len(data) == 1 else data[1::2])

    return [(a, d) for a, d in bus_writes(emu, since) if a == 116 or (a == 64 and torque_on(d))]
