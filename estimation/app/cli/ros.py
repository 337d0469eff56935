"""ROS 2 interchange commands: ``coopmap export`` (docs/ros.md)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from estimation.app.cli.common import cli_errors, file_size, make_console

if TYPE_CHECKING:
    from estimation.app.ros.export import ExportSummary

__all__ = ["McapOption", "export", "print_export"]

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
    result: Annotated[Path, typer.Argument(help="A result folder (coopmap batch or isam).")],
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
    """Export a result as a ROS 2 bag: map, voxels, OctoMap, paths, poses, tf, markers."""
    from estimation.app.ros.export import export_result

    print_export(export_result(result, mcap, dataset_dir=dataset))
