"""Device drivers (Modbus turntable, serial compass) and their simulators. Arrives with issue 3."""


class DriverError(Exception):
    """Base of every driver error."""
