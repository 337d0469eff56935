"""2D bands as ROS ``map_server`` maps: a PGM image and a YAML file that describes it.

The YAML holds ``image`` (the PGM, relative to the YAML's folder), ``resolution`` (m/cell),
``origin: [x, y, yaw]`` (the map-frame pose of the image's lower-left pixel), ``negate``,
``occupied_thresh``, ``free_thresh`` and ``mode``. Pixels are 8-bit grey: with ``negate: 0`` a
pixel p holds occupancy (255 − p) / 255 — black occupied, white free — and 205 marks an
unknown cell (``map_saver``'s convention). The image's first row is the top of the map (largest
y), so rows are flipped against ``Band`` (row 0 = smallest y).

The pixels keep the band's graded occupancy, quantised to 1/255 (coopmap's reader reads the
grades back); a known cell that would land on 205 is written as 206 (a change of 1/255) so that
it stays known. The YAML says ``mode: trinary`` with thresholds on either side of the unknown
pixel, so that ``map_server`` (ROS 1 and Nav2) loads 205 as unknown (−1) and every known pixel
as free (0) or occupied (100): with ``negate: 0`` it reads occ = (255 − p) / 255 and gives
100 when occ > ``occupied_thresh``, 0 when occ < ``free_thresh``, −1 otherwise. Pixel 206 is
occ = 49/255 ≈ 0.192, 205 is 50/255 ≈ 0.196 and 204 is 51/255 = 0.2, so ``free_thresh`` 0.194
and ``occupied_thresh`` 0.198 leave only 205 between them: a cell whose band layers are at
least a fifth occupied loads as occupied. (``mode: scale`` would load 205 as a known,
nearly free cell: map_server's scale mode marks unknown only through an alpha channel.)
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from mapping.band import Band
from mapping.errors import MapError
from sensors.atomic import atomic_path, write_text_atomic
from sensors.yamlio import YAML_LIMIT_BYTES, parse_yaml, read_file_bytes, read_text_file

__all__ = ["FREE_THRESH", "OCCUPIED_THRESH", "UNKNOWN_PIXEL", "read_band_pgm", "write_band_pgm"]

UNKNOWN_PIXEL = 205
#: map_server's thresholds (trinary mode) that load pixel 205 alone as unknown: see above.
FREE_THRESH = 0.194
OCCUPIED_THRESH = 0.198
_DIGITS = re.compile(rb"\d+")
_SPACE = (b" ", b"\t", b"\r", b"\n")
#: An 8-bit map_server image of 32,000 × 32,000 cells; anything larger is not a map.
PGM_LIMIT_BYTES = 2**30


def write_band_pgm(yaml_path: Path | str, band: Band) -> tuple[Path, Path]:
    """Write ``band`` as ``<stem>.pgm`` beside ``yaml_path`` and the YAML; return both paths."""
    yaml_path = Path(yaml_path)
    if yaml_path.suffix.lower() not in (".yaml", ".yml"):
        raise MapError(f"{yaml_path}: the map description must be a .yaml file")
    occupancy = np.clip(band.occupancy, 0.0, 1.0)
    if not np.all(np.isfinite(occupancy)):
        raise MapError("band occupancy holds non-finite values")
    pixels = np.rint((1.0 - occupancy) * 255.0).astype(np.uint8)
    pixels[band.known & (pixels == UNKNOWN_PIXEL)] = UNKNOWN_PIXEL + 1
    pixels[~band.known] = UNKNOWN_PIXEL
    rows, cols = band.shape
    pgm_path = yaml_path.with_suffix(".pgm")
    header = f"P5\n# written by coopmap\n{cols} {rows}\n255\n".encode("ascii")
    with atomic_path(pgm_path) as tmp:
        tmp.write_bytes(header + np.ascontiguousarray(pixels[::-1]).tobytes())
    description = {
        "image": pgm_path.name,
        "resolution": float(band.resolution_m),
        "origin": [float(band.lower_xy[0]), float(band.lower_xy[1]), 0.0],
        "negate": 0,
        "occupied_thresh": OCCUPIED_THRESH,
        "free_thresh": FREE_THRESH,
        "mode": "trinary",
    }
    write_text_atomic(yaml_path, yaml.safe_dump(description, sort_keys=False))
    return pgm_path, yaml_path


def _read_pgm(path: Path) -> np.ndarray:
    data = read_file_bytes(path, MapError, PGM_LIMIT_BYTES)
    if not data.startswith(b"P5") or data[2:3] not in (*_SPACE, b"#"):
        raise MapError(f"{path}: not a binary PGM (P5) image")
    pos = 2
    numbers: list[int] = []
    while len(numbers) < 3:
        while data[pos : pos + 1] in _SPACE or data[pos : pos + 1] == b"#":
            if data[pos : pos + 1] == b"#":
                end = data.find(b"\n", pos)
                pos = len(data) if end < 0 else end
            pos += 1
        token = _DIGITS.match(data, pos)
        if token is None:
            raise MapError(f"{path}: malformed PGM header")
        if len(token.group()) > 9:
            raise MapError(f"{path}: PGM header number of {len(token.group())} digits")
        numbers.append(int(token.group()))
        pos = token.end()
    if data[pos : pos + 1] not in _SPACE:
        raise MapError(f"{path}: malformed PGM header")
    pos += 1
    width, height, maxval = numbers
    if maxval != 255:
        raise MapError(f"{path}: only 8-bit PGM (maxval 255) is supported, got maxval {maxval}")
    if width <= 0 or height <= 0:
        raise MapError(f"{path}: empty image ({width} × {height})")
    if len(data) - pos < width * height:
        raise MapError(
            f"{path}: truncated: {width} × {height} pixels need {width * height} bytes, "
            f"found {len(data) - pos}"
        )
    pixels = np.frombuffer(data, dtype=np.uint8, count=width * height, offset=pos)
    return pixels.reshape(height, width)


def _number(path: Path, doc: dict[str, Any], key: str, default: float | None = None) -> float:
    value = doc.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise MapError(f"{path}: {key} must be a number, got {value!r}")
    return float(value)


def read_band_pgm(yaml_path: Path | str) -> Band:
    """Read a ``map_server`` map (YAML + PGM) as a ``Band``; MapError on anything malformed."""
    yaml_path = Path(yaml_path)
    doc = parse_yaml(
        read_text_file(yaml_path, MapError, YAML_LIMIT_BYTES), str(yaml_path), MapError
    )
    if not isinstance(doc, dict):
        raise MapError(f"{yaml_path}: a map description must be a YAML mapping")
    for key in ("image", "resolution", "origin"):
        if key not in doc:
            raise MapError(f"{yaml_path}: missing key {key!r}")
    if not isinstance(doc["image"], str) or not doc["image"]:
        raise MapError(f"{yaml_path}: image must be a file name, got {doc['image']!r}")
    resolution = _number(yaml_path, doc, "resolution")
    if resolution <= 0:
        raise MapError(f"{yaml_path}: resolution must be positive, got {resolution}")
    origin = doc["origin"]
    if (
        not isinstance(origin, list)
        or len(origin) != 3
        or not all(
            isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
            for v in origin
        )
    ):
        raise MapError(f"{yaml_path}: origin must be [x, y, yaw], got {origin!r}")
    if abs(origin[2]) > 1e-12:
        raise MapError(f"{yaml_path}: a rotated map (origin yaw {origin[2]}) is not supported")
    negate = doc.get("negate", 0)
    if isinstance(negate, bool) or negate not in (0, 1):  # YAML true is not map_server's 1
        raise MapError(f"{yaml_path}: negate must be 0 or 1, got {negate!r}")
    pixels = _read_pgm(yaml_path.parent / doc["image"])[::-1]
    # In place: one float64 array of the image's size and no temporaries of that size.
    known = pixels != UNKNOWN_PIXEL
    occupancy = pixels.astype(np.float64)
    if not negate:
        np.subtract(255.0, occupancy, out=occupancy)
    occupancy /= 255.0
    occupancy[~known] = 0.0
    return Band(
        occupancy=occupancy,
        known=known,
        lower_xy=np.array([float(origin[0]), float(origin[1])]),
        resolution_m=resolution,
    )
