"""ROS 2 interchange commands: ``coopmap export`` and ``coopmap import`` (docs/ros.md)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from estimation.app.cli.common import (
    cli_errors,
    file_size,
    make_console,
    option_config,
    option_overrides,
)

if TYPE_CHECKING:
    from estimation.app.ros.export import ExportSummary
    from estimation.app.ros.importer import ImportSummary

__all__ = ["McapOption", "export", "import_bag", "print_export", "print_import"]

McapOption = Annotated[
    Path | None,
    typer.Option(
        "--mcap",
        help="Also write the result as a ROS 2 bag (one .mcap file; docs/ros.md). An existing "
        "file is replaced only if coopmap wrote it.",
    ),
]


def print_export(summary: ExportSummary) -> None:
    """The topics and messages an export wrote, the file and its size; then any notes."""
    console = make_console()
    messages = sum(summary.topics.values())
    console.print(
        f"coopmap export: {len(summary.topics)} topics, {messages:,} messages: "
        + ", ".join(summary.topics)
    )
    console.print(f"  wrote {summary.path} ({file_size(summary.path)})")
    for note in summary.notes:
        console.print(f"  note: {note}")


@cli_errors
def export(
    result: Annotated[
        Path,
        typer.Argument(
            help="A result folder (coopmap batch or isam), or a dataset folder (mission.yaml, "
            "events.jsonl, robots/): its captures, odometry and events, for coopmap import."
        ),
    ],
    mcap: Annotated[Path, typer.Option("--mcap", help="The ROS 2 bag to write (.mcap).")],
    dataset: Annotated[
        Path | None,
        typer.Option(
            "--dataset",
            help="The dataset of the result, for the odometry frames (default: the one "
            "report.json names, else the result's parent folder).",
        ),
    ] = None,
) -> None:
    """Export a result as a ROS 2 bag (map, voxels, OctoMap, paths, poses, tf, markers), or a
    dataset (scans, raw capture records, odometry, tf, events, mission)."""
    from estimation.app.ros.dataset_bag import export_dataset, is_dataset
    from estimation.app.ros.export import export_result

    if is_dataset(result) and not (result / "report.json").exists():
        if dataset is not None:
            from estimation.app.config import ConfigError

            raise ConfigError(f"--dataset: {result} is a dataset; --dataset is for a result")
        print_export(export_dataset(result, mcap))
        return
    print_export(export_result(result, mcap, dataset_dir=dataset))


def _pairs(values: list[str] | None, flag: str) -> dict[str, str]:
    """NAME=VALUE options as a mapping (first NAME wins its place in the order)."""
    from estimation.app.config import ConfigError

    out: dict[str, str] = {}
    for text in values or []:
        name, sep, value = text.partition("=")
        if not sep or not name.strip() or not value.strip():
            raise ConfigError(f"{flag} {text!r}: expected NAME=VALUE")
        out[name.strip()] = value.strip()
    return out


def _starts(values: list[str] | None) -> dict[str, tuple[float, float, float]]:
    import math

    from estimation.app.config import ConfigError

    out = {}
    for name, pose in _pairs(values, "--start").items():
        try:
            x, y, yaw = (float(v) for v in pose.split(","))
        except ValueError:
            raise ConfigError(
                f"--start {name}={pose}: expected NAME=X_M,Y_M,YAW_DEG (e.g. a=2,3.5,20)"
            ) from None
        if not all(math.isfinite(v) for v in (x, y, yaw)):
            raise ConfigError(f"--start {name}={pose}: not finite")
        out[name] = (x, y, yaw)
    return out


def _size(n: int) -> str:
    return f"{n / 1e6:.1f} MB" if n >= 1e6 else f"{n / 1e3:.0f} kB"


def print_import(summary: ImportSummary) -> None:
    """Robots, scans, odometry, dwells, events, what was skipped, notes, bytes written."""
    console = make_console()
    how = "coopmap's records, lossless" if summary.lossless else "LaserScans re-encoded"
    console.print(f"coopmap import: {summary.bag} → {summary.out_dir} ({how})")
    for r in summary.robots:
        kind = "capture records" if summary.lossless else "scans"
        console.print(
            f"  robot {r.name}: {r.scan_topic} {r.scans:,} {kind} ({_size(r.capture_bytes)}), "
            f"{r.odometry_topic} {r.odometry_samples:,} odometry samples"
        )
    spans = ", ".join(f"{a:.1f}–{b:.1f} s" for a, b in summary.dwells[:6])
    spans += ", …" if len(summary.dwells) > 6 else ""
    if summary.dwell_rule is not None:
        rule = summary.dwell_rule
        console.print(
            f"  {len(summary.dwells)} dwells found (still below {rule.still_speed_m_s:g} m/s and "
            f"{rule.still_turn_rate_deg_s:g}°/s for {summary.min_dwell_s:g} s or more): {spans}"
        )
    else:
        console.print(f"  {len(summary.dwells)} dwells (the bag's events): {spans}")
    console.print(f"  {summary.events:,} events")
    skipped = ", ".join(f"{n:,} {why}" for why, n in summary.skipped.items()) or "none"
    line = f"  skipped messages: {skipped}"
    if summary.beams:
        line += "; beams without a range: " + ", ".join(
            f"{n:,} {why}" for why, n in summary.beams.items()
        )
    console.print(line)
    for note in summary.notes:
        console.print(f"  note: {note}")
    console.print(f"  wrote {summary.out_dir} ({_size(summary.bytes_written)})")


@cli_errors
def import_bag(
    bag: Annotated[
        Path,
        typer.Argument(help="A ROS 2 bag (.mcap, .db3 or its folder) or a ROS 1 bag (.bag)."),
    ],
    out: Annotated[Path, typer.Option("--out", "-o", help="The dataset folder to write.")],
    topics: Annotated[
        list[str] | None,
        typer.Option("--topics", help="Use only these topics (repeat, or comma-separated)."),
    ] = None,
    config: Annotated[
        Path | None,
        typer.Option(
            "--config", "-c", help="YAML config of the rig, written into mission.yaml (foreign)."
        ),
    ] = None,
    robot: Annotated[
        list[str] | None,
        typer.Option(
            help="NAME=TOPIC: robot NAME's LaserScan topic or namespace (repeat; gauge first)."
        ),
    ] = None,
    start: Annotated[
        list[str] | None,
        typer.Option(help="NAME=X_M,Y_M,YAW_DEG: a start pose (default: 0,0,0; repeat)."),
    ] = None,
    reference: Annotated[
        str | None, typer.Option(help="The reference robot of every dwell (foreign bags).")
    ] = None,
    mapper: Annotated[
        str | None, typer.Option(help="The mapper robot of every dwell (foreign bags).")
    ] = None,
    still_speed: Annotated[
        float, typer.Option(help="Dwells: standing still below this speed (m/s).")
    ] = 0.01,
    still_turn_rate: Annotated[
        float, typer.Option(help="Dwells: standing still below this turn rate (deg/s).")
    ] = 0.5,
    min_dwell: Annotated[
        float | None,
        typer.Option(help="Dwells: at least this long (s; default: half the mirror period)."),
    ] = None,
    intensity_threshold: Annotated[
        float, typer.Option(help="A LaserScan intensity above this is a reflector return.")
    ] = 0.5,
) -> None:
    """Import a ROS bag as a dataset: coopmap's own bags losslessly, others from their
    LaserScans and odometry (dwells found where the robots stood still)."""
    from estimation.app.ros.dwells import DwellRule
    from estimation.app.ros.importer import ImportOptions
    from estimation.app.ros.importer import import_bag as run_import

    if config is not None:
        option_config(config)  # a bad configuration is refused before the bag is read
    options = ImportOptions(
        topics=tuple(t.strip() for text in topics or [] for t in text.split(",") if t.strip()),
        overrides=option_overrides(config),
        robots=_pairs(robot, "--robot"),
        starts=_starts(start),
        reference=reference,
        mapper=mapper,
        dwell=DwellRule(still_speed, still_turn_rate, min_dwell),
        intensity_threshold=intensity_threshold,
    )
    print_import(run_import(bag, out, options))
