"""Device drivers (actuators, cameras), scripted motions and acquisition; simulated hardware in ``drivers.sim``."""
