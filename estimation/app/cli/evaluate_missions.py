"""``coopmap evaluate-missions``: a mission in each of N generated buildings, scored."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.measure import Measurement
from rich.table import Table

from estimation.app.cli.common import (
    ConfigOption,
    cli_errors,
    make_console,
    option_config,
    option_overrides,
)

__all__ = ["evaluate_missions", "format_ate", "print_evaluation"]


@cli_errors
def evaluate_missions(
    worlds: Annotated[int, typer.Option("--worlds", help="Number of buildings (>= 1).")],
    seed: Annotated[int, typer.Option("--seed", help="Seed of the first building (>= 0).")],
    robots: Annotated[int, typer.Option("--robots", help="Robots per mission: 2 or 3.")] = 2,
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")] = Path(
        "runs/evaluate-missions"
    ),
    rooms: Annotated[
        int | None, typer.Option("--rooms", help="Rooms per building, 3-15 (default: per seed).")
    ] = None,
    stations: Annotated[
        int | None,
        typer.Option("--stations", help="Station budget of each mission, 1-500 (default: 250)."),
    ] = None,
    config: ConfigOption = None,
) -> None:
    """Generate buildings (seeds SEED … SEED+N−1), fly a mission in each (simulate, batch,
    evaluate), print one row per building and the distribution; writes evaluation.json."""
    from estimation.app.evaluation.missions import (
        DEFAULT_STATIONS,
        check_arguments,
        evaluate_missions,
    )

    stations = DEFAULT_STATIONS if stations is None else stations

    check_arguments(worlds, seed, robots, rooms, stations)
    option_config(config)  # a bad --config is one line before any work
    overrides = option_overrides(config)
    err = make_console(stderr=True)
    with err.status(f"evaluating missions in {worlds} buildings…", spinner="dots") as status:
        document = evaluate_missions(
            worlds, seed, out, robots=robots, rooms=rooms, stations=stations, overrides=overrides,
            progress=status.update,
        )  # fmt: skip
    print_evaluation(document)
    make_console().print(f"wrote {out / 'evaluation.json'}")


def format_ate(robot: dict[str, Any]) -> str:
    """A robot's ATE as a cell: ``0.4 cm 0.12°``, or ``lost`` without a pose."""
    if robot.get("ate_m") is None:
        return "lost"
    return f"{robot['ate_m'] * 100:.1f} cm {robot['ate_deg']:.2f}°"


def _cell(value: float | None, pattern: str) -> str:
    return "-" if value is None else format(value, pattern)


def print_evaluation(document: dict[str, Any]) -> None:
    """The rows as a table, then the distribution over the buildings."""
    from estimation.app.evaluation.missions import ROBOT_NAMES

    names = ROBOT_NAMES[: document["robots"]]
    table = Table(title=None, show_edge=False, pad_edge=False)
    for header in ("seed", "rooms", "coverage", "rooms entered"):
        table.add_column(header, justify="right", no_wrap=True)
    for name in names:
        table.add_column(f"ATE {name}", justify="right", no_wrap=True)
    for header in ("reloc 10cm/1°", "precision", "recall", "time s"):
        table.add_column(header, justify="right", no_wrap=True)
    failed = []
    for row in document["rows"]:
        rooms = "-" if row["rooms"] is None else str(row["rooms"])
        if row["error"] is not None:
            failed.append(row)
            table.add_row(str(row["seed"]), rooms, "failed", *["-"] * (len(names) + 4),
                          f"{row['wall_time_s']:.1f}")  # fmt: skip
            continue
        found = row["relocalization"]
        table.add_row(
            str(row["seed"]),
            rooms,
            _cell(row["coverage"], ".1%"),
            f"{row['rooms_entered']} / {row['rooms_reachable']}",
            *[format_ate(row["robots"].get(name, {})) for name in names],
            "-" if found is None else f"{found['success']} / {found['searches']}",
            f"{row['map_precision']:.3f}",
            f"{row['map_recall']:.3f}",
            f"{row['wall_time_s']:.1f}",
        )
    console = make_console()
    # Never truncate a number: a table wider than the terminal is printed at its own width.
    wide = Measurement.get(console, console.options.update(max_width=1000), table).maximum
    Console(highlight=False, soft_wrap=True, width=max(console.width, wide)).print(table)
    for row in failed:
        console.print(f"seed {row['seed']} failed: {row['error']}")
    s = document["summary"]
    n = s["buildings"]
    ate_m, ate_deg, coverage = s["ate_m"], s["ate_deg"], s["coverage"]
    if ate_m["median"] is not None:
        console.print(
            f"ATE over the robots of {n - s['failed']} buildings: median "
            f"{ate_m['median'] * 100:.1f} cm / {ate_deg['median']:.2f}°, worst "
            f"{ate_m['worst'] * 100:.1f} cm / {ate_deg['worst']:.2f}°"
            + (f"; {s['robots_lost']} robots lost" if s["robots_lost"] else "")
        )
        console.print(f"floor coverage: min {coverage['min']:.1%}, median {coverage['median']:.1%}")
    console.print(
        f"every robot below 5 cm and 0.5°: {s['within_5cm_05deg']:.0%} of {n} buildings; "
        f"below 10 cm and 1°: {s['within_10cm_1deg']:.0%}; failed: {s['failed']} of {n}; "
        f"{s['wall_time_s']:.0f} s"
    )
