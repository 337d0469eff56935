"""The ``coopmap`` command line.

Every command takes ``--config FILE`` (YAML overrides of ``configs/default.yaml``). Known errors
print one line on stderr and exit with code 2, never a traceback. Each command is a thin shell
around a typed function that tests call directly; heavy modules are imported inside commands so
that ``coopmap --help`` stays fast. The commands live beside this module, one module per group.
"""

from __future__ import annotations

import sys

import typer

from estimation.app.cli import (
    bench,
    calibrate,
    dataset,
    evaluate_missions,
    live,
    lms,
    localize,
    mission,
    record,
    ros,
    world,
)
from estimation.app.memory import limit_arenas

__all__ = ["app", "main"]

app = typer.Typer(
    name="coopmap",
    help="Cooperative 3D mapping by mobile robots that localize each other.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)
app.command()(mission.demo)
app.command()(mission.simulate)
app.command()(mission.batch)
app.command()(mission.isam)
app.command()(mission.evaluate)
app.command()(ros.export)
app.command("import")(ros.import_bag)
app.command()(localize.localize)
app.command("evaluate-localization")(localize.evaluate_localization)
app.command("evaluate-missions")(evaluate_missions.evaluate_missions)
app.add_typer(world.world_app, name="world")
app.add_typer(world.config_app, name="config")
app.add_typer(bench.bench_app, name="bench")
app.add_typer(lms.lms_app, name="lms")
app.add_typer(calibrate.calibrate_app, name="calibrate")
app.add_typer(dataset.dataset_app, name="dataset")
app.command()(record.record)
app.command()(record.replay)
app.add_typer(record.clock_app, name="clock")
app.command()(live.robot)
app.command()(live.base)
app.command("live")(live.live)


def main() -> None:
    """Console-script entry point. The search threads share two malloc arenas
    (:mod:`estimation.app.memory`)."""
    limit_arenas(2)
    try:
        app()
    except KeyboardInterrupt:
        typer.echo("coopmap: interrupted", err=True)
        sys.exit(130)


# ``python -m estimation.app.cli.main``: how coopmap live starts its processes.
if __name__ == "__main__":
    main()
