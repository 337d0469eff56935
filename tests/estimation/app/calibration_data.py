"""A small simulated calibration recording shared by the calibration tests.

Two robots in a plain room (floor, four walls, a ceiling at 3 m, two pieces of furniture) stop
at poses where each sees the other's beacon at different bearings. The mission's configuration
holds the true rig (the simulator uses it as the truth); :data:`START` is a wrong calibration
to start from.
"""

from __future__ import annotations

import math
from pathlib import Path

import yaml

from estimation.app.sim.simulate import run_simulation

#: The rig the simulator builds (its truth).
TRUE = {
    "mirror": {"axis_offset_m": 0.11, "elevation_offset_deg": 1.0, "edge_on_motor_phase_deg": 40.0},
    "beacon": {"height_m": 1.65, "offset_m": 0.27},
}
#: A wrong calibration: d +30 mm, φ0 +3°, motor phase +60° (−1.5° of elevation), beacon height
#: −30 cm (every detection is gated out at the configured height), offset −7 cm.
START = {
    "mirror": {
        "axis_offset_m": 0.14,
        "elevation_offset_deg": 4.0,
        "edge_on_motor_phase_deg": 100.0,
    },
    "beacon": {"height_m": 1.35, "offset_m": 0.20},
}
#: Motor turns per half mirror turn with the default gear ratio: Δφ = −Δp / this.
HALF_TURN_MOTOR_TURNS = 40.0

WORLD = {
    "name": "calibration_room",
    "rooms": [{"name": "room", "footprint": [[0, 0], [10, 0], [10, 8], [0, 8]], "ceiling_m": 3.0}],
    "boxes": [
        {"name": "cabinet", "center": [0.4, 6.0], "size": [0.8, 1.2], "z_m": [0.0, 1.8]},
        {"name": "desk", "center": [8.5, 1.0], "size": [1.6, 0.8], "z_m": [0.0, 0.75]},
    ],
}


def facing(observer: list[float], range_m: float, alpha_deg: float, beta_deg: float) -> list[float]:
    """A pose from which a robot sees ``observer``'s beacon at about ``beta_deg`` while the
    observer sees it at about (``range_m``, ``alpha_deg``)."""
    x, y, yaw = observer
    heading = math.radians(yaw)
    sx, sy = x + 0.1 * math.cos(heading), y + 0.1 * math.sin(heading)
    bx = sx + range_m * math.cos(heading + math.radians(alpha_deg))
    by = sy + range_m * math.sin(heading + math.radians(alpha_deg))
    back = math.degrees(math.atan2(sy - by, sx - bx))
    return [round(bx, 2), round(by, 2), round((back - beta_deg) % 360, 1)]


def simulate_calibration_dataset(folder: Path) -> Path:
    """Write the world and mission into ``folder`` and simulate them; returns the dataset."""
    a = [3.0, 4.0, 0.0]
    b_station = [6.0, 4.0, 180.0]
    mission = {
        "world": "room.yaml",
        "seed": 3,
        "robots": [{"name": "a", "start": a}, {"name": "b", "start": facing(a, 2.5, 15, 45)}],
        "plan": [
            {"reference": "a", "mapper": "b",
             "scans": [facing(a, 3.0, -15, -40), facing(a, 3.5, 35, -15), facing(a, 2.0, -30, 15)]},
            {"reference": "b", "at": b_station, "mapper": "a",
             "scans": [facing(b_station, 2.8, 20, -45), facing(b_station, 3.2, -40, 20)]},
        ],
        "config": TRUE,
    }  # fmt: skip
    (folder / "room.yaml").write_text(yaml.safe_dump(WORLD), encoding="utf-8")
    (folder / "mission.yaml").write_text(yaml.safe_dump(mission), encoding="utf-8")
    out = folder / "dataset"
    run_simulation(folder / "mission.yaml", out)
    return out


def write_start_config(path: Path) -> Path:
    path.write_text(yaml.safe_dump(START), encoding="utf-8")
    return path
