"""Plant telemetry: the cell on the plant's MQTT broker as a Sparkplug B edge node."""
