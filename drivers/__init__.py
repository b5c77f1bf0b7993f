"""Device drivers (cameras, arms) and their emulated firmware (drivers.sim); imports nothing from cell."""
