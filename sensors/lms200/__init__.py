"""The SICK LMS 200 laser scanner: its serial protocol, a driver, a device emulator, captures."""
