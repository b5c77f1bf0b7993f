"""Device drivers (cameras, arms) and their simulated twins (drivers.sim)."""
