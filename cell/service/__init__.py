"""The cell as a long-running line service (`run-cell serve`): one process owning the camera,
calibration and arm, driven by commands from OPC UA, the web screen or signals."""
