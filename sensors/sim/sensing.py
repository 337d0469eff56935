"""Simulated sensing: an LMS 200 behind a rotating mirror, in a world with other robots.

For each horizontal scan at time t the simulator finds the mirror's angle and the motor's (the
blocking arm), folds every beam of the variant up to the elevation φ(t) (the geometry of paper
eq. 4: the beam meets the mirror at x = d and is reflected), ray-casts it, adds the LMS range
noise, and marks returns from retro-reflective surfaces (beacons, reflective world objects) in
the flag bits. It also reproduces the mechanics the processing relies on: the arm covering the
right-most beams for part of each motor turn, the mirror's edge blocking the central beams when
it is edge-on, and the backward half of each mirror half-turn returning nothing. The scans then
become the byte stream a real sensor would send (``B0`` telegrams with real-time indices, paced
at the baud rate, host receive stamps).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sensors.errors import SensorError
from sensors.lms200.protocol.scan import SpecialCode, encode_scan, scan_interval_s
from sensors.lms200.protocol.telegram import TURN_S
from sensors.scan3d.mirror import MirrorGeometry
from sensors.sim.scene import RaycastScene
from sensors.sim.world import World, world_from_mapping

__all__ = [
    "RobotBody",
    "SimulatedScanner",
    "SimulatedScans",
    "robot_cylinders",
    "scan_stream",
    "telegram_times",
    "world_with_robots",
]


@dataclass(frozen=True)
class RobotBody:
    """What another scanner sees of a robot: its body and its retro-reflective beacon."""

    footprint_radius_m: float = 0.3
    body_height_m: float = 0.35
    scanner_x_m: float = 0.1
    beacon_offset_m: float = 0.25  # ahead of the scanner origin
    beacon_height_m: float = 1.6  # centre
    beacon_radius_m: float = 0.1
    beacon_length_m: float = 0.6

    def solids(self, name: str, x_m: float, y_m: float, yaw_rad: float) -> list[dict[str, object]]:
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        ahead = self.scanner_x_m + self.beacon_offset_m
        half = self.beacon_length_m / 2
        return [
            {"name": f"{name}.body", "center": [x_m, y_m], "radius_m": self.footprint_radius_m,
             "z_m": [0.0, self.body_height_m], "movable": True},
            {"name": f"{name}.beacon", "center": [x_m + ahead * c, y_m + ahead * s],
             "radius_m": self.beacon_radius_m,
             "z_m": [self.beacon_height_m - half, self.beacon_height_m + half],
             "movable": True, "retroreflective": True},
        ]  # fmt: skip


def world_with_robots(
    world: World, robots: dict[str, tuple[float, float, float]], body: RobotBody
) -> World:
    """The world plus a body and a beacon for each robot at (x_m, y_m, yaw_rad)."""
    extra = [
        solid for name, (x, y, yaw) in robots.items() for solid in body.solids(name, x, y, yaw)
    ]
    document = world.model_dump()
    document["cylinders"] = [*document["cylinders"], *extra]
    return world_from_mapping(document, source=f"{world.name} with robots")


def telegram_times(start_s: float, duration_s: float, baud_rate: int, count: int,
                   resolution_deg: float, indices: bool = True) -> np.ndarray:  # fmt: skip
    """When the measured-value telegrams of continuous output start (mirror-turn boundaries)."""
    interval = scan_interval_s(baud_rate, count, resolution_deg, indices)
    turns = round(interval / TURN_S)
    first = math.ceil(start_s / TURN_S - 1e-9)
    n = max(0, math.floor(duration_s / interval))
    return (first + turns * np.arange(n)) * TURN_S


@dataclass(frozen=True)
class SimulatedScans:
    """Horizontal scans over time: what the LMS measured, and the truth behind it."""

    times_s: np.ndarray  # (S,) measurement time of each scan
    bearing_rad: np.ndarray  # (N,) the variant's beams, scanner frame
    ranges_m: np.ndarray  # (S, N) NaN where the sensor reports no valid range
    codes: np.ndarray  # (S, N) SpecialCode
    flags: np.ndarray  # (S, N) reflector bits
    elevation_rad: np.ndarray  # (S,) true φ
    truth_scanner: np.ndarray  # (S, N, 3) noise-free end points, scanner frame (NaN if none)
    surface_id: np.ndarray  # (S, N) −1 where no world surface was hit


@dataclass(frozen=True)
class SimulatedScanner:
    """An LMS 200 with a rotating mirror, as the simulator runs it (true mechanics)."""

    geometry: MirrorGeometry
    motor_period_s: float  # true period (the processing estimates it)
    arm_phase_time_s: float = 0.0  # a time at which the arm starts to block
    edge_on_turn: int = 0  # the motor turn at which the mirror is edge-on (with the phase)
    arm_width_rad: float = math.pi / 2
    arm_range_m: float = 0.12
    arm_drop_fraction: float = 0.0  # motor turns whose arm pass does not register
    field_of_view_deg: int = 100
    resolution_deg: float = 1.0
    max_range_m: float = 8.0
    min_range_m: float = 0.05
    range_sigma_m: float = 0.005
    reflector_level: int = 7
    seed: int = 0

    @property
    def bearing_rad(self) -> np.ndarray:
        count = round(self.field_of_view_deg / self.resolution_deg) + 1
        return np.radians(-self.field_of_view_deg / 2 + self.resolution_deg * np.arange(count))

    @property
    def edge_on_time_s(self) -> float:
        phase = self.geometry.edge_on_motor_phase_rad or 0.0
        return self.arm_phase_time_s + self.motor_period_s * (
            self.edge_on_turn + phase / (2 * math.pi)
        )

    def mirror_angle(self, times_s: np.ndarray) -> np.ndarray:
        """ψ(t), wrapped to [−π/2, π/2): 0 edge-on; a two-sided mirror repeats every π."""
        half_turn_s = self.motor_period_s * self.geometry.half_turn_motor_turns
        psi = math.pi * (np.asarray(times_s) - self.edge_on_time_s) / half_turn_s
        return np.asarray((psi + math.pi / 2) % math.pi - math.pi / 2)

    def arm_blocks(self, times_s: np.ndarray) -> np.ndarray:
        motor = (np.asarray(times_s) - self.arm_phase_time_s) / self.motor_period_s
        turn = np.floor(motor).astype(np.int64)
        blocking = (motor - turn) * 2 * math.pi < self.arm_width_rad
        if self.arm_drop_fraction > 0:
            # Which passes are lost is fixed per motor turn (hashed with the seed).
            lost = np.random.default_rng([self.seed, 17]).random(
                int(turn.max()) + 2 if len(turn) else 1
            )
            blocking &= lost[np.clip(turn, 0, None)] >= self.arm_drop_fraction
        return blocking

    def scan(
        self,
        scene: RaycastScene,
        T_map_scanner: np.ndarray,
        times_s: np.ndarray,
        rng: np.random.Generator,
        cylinders: np.ndarray | None = None,
    ) -> SimulatedScans:
        """Simulate the horizontal scans measured at ``times_s``.

        ``T_map_scanner`` is one (4, 4) pose or one per scan (S, 4, 4) for a moving robot.
        ``cylinders`` (S, K, 6) adds vertical cylinders per scan — other robots' bodies and
        beacons, which move — as rows (x_m, y_m, radius_m, z_min_m, z_max_m, reflective).
        """
        geometry = self.geometry
        times_s = np.asarray(times_s, dtype=float)
        theta = self.bearing_rad
        n_scans, n_beams = len(times_s), len(theta)
        psi = self.mirror_angle(times_s)
        phi = np.angle(np.exp(1j * (2 * psi + geometry.elevation_offset_rad)))
        d = geometry.axis_offset_m
        cos_t, sin_t = np.cos(theta), np.sin(theta)
        to_mirror = d / cos_t  # the beam's path to the mirror

        at_mirror = np.column_stack([np.full(n_beams, d), d * sin_t / cos_t, np.zeros(n_beams)])
        origins = np.broadcast_to(at_mirror, (n_scans, n_beams, 3))
        directions = np.stack(
            [
                np.outer(np.cos(phi), cos_t),
                np.broadcast_to(sin_t, (n_scans, n_beams)),
                np.outer(np.sin(phi), cos_t),
            ],
            axis=-1,
        )
        T = np.asarray(T_map_scanner, dtype=float)
        if T.shape == (4, 4):
            T = np.broadcast_to(T, (n_scans, 4, 4))
        if T.shape != (n_scans, 4, 4):
            raise SensorError(f"need one scanner pose or one per scan, got {T.shape}")
        origins_map = np.einsum("sij,snj->sni", T[:, :3, :3], origins) + T[:, None, :3, 3]
        directions_map = np.einsum("sij,snj->sni", T[:, :3, :3], directions)
        hits = scene.cast(origins_map.reshape(-1, 3), directions_map.reshape(-1, 3), normals=False)
        path = hits.range_m.reshape(n_scans, n_beams)
        surface = hits.surface_id.reshape(n_scans, n_beams)
        reflective = scene.mesh.surface_flags("retroreflective")
        hit_reflective = reflective[np.where(surface >= 0, surface, 0)] & (surface >= 0)
        if cylinders is not None and np.asarray(cylinders).size:
            t_cyl, cyl_reflective = _cylinder_hits(
                origins_map, directions_map, np.asarray(cylinders)
            )
            nearer = t_cyl < path
            path = np.where(nearer, t_cyl, path)
            surface = np.where(nearer, -2, surface)  # −2: another robot
            hit_reflective = np.where(nearer, cyl_reflective, hit_reflective)
        true_range = to_mirror + path
        truth = origins + directions * np.where(np.isfinite(path), path, np.nan)[..., None]

        ranges = true_range + rng.normal(0.0, self.range_sigma_m, true_range.shape)
        codes = np.zeros((n_scans, n_beams), dtype=np.uint8)
        flags = np.zeros((n_scans, n_beams), dtype=np.uint8)
        hit = (
            np.isfinite(path) & (true_range <= self.max_range_m) & (true_range >= self.min_range_m)
        )
        flags[hit & hit_reflective] = self.reflector_level

        # The backward half of each half-turn folds the plane onto the scanner: nothing returns.
        backward = (phi < geometry.elevation_min_rad) | (phi > geometry.elevation_max_rad)
        hit[backward] = False
        edge_on = np.abs(psi) < geometry.edge_on_half_width_rad
        by_edge = edge_on[:, None] & (np.abs(theta) < geometry.edge_on_beams_rad)[None, :]
        ranges[by_edge] = to_mirror[np.nonzero(by_edge)[1]] + rng.normal(
            0, self.range_sigma_m, by_edge.sum()
        )
        hit[by_edge] = True
        flags[by_edge] = 0
        arm = self.arm_blocks(times_s)
        arm_cells = np.zeros((n_scans, n_beams), dtype=bool)
        arm_cells[arm, : geometry.arm_samples] = True
        ranges[arm_cells] = self.arm_range_m + rng.normal(0, self.range_sigma_m, arm_cells.sum())
        hit[arm_cells] = True
        flags[arm_cells] = 0

        codes[~hit] = SpecialCode.NO_RETURN
        ranges[~hit] = np.nan
        blocked = by_edge | arm_cells | ~hit
        truth[blocked] = np.nan
        surface = np.where(blocked, -1, surface)
        flags[~hit] = 0
        return SimulatedScans(times_s, theta, ranges, codes, flags, phi, truth, surface)


def _cylinder_hits(
    origins: np.ndarray, directions: np.ndarray, cylinders: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit of each ray (S, N) with its scan's vertical cylinders (S, K, 6), and whether
    that cylinder is reflective; inf where none is hit. Sides and end caps both count."""
    o = origins[:, :, None, :]
    d = directions[:, :, None, :]
    cx, cy, r, z0, z1, refl = (cylinders[:, None, :, k] for k in range(6))
    ox, oy = o[..., 0] - cx, o[..., 1] - cy
    dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
    a = dx * dx + dy * dy
    b = 2 * (ox * dx + oy * dy)
    c = ox * ox + oy * oy - r * r
    disc = b * b - 4 * a * c
    with np.errstate(divide="ignore", invalid="ignore"):
        root = np.sqrt(np.where(disc >= 0, disc, np.nan))
        t_side = np.where(a > 1e-12, (-b - root) / (2 * a), np.nan)
        z_side = o[..., 2] + t_side * dz
        side_ok = (t_side > 0) & (z_side >= z0) & (z_side <= z1)
        best = np.where(side_ok, t_side, np.inf)
        for z_cap in (z0, z1):
            t_cap = (z_cap - o[..., 2]) / dz
            px, py = ox + t_cap * dx, oy + t_cap * dy
            cap_ok = (t_cap > 0) & (px * px + py * py <= r * r)
            best = np.minimum(best, np.where(cap_ok, t_cap, np.inf))
    nearest = np.argmin(best, axis=2)[..., None]
    t = np.take_along_axis(best, nearest, axis=2)[..., 0]
    reflective = np.take_along_axis(np.broadcast_to(refl, best.shape), nearest, axis=2)[..., 0]
    return t, (reflective > 0) & np.isfinite(t)


def robot_cylinders(body: RobotBody, poses: np.ndarray) -> np.ndarray:
    """(S, 2·R, 6) cylinder rows of R robots at poses (S, R, 3) = (x_m, y_m, yaw_rad) per scan."""
    poses = np.asarray(poses, dtype=float)
    if poses.ndim == 2:
        poses = poses[None]
    x, y, yaw = poses[..., 0], poses[..., 1], poses[..., 2]
    ahead = body.scanner_x_m + body.beacon_offset_m
    half = body.beacon_length_m / 2
    ones, zeros = np.ones_like(x), np.zeros_like(x)
    bodies = np.stack(
        [x, y, body.footprint_radius_m * ones, zeros, body.body_height_m * ones, zeros], axis=-1
    )
    beacons = np.stack(
        [
            x + ahead * np.cos(yaw),
            y + ahead * np.sin(yaw),
            body.beacon_radius_m * ones,
            (body.beacon_height_m - half) * ones,
            (body.beacon_height_m + half) * ones,
            ones,
        ],
        axis=-1,
    )
    return np.concatenate([bodies, beacons], axis=1)


def scan_stream(
    scans: SimulatedScans,
    *,
    baud_rate: int = 38400,
    measuring_mode: int = 1,
    unit_mm: bool = True,
    clock_offset_s: float = 0.0,
    latency_s: float = 0.002,
    first_telegram: int = 0,
) -> list[tuple[float, bytes]]:
    """The bytes the sensor sends for these scans, as (host receive stamp, telegram) chunks.

    Telegrams carry the real-time indices (the mirror-turn counter mod 256, and the telegram
    counter mod 256, counting on from ``first_telegram`` across calls); each is stamped when its
    last byte would reach the host: the end of the measuring turn, plus the transmission at
    ``baud_rate``, plus a fixed latency.
    """
    chunks = []
    for k, t in enumerate(scans.times_s):
        turn = round(t / TURN_S)
        telegram = encode_scan(
            scans.ranges_m[k],
            flags=scans.flags[k],
            codes=scans.codes[k],
            measuring_mode=measuring_mode,
            unit_mm=unit_mm,
            scan_index=turn & 0xFF,
            telegram_index=(first_telegram + k) & 0xFF,
        )
        arrival = t + TURN_S + len(telegram) * 10.0 / baud_rate + latency_s + clock_offset_s
        chunks.append((arrival, telegram))
    return chunks
