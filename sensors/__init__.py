"""coopmap sensors: the SICK LMS 200 (protocol, driver, emulator), the rotating-mirror 3D
scanner, beacons, and the simulator that stands in for the hardware."""

from sensors.jitcache import key_numba_cache

key_numba_cache()  # before any kernel is compiled or loaded (sensors.jitcache)

from sensors.errors import SensorError, WorldError  # noqa: E402

__all__ = ["SensorError", "WorldError"]
