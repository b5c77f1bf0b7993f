"""Simulated twins of the hardware: camera model, renderers, emulated firmware."""
