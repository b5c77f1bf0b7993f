"""The GRBL emulator alone: the replies a GRBL 1.1 at default settings gives, byte for byte."""

from drivers.sim.grbl_emulator import BANNER, GrblEmulator


def run(emu: GrblEmulator, data: bytes, now_s: float = 0.0) -> bytes:
    return emu.receive(data, now_s) + emu.tick(now_s)


def test_banner_and_idle_status_at_defaults():
    emu = GrblEmulator()
    assert emu.power_on(0.0) == b"\r\nGrbl 1.1h ['$' for help]\r\n"
    assert run(emu, b"?") == b"<Idle|MPos:0.000,0.000,0.000|FS:0,0>\r\n"


def test_motion_runs_at_finite_speed_and_reports_run_then_idle():
    emu = GrblEmulator()
    emu.power_on(0.0)
    assert run(emu, b"G21\nG90\nG1 X10 F300\n") == b"ok\r\nok\r\nok\r\n"
    # 10 mm at 300 mm/min takes 2 s: half-way after 1 s.
    assert run(emu, b"?", 1.0) == b"<Run|MPos:5.000,0.000,0.000|FS:300,0>\r\n"
    assert run(emu, b"?", 2.5) == b"<Idle|MPos:10.000,0.000,0.000|FS:0,0>\r\n"


def test_motion_time_is_machine_time_whatever_the_speed_scale():
    emu = GrblEmulator(speed_scale=10)
    emu.power_on(0.0)
    run(emu, b"G1 X10 F300\nG4 P0\n")  # 2 s of machine time: 0.2 s of clock at 10x
    assert emu.tick(0.1) == b""
    assert emu.tick(0.25) == b"ok\r\n"
    assert emu.motion_time_s == 2.0


def test_dwell_is_a_barrier_answered_after_motion():
    emu = GrblEmulator()
    emu.power_on(0.0)
    assert run(emu, b"G0 X5\nG4 P0\n") == b"ok\r\n"  # G4's ok waits for the move (5 mm at 500 mm/min)
    assert emu.tick(0.3) == b""
    assert emu.tick(0.7) == b"ok\r\n"


def test_errors_with_grbl_codes():
    emu = GrblEmulator()
    emu.power_on(0.0)
    assert run(emu, b"G1 X1\n") == b"error:22\r\n"  # no feed rate yet
    assert run(emu, b"G0 A3\n") == b"error:20\r\n"  # no A axis on a stock GRBL
    assert run(emu, b"$H\n") == b"error:5\r\n"  # homing disabled by default ($22=0)
    assert run(emu, b"$Q\n") == b"error:3\r\n"


def test_reset_while_moving_is_alarm_3_and_locks_gcode():
    emu = GrblEmulator()
    emu.power_on(0.0)
    run(emu, b"G0 X50\n")
    out = run(emu, b"\x18", 0.1)
    assert out == b"ALARM:3\r\n" + BANNER + b"[MSG:'$H'|'$X' to unlock]\r\n"
    assert run(emu, b"G0 X1\n", 0.2) == b"error:9\r\n"


def test_feed_hold_freezes_and_resume_continues():
    emu = GrblEmulator()
    emu.power_on(0.0)
    run(emu, b"G1 X10 F300\n")
    run(emu, b"!", 1.0)
    assert run(emu, b"?", 3.0).startswith(b"<Hold:0|MPos:5.000,")
    run(emu, b"~", 3.0)
    assert run(emu, b"?", 5.5).startswith(b"<Idle|MPos:10.000,")


def test_gripper_listener_gets_pose_on_spindle_change():
    emu = GrblEmulator()
    events = []
    emu.add_tool_listener(lambda *a: events.append(a))
    emu.power_on(0.0)
    run(emu, b"G0 X5 Y6 Z7\nM3 S1000\n")
    run(emu, b"", 5.0)
    run(emu, b"M5\n", 5.0)
    assert events == [(True, 5.0, 6.0, 7.0, 0.0), (False, 5.0, 6.0, 7.0, 0.0)]
    assert emu.tool_pose() == (5.0, 6.0, 7.0, 0.0)
