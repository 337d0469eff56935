"""Whether a robot can drive through a furnished room: a floor raster check (numpy only).

The room's floor is rasterised at ``RASTER_M``; walls (open where a door is), and every object
that starts below the robot's height, block it; the blocked cells grown by the robot's radius
leave the cells where its centre fits. Every door's approach must be among them and all joined
(4-connected), together with most of the free floor.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from sensors.sim.floorplan import PlanRoom
from sensors.sim.polygon import points_in_polygon
from sensors.sim.world import Box

__all__ = ["RASTER_M", "floor_reachable"]

#: Floor raster of the check (metres).
RASTER_M = 0.1


def _blocked(
    room: PlanRoom,
    boxes: list[dict[str, Any]],
    cylinders: list[dict[str, Any]],
    doors: list[tuple[np.ndarray, np.ndarray]],
    low_m: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The room's floor raster: (cell centres (H, W, 2), inside (H, W), blocked (H, W))."""
    lower = room.footprint.min(axis=0) - 1.0
    upper = room.footprint.max(axis=0) + 1.0
    shape = np.ceil((upper - lower) / RASTER_M).astype(int)
    xs = lower[0] + (np.arange(shape[0]) + 0.5) * RASTER_M
    ys = lower[1] + (np.arange(shape[1]) + 0.5) * RASTER_M
    gx, gy = np.meshgrid(xs, ys)
    centres = np.column_stack([gx.ravel(), gy.ravel()])
    inside = points_in_polygon(centres, room.footprint)
    blocked = ~inside
    for a, b in doors:  # the floor beyond a door is open, so the doorway keeps its width
        along = (b - a) / np.linalg.norm(b - a)
        rel = centres - a
        s, n = rel @ along, rel @ np.array([-along[1], along[0]])
        blocked &= ~((s > 0) & (s < float(np.linalg.norm(b - a))) & (n > -1.0) & (n < 0.05))
    for doc in boxes:
        if doc["z_m"][0] < low_m:
            blocked |= points_in_polygon(centres, Box.model_validate(doc).corners_xy())
    for doc in cylinders:
        if doc["z_m"][0] < low_m:
            blocked |= np.hypot(*(centres - doc["center"]).T) <= doc["radius_m"]
    return centres.reshape(*gx.shape, 2), inside.reshape(gx.shape), blocked.reshape(gx.shape)


def _dilate(mask: np.ndarray, radius_cells: int) -> np.ndarray:
    padded = np.pad(mask, radius_cells)
    out = np.zeros_like(mask)
    h, w = mask.shape
    for dy in range(-radius_cells, radius_cells + 1):
        for dx in range(-radius_cells, radius_cells + 1):
            if dx * dx + dy * dy <= radius_cells * radius_cells:
                out |= padded[
                    radius_cells + dy : radius_cells + dy + h,
                    radius_cells + dx : radius_cells + dx + w,
                ]
    return out


def _reach(free: np.ndarray, seed: tuple[int, int]) -> np.ndarray:
    """The cells of ``free`` 4-connected to ``seed`` (a breadth-first wave, vectorised)."""
    h, w = free.shape
    flat = free.ravel()
    seen = np.zeros(h * w, dtype=bool)
    start = seed[0] * w + seed[1]
    seen[start] = True
    front = np.array([start])
    while len(front):
        rows, cols = front // w, front % w
        nxt = np.concatenate(
            [
                front[rows > 0] - w,
                front[rows < h - 1] + w,
                front[cols > 0] - 1,
                front[cols < w - 1] + 1,
            ]
        )
        nxt = np.unique(nxt[flat[nxt] & ~seen[nxt]])
        seen[nxt] = True
        front = nxt
    return seen.reshape(h, w)


def floor_reachable(
    room: PlanRoom,
    boxes: list[dict[str, Any]],
    cylinders: list[dict[str, Any]],
    doors: list[tuple[np.ndarray, np.ndarray]],
    *,
    radius_m: float,
    low_m: float = 0.35,
) -> bool:
    """Whether a robot of ``radius_m`` can drive between every pair of the room's doors, and
    reaches most of its free floor."""
    centres, inside, blocked = _blocked(room, boxes, cylinders, doors, low_m)
    free = ~_dilate(blocked, math.ceil(radius_m / RASTER_M)) & inside
    if not free.any():
        return False
    targets = []
    for a, b in doors:
        along = (b - a) / np.linalg.norm(b - a)
        p = 0.5 * (a + b) + 0.6 * np.array([-along[1], along[0]])
        cell = (
            int((p[1] - centres[0, 0, 1]) / RASTER_M + 0.5),
            int((p[0] - centres[0, 0, 0]) / RASTER_M + 0.5),
        )
        if not free[cell]:
            return False
        targets.append(cell)
    first = np.argwhere(free)[0]
    seed = targets[0] if targets else (int(first[0]), int(first[1]))
    reached = _reach(free, seed)
    return bool(all(reached[c] for c in targets) and reached.sum() >= 0.7 * free.sum())
