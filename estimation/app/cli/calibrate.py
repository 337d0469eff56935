"""Calibration commands: the mirror and the beacon from a recorded dataset (docs/calibration.md)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from estimation.app.cli.common import (
    ConfigOption,
    JsonOption,
    cli_errors,
    make_console,
    option_overrides,
)

if TYPE_CHECKING:
    from estimation.app.calibration import BeaconResult, MirrorResult

calibrate_app = typer.Typer(
    help="Calibrate the rig (mirror, beacon) from a recorded dataset.", no_args_is_help=True
)

DatasetArgument = Annotated[
    Path, typer.Argument(help="A dataset folder recorded with the rig standing still in a room.")
]
OutOption = Annotated[
    Path | None,
    typer.Option(
        "--out", "-o", help="Fragment file to write (or update); without it, print the fragment."
    ),
]


def _finish(result: MirrorResult | BeaconResult, out: Path | None, json_out: bool,
            lines: list[str]) -> None:  # fmt: skip
    """Write or print the fragment; the summary goes to stdout with --out, else to stderr."""
    import json

    from estimation.app.calibration import fragment_text, write_fragment

    text = write_fragment(out, result) if out is not None else fragment_text(result)
    for warning in result.warnings:
        typer.echo(f"coopmap: warning: {warning}", err=True)
    if json_out:
        typer.echo(json.dumps({**result.to_json(), "fragment": text,
                               "out": None if out is None else str(out)}))  # fmt: skip
        return
    console = make_console(stderr=out is None)
    for line in lines:
        console.print(line)
    if out is None:
        typer.echo(text, nl=False)
    else:
        console.print(f"  wrote {out}")


@calibrate_app.command("mirror")
@cli_errors
def mirror(
    dataset: DatasetArgument,
    robot: Annotated[
        str | None, typer.Option(help="The robot whose scanner to calibrate (default: the first).")
    ] = None,
    out: OutOption = None,
    config: ConfigOption = None,
    json_out: JsonOption = False,
) -> None:
    """Mirror axis offset, elevation offset and edge-on motor phase from static sweeps of a room
    (floor at the scanner height, walls, ceiling)."""
    from estimation.app.calibration import calibrate_mirror, check_fragment_target

    if out is not None:
        check_fragment_target(out)
    overrides = option_overrides(config)
    with make_console(stderr=True).status(f"calibrating the mirror from {dataset}…"):
        result = calibrate_mirror(dataset, robot, overrides)
    f, s, e = result.fit, result.start, result.estimate
    lines = [
        f"coopmap calibrate mirror: robot {result.robot}, {f.sweeps} sweeps of {result.dwells} "
        f"dwells, {f.points:,} points ({f.floor_points:,} on the floor) on "
        f"{sum(f.planes.values())} planes; point-to-plane RMS {f.rms_before_m * 1e3:.1f} → "
        f"{f.rms_after_m * 1e3:.1f} mm",
        f"  axis_offset_m {s['axis_offset_m']:g} → {e['axis_offset_m']:.5f} "
        f"(σ {f.sigma_axis_offset_m * 1e3:.3f} mm)",
        f"  elevation_offset_deg {s['elevation_offset_deg']:g} → {e['elevation_offset_deg']:.3f}",
    ]
    if "edge_on_motor_phase_deg" in e and result.phase is not None:
        import math

        spread = math.degrees(result.phase.spread_rad)
        lines.append(
            f"  edge_on_motor_phase_deg {s['edge_on_motor_phase_deg']:g} → "
            f"{e['edge_on_motor_phase_deg']:.3f} (spread {spread:.1f}° over "
            f"{result.phase.dwells} dwells)"
        )
    _finish(result, out, json_out, lines)


@calibrate_app.command("beacon")
@cli_errors
def beacon(
    dataset: DatasetArgument,
    out: OutOption = None,
    height_search_m: Annotated[
        float,
        typer.Option(help="Search the beacon this far (m) beyond its band around its height."),
    ] = 1.0,
    config: ConfigOption = None,
    json_out: JsonOption = False,
) -> None:
    """Beacon height and offset from the mutual observations of two robots facing each other."""
    from estimation.app.calibration import calibrate_beacon, check_fragment_target

    if out is not None:
        check_fragment_target(out)
    overrides = option_overrides(config)
    with make_console(stderr=True).status(f"calibrating the beacon from {dataset}…"):
        result = calibrate_beacon(dataset, overrides, height_search_m=height_search_m)
    o, s, e = result.offset, result.start, result.estimate
    lines = [
        f"coopmap calibrate beacon: {result.observations} mutual observations "
        f"({result.at_configured_height} found at the configured height), {o.used} used, "
        f"{o.skipped_degenerate} degenerate skipped, {o.downweighted} down-weighted; "
        f"|s1 − s2| RMS {o.separation_rms_before_m * 1e3:.1f} → "
        f"{o.separation_rms_after_m * 1e3:.1f} mm",
        f"  height_m {s['height_m']:g} → {e['height_m']:.4f} (from {result.heights} detections, "
        f"spread {result.height_spread_m * 1e3:.0f} mm)",
        f"  offset_m {s['offset_m']:g} → {e['offset_m']:.4f} (σ {o.sigma_m * 1e3:.1f} mm)",
    ]
    _finish(result, out, json_out, lines)
