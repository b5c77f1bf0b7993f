"""One process per device: a second command on a port in use is refused (exit 2) naming the
process that holds it, before it sends a byte; the drivers open their ports exclusively."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import serial

from cell.cli import main
from cell.locks import Busy, holding, lock_path
from drivers.arm.config import ArmConfig
from drivers.arm.errors import ConnectionLost
from drivers.arm.factory import make_arm
from drivers.sim.dxl_emulator import DxlBusEmulator
from drivers.sim.grbl_emulator import GrblEmulator
from drivers.sim.pty_port import serve_pty

pytestmark = pytest.mark.timeout(90)  # opens ptys or subprocesses: never hang the suite

RUN_CELL = Path(sys.executable).parent / "run-cell"


def wait_for(predicate, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.02)


@pytest.mark.slow  # a run-cell subprocess jogging at the arm's real speed
def test_a_second_jog_on_the_port_of_a_moving_arm_is_refused_and_the_first_stops_safely(capsys):
    emu = GrblEmulator(speed_scale=1)  # 500 mm/min: the first jog is still moving when the second comes
    with serve_pty(emu) as path:
        first = subprocess.Popen(
            [str(RUN_CELL), "jog", "--arm", "serial", "--port", path, "--to", "150", "0", "50"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            wait_for(lambda: emu.state == "Run")
            assert main(["jog", "--arm", "serial", "--port", path, "--to", "10", "10", "10"]) == 2
            err = capsys.readouterr().err
            assert (
                err == f"run-cell jog: error: port {path} in use by run-cell pid {first.pid} "
                f"(hint: wait for it to finish or stop it; lock file {lock_path(path)})\n"
            )
            assert emu.state == "Run"  # not soft-reset, no ALARM:3: the second never opened the port
            first.send_signal(signal.SIGTERM)
            out, err = first.communicate(timeout=30)
        finally:
            first.kill()
            first.wait()
        assert first.returncode == 130
        assert err.strip().splitlines()[-1] == "run-cell jog: stopped: SIGTERM"
        wait_for(lambda: emu.state.startswith("Hold"), 5)  # the driver held the feed on the way out


@pytest.mark.parametrize("kind,emulator", [("serial", GrblEmulator), ("dynamixel", DxlBusEmulator)])
def test_the_drivers_open_their_port_exclusively(kind, emulator):
    """Even without the lock file (another program), the port cannot be opened twice."""
    with serve_pty(emulator()) as path:
        with serial.Serial(path, exclusive=True):
            arm = make_arm(ArmConfig(kind=kind, port=path))
            with pytest.raises(ConnectionLost, match="exclusively lock port"):
                arm.connect()


def test_a_lock_names_its_holder_and_dies_with_it(tmp_path):
    resource = tmp_path / "calibration.json"
    code = (
        "import sys, time\nfrom cell.locks import holding\n"
        f"with holding({str(resource)!r}, 'file'):\n    print('held', flush=True)\n    time.sleep(60)\n"
    )
    holder = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline() == "held\n"
        with pytest.raises(Busy, match=rf"file {resource} in use by -c pid {holder.pid}"):
            with holding(resource, "file"):
                pass
    finally:
        holder.kill()
        holder.wait()
    with holding(resource, "file", wait_s=1.0) as path:  # the kernel dropped the dead holder's lock
        assert path.read_text() == f"{Path(sys.argv[0]).name} pid {os.getpid()}"
    assert path.read_text() == ""


def test_a_symlinked_port_and_its_target_share_one_lock(tmp_path):
    target = tmp_path / "ttyUSB0"
    target.touch()
    link = tmp_path / "by-id"
    link.symlink_to(target)
    with holding(target):
        with pytest.raises(Busy, match=f"port {link} in use by"):
            with holding(link):
                pass
