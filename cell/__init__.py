"""Vision-guided pick-and-place cell: calibration, vision, planning, state machine, CLI."""
