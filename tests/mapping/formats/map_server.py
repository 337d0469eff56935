"""A ROS ``map_server`` loader written from its documentation, to check coopmap's maps as ROS
reads them (ROS 1 map_server's image_loader and Nav2's map_io agree on these rules).

YAML keys: ``image`` (relative to the YAML), ``resolution``, ``origin``, ``negate``,
``occupied_thresh``, ``free_thresh``, ``mode`` (``trinary`` by default, ``scale`` or ``raw``).
A pixel p of an 8-bit grey image reads as occ = p / 255 with ``negate: 1``, else
(255 − p) / 255. Trinary: 100 if occ > occupied_thresh, 0 if occ < free_thresh, else −1. Scale:
the same ends, and in between rint(100 · (occ − free) / (occupied − free)) — unknown only
through an alpha channel, which a PGM has none of. Raw: the pixel value itself. Cells are
returned as ``nav_msgs/OccupancyGrid`` orders them: row 0 is the image's last (lowest y).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml


def read_pgm_pixels(path: Path) -> np.ndarray:
    """(rows, cols) uint8 of a binary PGM without comments after the magic line."""
    data = path.read_bytes()
    assert data[:2] == b"P5"
    tokens: list[bytes] = []
    pos = 2
    while len(tokens) < 3:
        while data[pos : pos + 1].isspace():
            pos += 1
        if data[pos : pos + 1] == b"#":
            pos = data.index(b"\n", pos) + 1
            continue
        end = pos
        while not data[end : end + 1].isspace():
            end += 1
        tokens.append(data[pos:end])
        pos = end
    width, height, maxval = (int(t) for t in tokens)
    assert maxval == 255
    return np.frombuffer(data, np.uint8, width * height, pos + 1).reshape(height, width)


def load_map_server(yaml_path: Path) -> tuple[np.ndarray, dict[str, object]]:
    """(cells (rows, cols) int8 as map_server publishes them, the YAML document)."""
    doc = yaml.safe_load(yaml_path.read_text())
    pixels = read_pgm_pixels(yaml_path.parent / doc["image"]).astype(np.float64)
    mode = doc.get("mode", "trinary")
    if mode == "raw":
        return pixels[::-1].astype(np.int16).astype(np.int8), doc
    occ = pixels / 255.0 if doc.get("negate", 0) else (255.0 - pixels) / 255.0
    high, low = float(doc["occupied_thresh"]), float(doc["free_thresh"])
    if mode == "trinary":
        middle = np.full(occ.shape, -1.0)
    else:
        middle = np.rint((occ - low) / (high - low) * 100.0)
    cells = np.where(occ > high, 100.0, np.where(occ < low, 0.0, middle))
    return cells[::-1].astype(np.int8), doc
