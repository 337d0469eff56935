"""The world and config command groups."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from estimation.app.cli.common import (
    ConfigOption,
    cli_errors,
    file_size,
    make_console,
    option_config,
)
from estimation.app.config import ConfigError, config_to_yaml

world_app = typer.Typer(help="Simulated worlds.", no_args_is_help=True)
config_app = typer.Typer(help="The configuration.", no_args_is_help=True)


@world_app.command("show")
@cli_errors
def world_show(
    world: Annotated[str, typer.Argument(help="A built-in world name or a world YAML file.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="PNG file to write.")],
    config: ConfigOption = None,
) -> None:
    """Draw a world: top view with a height colour scale, and its sub-ceiling band."""
    from estimation.app.figures import render_world
    from estimation.app.resources import resolve_builtin
    from sensors.sim.world import load_world

    cfg = option_config(config)
    if out.suffix.lower() != ".png":
        raise ConfigError(f"{out}: --out must name a .png file")
    model = load_world(resolve_builtin("worlds", world))
    band = cfg.bands.ceiling
    path = render_world(
        model,
        out,
        band_m=(band.min_m, band.max_m),
        band_resolution_m=cfg.grid.resolution_m,
        cylinder_segments=cfg.simulation.cylinder_segments,
    )
    movable = len(model.movable_names())
    make_console().print(
        f"wrote {path} ({file_size(path)}): {model.name}, {len(model.rooms)} rooms, "
        f"{len(model.boxes)} boxes, {len(model.cylinders)} cylinders ({movable} movable)"
    )


@world_app.command("generate")
@cli_errors
def world_generate(
    seed: Annotated[int, typer.Option("--seed", help="Seed of the building (>= 0).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="World YAML file to write.")],
    rooms: Annotated[
        int | None, typer.Option("--rooms", help="Number of rooms, 3-15 (default: from the seed).")
    ] = None,
    config: ConfigOption = None,
) -> None:
    """Generate a building (rooms, doors, ceiling structure, furniture) as a world file."""
    from sensors.sim.furnish import FurnishParams
    from sensors.sim.generate import write_generated_world

    cfg = option_config(config)
    params = FurnishParams(
        band_m=(cfg.bands.ceiling.min_m, cfg.bands.ceiling.max_m),
        robot_radius_m=cfg.robot.footprint_radius_m,
        beacon_height_m=cfg.beacon.height_m,
        beacon_length_m=cfg.beacon.length_m,
    )
    building = write_generated_world(out, seed, rooms, params)
    model = building.world
    kinds = ", ".join(f"{n} {kind}" for kind, n in sorted(building.kinds().items()))
    ceilings = [room.ceiling_m for room in building.rooms]
    make_console().print(
        f"wrote {out} ({file_size(out)}): {model.name}, {len(model.rooms)} rooms ({kinds}), "
        f"ceilings {min(ceilings):g}-{max(ceilings):g} m, "
        f"{len(model.boxes) + len(model.cylinders)} objects ({len(model.movable_names())} movable)"
    )


@world_app.command("list")
@cli_errors
def world_list(config: ConfigOption = None) -> None:
    """List the built-in worlds."""
    from estimation.app.resources import builtin_names, resolve_builtin
    from sensors.sim.world import load_world

    option_config(config)  # validated like every command's, though listing needs none of it
    console = make_console()
    for name in builtin_names("worlds"):
        model = load_world(resolve_builtin("worlds", name))
        lower, upper = model.bounds_xy()
        size = upper - lower
        console.print(
            f"{name:16s} {size[0]:5.1f} m × {size[1]:4.1f} m, {len(model.rooms):2d} rooms, "
            f"{len(model.boxes) + len(model.cylinders):3d} objects "
            f"({len(model.movable_names())} movable)"
        )


@config_app.command("show")
@cli_errors
def config_show(config: ConfigOption = None) -> None:
    """Print the effective configuration (defaults merged with --config) as YAML."""
    typer.echo(config_to_yaml(option_config(config)), nl=False)
