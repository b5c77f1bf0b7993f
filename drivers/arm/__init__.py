"""Arm drivers: one interface (base.Arm), a serial G-code driver, a Dynamixel driver, a mock."""
