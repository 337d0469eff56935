"""The dataset command group: check a dataset folder (and merge robots' recordings)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from estimation.app.cli.common import JsonOption, cli_errors, make_console, option_overrides

dataset_app = typer.Typer(help="Dataset folders: check, merge.", no_args_is_help=True)


@dataset_app.command("check")
@cli_errors
def dataset_check(
    dataset: Annotated[Path, typer.Argument(help="A dataset folder (docs/dataset.md).")],
    decode: Annotated[
        bool, typer.Option(help="Also decode the captures and cut every dwell's sweep.")
    ] = True,
    json_out: JsonOption = False,
) -> None:
    """Print every problem of a dataset (errors, then warnings); exit 2 when any is an error."""
    from estimation.app.dataset_check import check_dataset

    console = make_console(stderr=True)
    with console.status("checking") as status:
        check = check_dataset(dataset, decode=decode, progress=lambda s: status.update(s))
    if json_out:
        typer.echo(json.dumps(check.as_dict()))
    else:
        for problem in sorted(check.problems, key=lambda p: p.level != "error"):
            typer.echo(problem.line())
        typer.echo(
            f"{dataset}: {len(check.robots)} robots, {check.events} events, {check.dwells} "
            f"dwells" + (f", {check.sweeps} sweeps" if decode else "") + f": {check.errors} "
            f"errors, {check.warnings} warnings"
        )
    if check.errors:
        raise typer.Exit(code=2)


@dataset_app.command("merge")
@cli_errors
def dataset_merge(
    recordings: Annotated[list[Path], typer.Argument(help="Recording folders, one per robot.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Dataset folder to write.")],
    mission: Annotated[
        Path | None, typer.Option(help="mission.yaml: robots (gauge first), start poses, config.")
    ] = None,
    robot: Annotated[
        list[str] | None,
        typer.Option(help="Instead of --mission: NAME=X_M,Y_M,YAW_DEG (repeat; gauge first)."),
    ] = None,
    mission_start: Annotated[
        float | None, typer.Option(help="Reference-clock time of mission time 0.")
    ] = None,
    tolerance: Annotated[
        float, typer.Option(help="Seconds within which two recordings' events are one.")
    ] = 0.5,
    config: Annotated[
        Path | None, typer.Option("--config", "-c", help="YAML merged over the mission's config.")
    ] = None,
) -> None:
    """Merge robots' recordings (coopmap record) into one dataset on the mission clock."""
    from estimation.app.merge import merge_recordings

    overrides = option_overrides(config)
    result = merge_recordings(
        recordings, out, mission=mission, robots=robot, overrides=overrides,
        mission_start_ref_s=mission_start, tolerance_s=tolerance,
    )  # fmt: skip
    for warning in result.warnings:
        typer.echo(f"coopmap: warning: {warning}", err=True)
    clocks = ", ".join(
        f"{name} rate {m.rate:.6f} ±{m.uncertainty_s * 1e3:.2f} ms"
        for name, m in result.clocks.items()
    )
    typer.echo(
        f"wrote {out}: robots {', '.join(result.robots)}, {result.events} events "
        f"({result.dwells} dwells), mission start at reference {result.mission_start_ref_s:.6f} s; "
        f"clocks: {clocks}"
    )
