"""The domain core: commands, roles, the one command table, events, the event bus, the records every
consumer reads and the registry of part classes. It imports nothing else of the cell: history,
telemetry, OPC UA, the screen and the CLI depend on it, never on each other."""
