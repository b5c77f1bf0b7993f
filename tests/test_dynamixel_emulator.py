"""The emulated Protocol 2.0 bus alone, byte for byte (examples from the ROBOTIS e-manual)."""

import pytest

from drivers.sim.dxl_emulator import (
    PING,
    READ,
    REBOOT,
    STATUS,
    SYNC_READ,
    SYNC_WRITE,
    WRITE,
    DxlBusEmulator,
    crc16,
    packet,
    stuff,
    unstuff,
)


def test_packet_and_crc_match_the_e_manual_ping_example():
    assert packet(1, PING) == bytes.fromhex("ff ff fd 00 01 03 00 01 19 4e")
    assert packet(1, STATUS, bytes.fromhex("00 06 04 26")) == bytes.fromhex("ff ff fd 00 01 07 00 55 00 06 04 26 65 5d")
    assert crc16(bytes.fromhex("ff ff fd 00 01 03 00 01")) == 0x4E19


def test_byte_stuffing_round_trip():
    raw = bytes.fromhex("03 ff ff fd 01")
    assert stuff(raw) == bytes.fromhex("03 ff ff fd fd 01")
    assert unstuff(stuff(raw)) == raw


def test_ping_read_write_and_their_errors():
    emu = DxlBusEmulator(ids=(11,))
    assert emu.receive(packet(11, PING), 0.0) == packet(
        11, STATUS, bytes([0]) + (1020).to_bytes(2, "little") + bytes([52])
    )
    assert emu.receive(packet(7, PING), 0.0) == b""  # nobody there
    # Present position (132, 4 bytes) of a servo at the default home pose of joint 1.
    assert emu.receive(packet(11, READ, bytes([132, 0, 4, 0])), 0.0) == packet(
        11, STATUS, bytes([0]) + (2048).to_bytes(4, "little")
    )
    assert emu.receive(packet(11, WRITE, bytes([64, 0, 1])), 0.0) == packet(11, STATUS, b"\x00")  # torque on
    assert emu.receive(packet(11, WRITE, bytes([11, 0, 1])), 0.0) == packet(
        11, STATUS, b"\x07"
    )  # EEPROM locked: access error
    assert emu.receive(packet(11, WRITE, bytes([116, 0]) + (5000).to_bytes(4, "little")), 0.0) == packet(
        11, STATUS, b"\x06"
    )
    bad = bytearray(packet(11, PING))
    bad[-1] ^= 0xFF
    assert emu.receive(bytes(bad), 0.0) == packet(11, STATUS, b"\x03")  # CRC error


def test_sync_write_moves_at_profile_velocity_and_sync_read_answers_in_order():
    emu = DxlBusEmulator(ids=(1, 2))
    emu.receive(packet(0xFE, SYNC_WRITE, bytes([64, 0, 1, 0, 1, 1, 2, 1])), 0.0)  # torque on both
    # Profile velocity 100 (22.9 rev/min = 1563.3 ticks/s), goal 2048 + 1000 on servo 1.
    emu.receive(packet(0xFE, SYNC_WRITE, bytes([112, 0, 4, 0, 1]) + (100).to_bytes(4, "little")), 0.0)
    emu.receive(packet(0xFE, SYNC_WRITE, bytes([116, 0, 4, 0, 1]) + (3048).to_bytes(4, "little")), 0.0)
    emu.tick(0.1)
    reply = emu.receive(packet(0xFE, SYNC_READ, bytes([132, 0, 4, 0, 1, 2])), 0.1)
    assert reply == (
        packet(1, STATUS, bytes([0]) + (2048 + 156).to_bytes(4, "little"))
        + packet(2, STATUS, bytes([0]) + (2048).to_bytes(4, "little"))
    )
    emu.tick(1.0)
    assert emu.receive(packet(1, READ, bytes([122, 0, 1, 0])), 1.0) == packet(1, STATUS, b"\x00\x00")  # arrived


def test_motion_time_is_the_longest_servo_move_at_profile_velocity_whatever_the_speed_scale():
    emu = DxlBusEmulator(ids=(1, 2), speed_scale=10)
    emu.receive(packet(0xFE, SYNC_WRITE, bytes([64, 0, 1, 0, 1, 1, 2, 1])), 0.0)
    emu.receive(
        packet(
            0xFE,
            SYNC_WRITE,
            bytes([112, 0, 4, 0, 1]) + (100).to_bytes(4, "little") + bytes([2]) + (100).to_bytes(4, "little"),
        ),
        0.0,
    )
    goals = bytes([1]) + (2048 + 1000).to_bytes(4, "little") + bytes([2]) + (2048 - 500).to_bytes(4, "little")
    emu.receive(packet(0xFE, SYNC_WRITE, bytes([116, 0, 4, 0]) + goals), 0.0)
    for t in (0.02, 0.04, 0.06, 0.08):  # 1000 ticks at 1563.3 ticks/s: 0.64 s, 0.064 s of clock at 10x
        emu.tick(t)
    assert emu.motion_time_s == pytest.approx(1000 / (100 * 0.229 / 60 * 4096))


def test_overload_sets_alert_bit_until_reboot():
    emu = DxlBusEmulator(ids=(1,))
    emu.receive(packet(1, WRITE, bytes([64, 0, 1])), 0.0)
    emu.inject("overload", id=1)
    emu.receive(packet(1, WRITE, bytes([116, 0]) + (3000).to_bytes(4, "little")), 0.0)
    emu.tick(0.01)
    emu.tick(0.02)
    assert emu.receive(packet(1, READ, bytes([70, 0, 1, 0])), 0.02) == packet(1, STATUS, b"\x80\x20")
    assert emu.receive(packet(1, WRITE, bytes([64, 0, 1])), 0.02) == packet(1, STATUS, b"\x87")  # no torque back
    assert emu.receive(packet(1, REBOOT), 0.03) == packet(1, STATUS, b"\x80")
    assert emu.receive(packet(1, READ, bytes([70, 0, 1, 0])), 0.03) == packet(1, STATUS, b"\x00\x00")
