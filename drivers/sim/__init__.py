"""Emulated firmware on pseudo-terminals (GRBL, Dynamixel bus) for driving the real drivers."""
