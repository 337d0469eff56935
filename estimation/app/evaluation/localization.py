"""``coopmap evaluate-localization``: global-localization accuracy on simulated and real data.

Every trial searches the whole map — no prior, unless a row says so — and compares the refined
best pose with the truth. Success: within 0.1 m and 1° (the paper's claim); "strict": within
0.05 m and 0.5°. "Dominant": the search's own verdict (peak ratio ≥ ``search.dominance_ratio``),
and how often a dominant answer was right.

* **Simulated worlds** (``sim``): the global map is the band of 360° views (``demo``'s
  simulated LMS with range noise) taken every 2.5 m over the world and fused in the map frame;
  a local map is the band of one 360° view fused in the robot's own frame, at a random free pose
  (random yaw). office_loop is also searched from a prior (the truth displaced by 1 m σ per
  axis; a 4 m window that doubles until the peak is dominant) and with station maps. In
  ``cluttered_hall`` the clutter is then moved (``perturb_movables``: every movable object
  shifted up to 1 m and turned up to 45°, a fifth removed) before the local views are taken,
  and both the ceiling band and a floor band are searched.
* **geb079** (``../shared/data/octomap_fr079/geb079.bt``, building 079 of the University of
  Freiburg, OctoMap's sample map, 0.08 m): a ceiling band (z 2.30–2.55 m) and a floor band
  (z 0.3–1.5 m) of the whole building; local grids cut at random poses in the corridors — the
  building's voxels within 8 m, re-gridded (2×2 sub-columns per voxel) in a frame turned by a
  random yaw and shifted by a random sub-cell offset, with occupancy noise (σ 0.1), 2 % of the
  cells inverted and 20 % dropped.
* **CARMEN** (``../shared/data/carmen_corrected``: Intel Research Lab, D. Hähnel; Freiburg 079,
  C. Stachniss): the 2D map is fused from the even-numbered scans at their corrected poses; a
  local map is one odd-numbered scan (or a few consecutive ones, fused in the frame of the
  first) in the robot frame; the truth is its corrected pose (itself a SLAM estimate: 6.8 cm
  and 2.4° mean error against the benchmark's relations for Intel, per the data's README).

β is calibrated on the simulated ceiling searches: the value that maximises the mean log
probability the PDF gives to the lattice cell holding the true pose (a proper scoring rule).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from estimation.app.config import Config
from estimation.app.evaluation.localization_real import carmen_trials, geb079_trials
from estimation.app.evaluation.localization_sim import simulated_trials, view_scan, world_map
from estimation.app.evaluation.trials import (
    BETAS,
    Progress,
    Trial,
    by_room_kind,
    calibrate_beta,
    summarise,
)
from estimation.app.resources import DATA_DIR, resolve_builtin
from estimation.app.rig import T_robot_scanner, search_params
from estimation.search.exhaustive import search
from mapping.band import Band, extract_band
from mapping.fusion import fuse_scans
from mapping.grid import GridParams

__all__ = [
    "Trial",
    "by_room_kind",
    "calibrate_beta",
    "carmen_trials",
    "format_report",
    "geb079_trials",
    "run_evaluation",
    "simulated_trials",
    "summarise",
    "write_figures",
]


def write_figures(
    out_dir: Path, config: Config, data_dir: Path = DATA_DIR, seed: int = 0
) -> list[Path]:
    """``search_geb079.png`` (a local ceiling grid placed in geb079, when the data is there) and
    ``search_office_loop.png`` (a single view in office_loop's south corridor: the PDF also
    shows the weaker places along the corridors where the view nearly fits), drawn by
    ``localize.render_pdf``."""
    from estimation.app.localize import Localization, render_pdf
    from sensors.sim.scene import RaycastScene, build_mesh
    from sensors.sim.world import load_world

    written: list[Path] = []
    params = search_params(config.search)
    rng = np.random.default_rng(seed)
    path = data_dir / "octomap_fr079" / "geb079.bt"
    if path.exists():
        captured: dict[str, Band] = {}

        def keep(local: Band, global_: Band) -> None:
            captured["local"], captured["global"] = local, global_

        geb079_trials(path, config, rng, 1, bands=("ceiling",), capture=keep)
        result = search(captured["local"], captured["global"], params)
        found = Localization(
            result, (), result.is_dominant(params.dominance_ratio), captured["global"],
            captured["local"], result.seconds,
        )  # fmt: skip
        written.append(render_pdf(found, out_dir / "search_geb079.png"))
    world = load_world(resolve_builtin("worlds", "office_loop"))
    grid_params = GridParams(**config.grid.model_dump())
    scene = RaycastScene(build_mesh(world, cylinder_segments=config.simulation.cylinder_segments))
    global_ = world_map(world, config, rng, scene)["ceiling"]
    scan = view_scan(world, (7.0, 1.25, 90.0), config, rng, scene)
    local_grid = fuse_scans([scan], [T_robot_scanner(config)], grid_params)
    limits = config.bands.ceiling
    local = extract_band(
        local_grid, limits.min_m, limits.max_m, free_min_observed=config.bands.free_min_observed
    )
    result = search(local, global_, params)
    found = Localization(
        result, (), result.is_dominant(params.dominance_ratio), global_, local, result.seconds
    )
    written.append(render_pdf(found, out_dir / "search_office_loop.png"))
    return written


# -- summary -----------------------------------------------------------------------------------


def run_evaluation(
    config: Config,
    *,
    parts: tuple[str, ...] = ("sim", "geb079", "carmen"),
    trials: int = 40,
    data_dir: Path = DATA_DIR,
    seed: int = 0,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Run the parts asked for; real-data parts are skipped (and said so) without the data."""
    started = time.perf_counter()
    rows: list[dict[str, Any]] = []
    skipped: list[str] = []
    calibration: list[Trial] = []

    def add(trial_list: list[Trial]) -> None:
        by_key: dict[tuple[str, str], list[Trial]] = {}
        for trial in trial_list:
            by_key.setdefault((trial.case, trial.band), []).append(trial)
        for (case, band), group in by_key.items():
            rows.append({"case": case, "band": band, **summarise(group)})

    if "sim" in parts:
        for k, world in enumerate(("essex_lab", "office_loop", "cluttered_hall")):
            found = simulated_trials(
                world, config, np.random.default_rng(seed + k), trials, progress=progress
            )
            calibration += found
            add(found)
            if world == "office_loop":
                add(by_room_kind(found))
        rng = np.random.default_rng(seed + 5)
        add(
            simulated_trials(
                "office_loop", config, rng, trials, prior_sigma_m=1.0, progress=progress
            )
        )
        rng = np.random.default_rng(seed + 6)
        found = simulated_trials("office_loop", config, rng, trials, views=3, progress=progress)
        add(found)
        add(by_room_kind(found))
        perturb = (1.0, 1.0, 45.0, 0.2)
        add(
            simulated_trials(
                "cluttered_hall", config, np.random.default_rng(seed + 10), trials,
                bands=("ceiling", "floor"), perturb=perturb, progress=progress,
            )
        )  # fmt: skip
    if "geb079" in parts:
        path = data_dir / "octomap_fr079" / "geb079.bt"
        if path.exists():
            rng = np.random.default_rng(seed + 20)
            add(geb079_trials(path, config, rng, trials, progress=progress))
        else:
            skipped.append(f"geb079: {path} not found")
    if "carmen" in parts:
        for k, name in enumerate(("intel", "freiburg-079")):
            path = data_dir / "carmen_corrected" / f"{name}-corrected.log.gz"
            if not path.exists():
                skipped.append(f"{name}: {path} not found")
                continue
            for per_map in (1, 5):
                add(
                    carmen_trials(
                        path, config, np.random.default_rng(seed + 30 + k), trials,
                        scans_per_local_map=per_map, progress=progress,
                    )
                )  # fmt: skip
    report: dict[str, Any] = {"rows": rows, "skipped": skipped, "beta": config.search.beta}
    if calibration:
        best, curve = calibrate_beta(calibration)
        report["calibrated_beta"] = best
        report["beta_log_likelihood"] = dict(zip([float(b) for b in BETAS], curve, strict=True))
    report["seconds"] = time.perf_counter() - started
    return report


def format_report(report: dict[str, Any]) -> str:
    lines = [
        "| case | band | trials | success (<0.1 m, <1°) | strict (<0.05 m, <0.5°) | median error | "
        "95th percentile | dominant | correct when dominant | median search |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in report["rows"]:
        lines.append(
            f"| {row['case']} | {row['band']} | {row['trials']} | {row['success'] * 100:.0f} % | "
            f"{row['strict'] * 100:.0f} % | {row['median_m'] * 100:.1f} cm, "
            f"{row['median_deg']:.2f}° | {row['p95_m'] * 100:.1f} cm, {row['p95_deg']:.2f}° | "
            f"{row['dominant'] * 100:.0f} % | {row['dominant_correct'] * 100:.0f} % | "
            f"{row['median_seconds']:.2f} s |"
        )
    for note in report["skipped"]:
        lines.append(f"skipped: {note}")
    if "calibrated_beta" in report:
        lines.append(
            f"β maximising the mean log P(true cell) on the simulated ceiling searches: "
            f"{report['calibrated_beta']:.3g} (configured: {report['beta']:.3g})"
        )
    lines.append(f"({report['seconds']:.0f} s)")
    return "\n".join(lines)
