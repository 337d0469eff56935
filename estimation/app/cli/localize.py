"""Global-localization commands: localize, evaluate-localization."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from estimation.app.cli.common import (
    ConfigOption,
    JsonOption,
    check_seed,
    cli_errors,
    file_size,
    make_console,
    option_config,
)
from estimation.app.config import ConfigError
from estimation.app.resources import DATA_DIR


@cli_errors
def localize(
    map_yaml: Annotated[
        Path, typer.Option("--map", help="The map: a map_server YAML (with its PGM).")
    ],
    scan_yaml: Annotated[
        Path, typer.Option("--scan", help="The local grid to place: a map_server YAML.")
    ],
    prior: Annotated[
        tuple[float, float, float] | None,
        typer.Option(help="Estimate X_M Y_M YAW_DEG: search a window around it that grows."),
    ] = None,
    window_m: Annotated[
        float | None, typer.Option("--window-m", help="First window side (with --prior).")
    ] = None,
    json_out: JsonOption = False,
    pdf_out: Annotated[
        Path | None, typer.Option("--pdf-out", help="PNG of the position PDF and the match.")
    ] = None,
    config: ConfigOption = None,
) -> None:
    """Global localization: the pose of the scan grid's frame in the map frame (exhaustive
    x, y, θ search with the whole pose PDF)."""
    import json
    import math

    from estimation.app.localize import localize_files, render_pdf

    cfg = option_config(config)
    if pdf_out is not None and pdf_out.suffix.lower() != ".png":
        raise ConfigError(f"{pdf_out}: --pdf-out must name a .png file")
    err = make_console(stderr=True)
    with err.status("searching every pose…", spinner="dots"):
        found = localize_files(map_yaml, scan_yaml, cfg.search, prior=prior, window_m=window_m)
    if pdf_out is not None:
        render_pdf(found, pdf_out)
    report = found.as_json()
    if json_out:
        typer.echo(json.dumps(report))
        return
    sigma = [math.sqrt(max(found.result.covariance[i, i], 0.0)) for i in range(3)]
    windows = (
        f", windows {' → '.join(f'{w:g}' for w in report['windows_m'])} m"
        if report["windows_m"]
        else ", whole map"
    )
    verdict = "dominant" if found.dominant else "NOT dominant (ambiguous)"
    if report["poses_at_full_resolution"] < report["poses_searched"]:
        windows += (
            f"; coarse to fine: {report['poses_at_full_resolution']:,} at full resolution, "
            f"estimated unevaluated mass {report['unevaluated_mass']:.1e}"
        )
    console = make_console()
    console.print(
        f"coopmap localize: x={report['x_m']:.3f} m, y={report['y_m']:.3f} m, "
        f"yaw={report['yaw_deg']:.2f}° (σ {sigma[0] * 100:.1f} cm, {sigma[1] * 100:.1f} cm, "
        f"{math.degrees(sigma[2]):.2f}°); peak ratio {found.result.peak_ratio:.3g}, {verdict}; "
        f"{report['poses_searched']:,} poses in {report['seconds']:.3f} s{windows}"
    )
    if pdf_out is not None:
        console.print(f"  wrote {pdf_out} ({file_size(pdf_out)})")


@cli_errors
def evaluate_localization(
    trials: Annotated[int, typer.Option(min=1, help="Trials per case.")] = 40,
    only: Annotated[
        list[str] | None,
        typer.Option(help="Run only this part (repeatable): sim, geb079, carmen."),
    ] = None,
    data: Annotated[
        Path | None, typer.Option(help="The shared data folder (default: ../shared/data).")
    ] = None,
    seed: Annotated[int, typer.Option(help="Seed of the random poses and noise.")] = 0,
    figures: Annotated[
        Path | None, typer.Option(help="Also draw two localizations' PDFs into this folder.")
    ] = None,
    json_out: JsonOption = False,
    config: ConfigOption = None,
) -> None:
    """Global-localization accuracy: simulated worlds, geb079 (OctoMap), CARMEN logs."""
    import json

    from estimation.app.evaluation.localization import (
        format_report,
        run_evaluation,
        write_figures,
    )

    cfg = option_config(config)
    check_seed(seed)
    parts = tuple(only or ("sim", "geb079", "carmen"))
    unknown = sorted(set(parts) - {"sim", "geb079", "carmen"})
    if unknown:
        raise ConfigError(f"--only must be sim, geb079 or carmen, got {', '.join(unknown)}")
    err = make_console(stderr=True)
    with err.status("localizing…", spinner="dots") as status:
        report = run_evaluation(
            cfg,
            parts=parts,
            trials=trials,
            data_dir=data or DATA_DIR,
            seed=seed,
            progress=lambda text: status.update(f"localizing: {text}"),
        )
        if figures is not None:
            status.update("drawing the figures…")
            report["figures"] = [str(p) for p in write_figures(figures, cfg, data or DATA_DIR)]
    typer.echo(json.dumps(report) if json_out else format_report(report))
    if figures is not None and not json_out:
        for path in report["figures"]:
            typer.echo(f"wrote {path}")
