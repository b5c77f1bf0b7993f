"""The fault-injection matrix on the simulated cell, in-process, through the real drivers and
their emulators: a full disk at an audit write, a stop or pause signal at a point of the run.

Whatever fails, the run must end with the arm safe (gripper open, no part held, torque per
the arm's policy, the emulator's pty gone) and the documented exit code. The default suite
takes one write of every (event kind, state) the run produces, and the write right after
the gripper closed on both arms; --exhaustive sweeps every write of a whole run and every
signal in every state on both arms.
"""

from __future__ import annotations

import itertools
import os
import signal

import pytest

from cell.cli import main
from tests.faults import FullDiskAt, assert_arm_safe, audit_events, capture_sim, fast_config

# Whole runs of the cell or of recalibrations (slow); ptys and subprocesses must never hang the suite.
pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]

KINDS = ("dynamixel", "serial")


def run_cell(tmp_path, kind: str, max_attempts: int | None = None) -> int:
    cfg = fast_config(tmp_path, kind, max_attempts)
    return main(["--config", str(cfg), "--log-dir", str(tmp_path / "logs")])


@pytest.fixture(scope="module")
def writes(tmp_path_factory):
    """(kind, state) of each audit write: of a normal run's first picks (cut short by a full
    disk at write 40) and of a run that faults after its first pick (run.max_attempts_total), per arm."""
    out = {}
    with pytest.MonkeyPatch.context() as mp:
        for kind in KINDS:
            d = tmp_path_factory.mktemp(f"ref-{kind}")
            FullDiskAt(40).install(mp)
            assert run_cell(d / "a", kind) == 3
            FullDiskAt(None).install(mp)
            assert run_cell(d / "b", kind, max_attempts=1) == 3
            out[kind] = {
                "normal": [(e["kind"], e["state"]) for e in audit_events(d / "a" / "logs")],
                "fault": [(e["kind"], e["state"]) for e in audit_events(d / "b" / "logs")],
            }
    return out


def firsts(seq: list[tuple[str, str]]) -> dict[tuple[str, str], int]:
    """Write number (1-based) of the first write of each (kind, state)."""
    out = {}
    for n, pair in enumerate(seq, start=1):
        out.setdefault(pair, n)
    return out


# Which writes the default suite fails: every (kind, state) pair once, arms taking turns; the
# runs are chosen by name here and resolved against the reference runs in the test.
NORMAL_PAIRS = [
    ("config", "idle"),
    ("run_start", "idle"),
    ("arm", "idle"),
    ("state", "idle"),
    ("arm", "home"),
    ("state", "home"),
    ("state", "capture"),
    ("frame", "locate"),
    ("state", "locate"),
    ("target", "plan"),
    ("state", "plan"),
    ("arm", "pick"),
    ("state", "pick"),
    ("arm", "place"),
    ("state", "place"),
    ("verify", "verify"),
    ("state", "verify"),
]
FAULT_PAIRS = [
    ("fault", "plan"),
    ("safe_step", "plan"),
    ("state", "plan"),
    ("sim_truth", "fault"),
    ("summary", "fault"),
    ("run_end", "fault"),
]
CASES = (
    [("normal", pair, KINDS[i % 2]) for i, pair in enumerate(NORMAL_PAIRS)]
    + [("fault", pair, KINDS[i % 2]) for i, pair in enumerate(FAULT_PAIRS)]
    + [("normal", "after close_gripper", kind) for kind in KINDS]
)


def write_number(writes, kind: str, run: str, what) -> int:
    seq = writes[kind][run]
    if what == "after close_gripper":  # the case: the disk fills as the jaws hold a nut
        return seq.index(("arm", "pick"), 13) + 1 + 4  # approach, down, close, then the lift's write
    return firsts(seq[: -1 if run == "normal" else None])[tuple(what)]


def full_disk_run(tmp_path, kind: str, n: int, monkeypatch, capsys, max_attempts: int | None = None):
    """Run with the disk full from audit write n: (exit code, injector, captured sim, stderr).

    On an overloaded machine the emulated servos can miss the driver's 34 ms status timeout
    and fault the run before write n; that run (still checked to be safe) does not test the
    full disk, so it is run once more."""
    for attempt in (1, 2):
        where = tmp_path / f"try{attempt}"
        disk = FullDiskAt(n).install(monkeypatch)
        sim = capture_sim(monkeypatch)
        code = run_cell(where, kind, max_attempts)
        err = capsys.readouterr().err
        if disk.failed_line is not None or attempt == 2:
            return code, disk, sim, err, where / "logs"
        assert code == 3 and sim.cell is not None, err
        assert_arm_safe(sim.cell, where / "logs")


@pytest.mark.parametrize("run,what,kind", CASES, ids=lambda v: "-".join(v) if isinstance(v, tuple) else str(v))
def test_a_full_disk_at_an_audit_write_leaves_the_arm_safe_and_exits_3(
    writes, run, what, kind, tmp_path, monkeypatch, capsys
):
    n = write_number(writes, kind, run, what)
    code, disk, sim, err, logs = full_disk_run(tmp_path, kind, n, monkeypatch, capsys, 1 if run == "fault" else None)
    assert code == 3
    assert disk.failed_line is not None and f'"seq":{n},' in disk.failed_line, err
    assert "write failed (No space left on device)" in err
    last = err.strip().splitlines()[-1]
    assert last.startswith("run-cell: ") and "exit 3" in last or "cannot write event 1 (config)" in last
    events = audit_events(logs)
    assert [e["seq"] for e in events] == list(range(1, n))  # everything before the full disk kept, in order
    if sim.cell is None:  # the first write failed before any device was opened
        assert n == 1
        return
    assert_arm_safe(sim.cell, logs)
    assert "the audit log is incomplete; the run's summary:" in err


# ---- signals -----------------------------------------------------------------------------------
REASONS = {signal.SIGINT: "Ctrl-C", signal.SIGTERM: "SIGTERM", signal.SIGHUP: "SIGHUP (terminal closed)"}
# Where in the run a signal comes: at the write of this (kind, state), i.e. during that state's work.
POINTS = {
    "start-up": ("run_start", "idle"),
    "idle": ("arm", "idle"),
    "home": ("arm", "home"),
    "capture": ("state", "capture"),
    "locate": ("frame", "locate"),
    "plan": ("target", "plan"),
    "pick": "after close_gripper",
    "place": ("arm", "place"),
    "verify": ("verify", "verify"),
}
STOPS = list(REASONS)
# The default suite: every point once, the three stop signals and both arms taking turns.
STOP_CASES = [(point, STOPS[i % 3], KINDS[i % 2]) for i, point in enumerate(POINTS)]
ALL_STOP_CASES = [c for c in itertools.product(POINTS, STOPS, KINDS) if c not in STOP_CASES]


def signal_at(n: int, sig: int, then=None) -> FullDiskAt:
    """Audit writes that send `sig` to this process after write n (a disk that never fills);
    then(data) is called on every later write; `.sent` says whether the signal went."""

    def hook(count, data):
        if count == n:
            injector.sent = True
            os.kill(os.getpid(), sig)
        elif count > n and then is not None:
            then(data)

    injector = FullDiskAt(None, hook=hook)
    injector.sent = False
    return injector


def signalled_run(
    tmp_path, kind: str, n: int, sig: int, monkeypatch, capsys, then=None, max_attempts: int | None = None
):
    """Run with `sig` sent at write n, then(data, sim) called on each later write: (exit code,
    captured sim, stderr, log folder). A run the
    overloaded machine faulted before write n (the servos' 34 ms status timeout) never got the
    signal: it is checked safe and run once more."""
    for attempt in (1, 2):
        where = tmp_path / f"try{attempt}"
        sim = capture_sim(monkeypatch)
        injector = signal_at(n, sig, then and (lambda data, sim=sim: then(data, sim))).install(monkeypatch)
        code = run_cell(where, kind, max_attempts)
        err = capsys.readouterr().err
        if injector.sent or attempt == 2:
            return code, sim, err, where / "logs"
        assert code == 3 and sim.cell is not None, err
        assert_arm_safe(sim.cell, where / "logs")


def point_number(writes, kind: str, point: str) -> int:
    what = POINTS[point]
    return write_number(writes, kind, "normal", what)


def check_stopped(logs, sim, sig, err: str) -> None:
    assert_arm_safe(sim.cell, logs)
    events = audit_events(logs)
    end = events[-1]
    assert end["kind"] == "run_end" and end["outcome"] == "stopped" and end["reason"].startswith(REASONS[sig])
    assert err.strip().splitlines()[-1].startswith("run-cell: stopped in ")
    assert err.strip().splitlines()[-1].endswith(f"{REASONS[sig]} (arm made safe; exit 130)")


def _stop_case(writes, point, sig, kind, tmp_path, monkeypatch, capsys):
    code, sim, err, logs = signalled_run(tmp_path, kind, point_number(writes, kind, point), sig, monkeypatch, capsys)
    assert code == 130, err
    check_stopped(logs, sim, sig, err)


@pytest.mark.parametrize("point,sig,kind", STOP_CASES, ids=lambda v: getattr(v, "name", v))
def test_a_stop_signal_in_each_state_stops_safely(writes, point, sig, kind, tmp_path, monkeypatch, capsys):
    _stop_case(writes, point, sig, kind, tmp_path, monkeypatch, capsys)


@pytest.mark.exhaustive
@pytest.mark.parametrize("point,sig,kind", ALL_STOP_CASES, ids=lambda v: getattr(v, "name", v))
def test_every_stop_signal_in_every_state_on_both_arms(writes, point, sig, kind, tmp_path, monkeypatch, capsys):
    _stop_case(writes, point, sig, kind, tmp_path, monkeypatch, capsys)


def test_a_stop_signal_before_any_device_is_opened(tmp_path, monkeypatch, capsys):
    signal_at(1, signal.SIGTERM).install(monkeypatch)
    sim = capture_sim(monkeypatch)
    assert run_cell(tmp_path, "serial") == 130
    assert sim.cell is None
    assert capsys.readouterr().err.strip().splitlines()[-1] == "run-cell: stopped: SIGTERM"
    assert audit_events(tmp_path / "logs")[-1]["outcome"] == "stopped"


def test_a_stop_signal_during_plate_calibration(tmp_path, monkeypatch, capsys):
    """The slow part of start-up: the pty of the emulated arm is not opened, nothing is left."""
    import cell.sim.cell as simcell

    real = simcell.calibrate

    def hung_up(*a, **k):
        os.kill(os.getpid(), signal.SIGHUP)
        return real(*a, **k)

    monkeypatch.setattr(simcell, "calibrate", hung_up)
    monkeypatch.setattr(simcell, "_PLATE_FITS", {})  # fit now, not from an earlier run's cache
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))  # nor from an earlier process's
    cfg = fast_config(tmp_path, "dynamixel")
    cfg.write_text(cfg.read_text().replace("perfect_calibration = true\n", ""))
    sim = capture_sim(monkeypatch)
    assert main(["--config", str(cfg), "--log-dir", str(tmp_path / "logs")]) == 130
    assert capsys.readouterr().err.strip().splitlines()[-1] == "run-cell: stopped: SIGHUP (terminal closed)"
    assert audit_events(tmp_path / "logs")[-1]["reason"] == "SIGHUP (terminal closed)"
    assert sim.cell is None  # stopped inside the plate fit: the emulated arm's pty was never opened


def test_sigusr1_during_plate_calibration_pauses_before_the_first_motion(tmp_path, monkeypatch, capsys):
    import cell.sim.cell as simcell

    real = simcell.calibrate

    def paused(*a, **k):
        os.kill(os.getpid(), signal.SIGUSR1)
        return real(*a, **k)

    def at_pause(data: bytes):
        if b'"target":"paused"' in data:
            os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr(simcell, "calibrate", paused)
    monkeypatch.setattr(simcell, "_PLATE_FITS", {})  # fit now, not from an earlier run's cache
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))  # nor from an earlier process's
    FullDiskAt(None, hook=lambda count, data: at_pause(data)).install(monkeypatch)
    sim = capture_sim(monkeypatch)
    cfg = fast_config(tmp_path, "serial")
    cfg.write_text(cfg.read_text().replace("perfect_calibration = true\n", ""))
    assert main(["--config", str(cfg), "--log-dir", str(tmp_path / "logs")]) == 130
    events = audit_events(tmp_path / "logs")
    assert [e["command"] for e in events if e["kind"] == "arm"] == ["connect"]  # paused before anything moved
    assert [(e["source"], e["target"]) for e in events if e["kind"] == "state"][:2] == [
        ("idle", "home"),
        ("home", "paused"),
    ]
    check_stopped(tmp_path / "logs", sim, signal.SIGTERM, capsys.readouterr().err)


def test_a_stop_signal_during_the_safe_stop_does_not_cut_it_short(writes, tmp_path, monkeypatch, capsys):
    n = firsts(writes["serial"]["fault"])[("safe_step", "plan")]
    signal_at(n, signal.SIGINT).install(monkeypatch)
    sim = capture_sim(monkeypatch)
    assert run_cell(tmp_path, "serial", max_attempts=1) == 3  # the fault stands; Ctrl-C did not interrupt
    assert_arm_safe(sim.cell, tmp_path / "logs")
    steps = [(e["step"], e["ok"]) for e in audit_events(tmp_path / "logs") if e["kind"] == "safe_step"]
    assert steps == [("finish motion", True), ("open gripper", True), ("home", True), ("release torque", True)]


PAUSE_POINTS = ["start-up", "pick", "verify"]  # the default suite; --exhaustive takes the other states


def _pause_case(writes, point, tmp_path, monkeypatch, capsys):
    kind = "serial"
    seen = {}

    def at_pause(data: bytes, sim):
        if b'"target":"paused"' in data and not seen:
            seen["held"] = sim.cell.world.held()
            os.kill(os.getpid(), signal.SIGTERM)  # stop while paused

    code, sim, err, logs = signalled_run(
        tmp_path, kind, point_number(writes, kind, point), signal.SIGUSR1, monkeypatch, capsys, then=at_pause
    )
    assert code == 130, err
    assert seen["held"] is None  # paused with nothing in the gripper
    check_stopped(logs, sim, signal.SIGTERM, err)


@pytest.mark.parametrize("point", PAUSE_POINTS)
def test_sigusr1_pauses_at_a_safe_point(writes, point, tmp_path, monkeypatch, capsys):
    _pause_case(writes, point, tmp_path, monkeypatch, capsys)


@pytest.mark.exhaustive
@pytest.mark.parametrize("point", [p for p in POINTS if p not in PAUSE_POINTS])
def test_sigusr1_pauses_at_a_safe_point_in_every_state(writes, point, tmp_path, monkeypatch, capsys):
    _pause_case(writes, point, tmp_path, monkeypatch, capsys)


def test_sigusr1_during_start_up_pauses_before_the_first_motion_and_resumes(writes, tmp_path, monkeypatch, capsys):
    sim = capture_sim(monkeypatch)
    seen = {}

    def at_pause(data: bytes):
        if b'"target":"paused"' in data and not seen:
            seen["pose"] = sim.cell.emulated.emulator.tool_pose()
            seen["line"] = data.decode()
            os.kill(os.getpid(), signal.SIGUSR1)  # resume

    signal_at(point_number(writes, "serial", "start-up"), signal.SIGUSR1, then=at_pause).install(monkeypatch)
    assert run_cell(tmp_path, "serial", max_attempts=1) == 3  # one pick after resuming, then the safety stop
    events = audit_events(tmp_path / "logs")
    states = [(e["source"], e["target"]) for e in events if e["kind"] == "state"]
    assert states[:4] == [("idle", "home"), ("home", "paused"), ("paused", "home"), ("home", "capture")]
    before = [
        e["command"]
        for e in events[: events.index(next(e for e in events if e.get("target") == "paused"))]
        if e["kind"] == "arm"
    ]
    assert before == ["connect"]  # nothing had moved when it paused
    assert [e["kind"] for e in events].count("target") == 1 and any(
        e["kind"] == "verify" and e["result"] == "picked" for e in events
    )


# ---- the exhaustive sweep (--exhaustive): a full disk at every audit write of a whole run -------------
@pytest.fixture(scope="module")
def whole_run_writes(tmp_path_factory):
    counts = {}
    for kind in KINDS:
        d = tmp_path_factory.mktemp(f"whole-{kind}")
        assert run_cell(d, kind) == 0
        counts[kind] = len(audit_events(d / "logs"))
    return counts


@pytest.mark.exhaustive
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("n", range(1, 321))
def test_a_full_disk_at_every_audit_write(whole_run_writes, kind, n, tmp_path, monkeypatch, capsys):
    if n > whole_run_writes[kind]:
        pytest.skip(f"the {kind} run writes {whole_run_writes[kind]} events")
    code, disk, sim, err, logs = full_disk_run(tmp_path, kind, n, monkeypatch, capsys)
    assert code == 3 and disk.failed_line is not None, err
    assert [e["seq"] for e in audit_events(logs)] == list(range(1, n))
    if sim.cell is not None:
        assert_arm_safe(sim.cell, logs)


# ---- a real full disk ----------------------------------------------------------------------------
@pytest.fixture
def tiny_filesystem(tmp_path):
    """A 64 KiB tmpfs (needs root and mount(8)); skipped, saying why, where that is not allowed."""
    import shutil
    import subprocess

    where = tmp_path / "tiny"
    where.mkdir()
    if os.geteuid() != 0 or not shutil.which("mount"):
        pytest.skip("mounting a 64 KiB tmpfs needs root and mount(8); the injected ENOSPC cases cover the logic")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(where)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")
    try:
        yield where
    finally:
        subprocess.run(["umount", str(where)], check=False)


def test_a_real_full_disk_mid_run(tiny_filesystem, monkeypatch, capsys):
    sim = capture_sim(monkeypatch)
    cfg = fast_config(tiny_filesystem.parent, "dynamixel")
    assert main(["--config", str(cfg), "--log-dir", str(tiny_filesystem)]) == 3
    err = capsys.readouterr().err
    assert "write failed (No space left on device)" in err and "the audit log is incomplete" in err
    assert "simulated truth: " in err and "gripper:" not in err
    assert (
        err.strip()
        .splitlines()[-1]
        .endswith(
            "No space left on device (hint: free space on its filesystem or "
            "set run.log_dir elsewhere) (arm made safe; exit 3)"
        )
    )
    assert_arm_safe(sim.cell, tiny_filesystem)
