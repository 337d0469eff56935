"""coopmap sensors: the SICK LMS 200 (protocol, driver, emulator), the rotating-mirror 3D
scanner, beacons, and the simulator that stands in for the hardware."""

from sensors.errors import SensorError, WorldError

__all__ = ["SensorError", "WorldError"]
