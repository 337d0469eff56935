"""The dataset command group: check a dataset folder (and merge robots' recordings)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from estimation.app.cli.common import JsonOption, cli_errors, make_console

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
