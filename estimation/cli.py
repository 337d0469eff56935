"""The ``coopmap`` command line (DESIGN §11).

Every command takes ``--config FILE`` (YAML overrides of ``configs/default.yaml``). Known errors
print one line on stderr and exit with code 2, never a traceback. Each command is a thin shell
around a typed function that tests call directly; heavy modules are imported inside commands so
that ``coopmap --help`` stays fast.
"""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, ParamSpec, TypeVar

import typer
from rich.console import Console

from estimation.config import Config, ConfigError, config_to_yaml, load_config

__all__ = ["app", "main"]

P = ParamSpec("P")
R = TypeVar("R")

app = typer.Typer(
    name="coopmap",
    help="Cooperative 3D mapping by mobile robots that localize each other.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)
world_app = typer.Typer(help="Simulated worlds.", no_args_is_help=True)
config_app = typer.Typer(help="The configuration.", no_args_is_help=True)
bench_app = typer.Typer(
    help="Side-by-side benchmarks: coopmap and its peer in one process, with their ratio.",
    no_args_is_help=True,
)
lms_app = typer.Typer(help="The SICK LMS 200: decode, emulate, record.", no_args_is_help=True)
app.add_typer(world_app, name="world")
app.add_typer(config_app, name="config")
app.add_typer(bench_app, name="bench")
app.add_typer(lms_app, name="lms")

JsonOption = Annotated[
    bool, typer.Option("--json", help="Print one machine-readable JSON object on stdout.")
]

ConfigOption = Annotated[
    Path | None,
    typer.Option("--config", "-c", help="YAML file of overrides merged over the defaults."),
]


def _known_errors() -> tuple[type[BaseException], ...]:
    from estimation.errors import EstimationError
    from mapping.errors import MapError
    from sensors.errors import SensorError

    return (ConfigError, SensorError, MapError, EstimationError, OSError)


def _describe(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.strerror and exc.filename:
        return f"{exc.filename}: {exc.strerror.lower()}"
    return str(exc) or type(exc).__name__


def cli_errors(command: Callable[P, R]) -> Callable[P, R]:
    """Turn known errors into one line on stderr and exit code 2."""

    @functools.wraps(command)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        try:
            return command(*args, **kwargs)
        except _known_errors() as exc:
            typer.echo(f"coopmap: error: {_describe(exc)}", err=True)
            raise typer.Exit(code=2) from None

    return wrapper


def _config(path: Path | None) -> Config:
    return load_config(path)


def _console(stderr: bool = False) -> Console:

    # soft_wrap: never break long lines (paths) when the output is piped or captured.
    return Console(stderr=stderr, highlight=False, soft_wrap=True)


def _file_size(path: Path) -> str:
    size = path.stat().st_size
    return f"{size / 1e6:.1f} MB" if size >= 1e6 else f"{size / 1e3:.0f} kB"


@app.command()
@cli_errors
def demo(
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")] = Path("runs/demo"),
    config: ConfigOption = None,
    seed: Annotated[int | None, typer.Option(help="Override the mission's seed.")] = None,
) -> None:
    """Simulate the default mission (essex_lab, two robots), optimize, fuse, evaluate, render."""
    import time

    from estimation.demo import DEFAULT_POSE, DEFAULT_WORLD, run_demo
    from estimation.evaluate import evaluate as run_evaluate
    from estimation.pipeline import run_batch
    from estimation.resources import resolve_builtin
    from estimation.simulate import run_simulation
    from sensors.yamlio import read_yaml_mapping

    overrides = read_yaml_mapping(config, ConfigError) if config is not None else None
    cfg = _config(config)
    started = time.perf_counter()
    err = _console(stderr=True)
    with err.status("simulating the essex_lab mission…", spinner="dots") as status:
        sim = run_simulation(
            resolve_builtin("missions", "essex_lab"), out, overrides=overrides, seed=seed,
            progress=lambda robot, f: status.update(f"simulating: robot {robot} ({f:.0%})"),
        )  # fmt: skip
        status.update("decoding, mutual localization, pose graph, fusion…")
        output = run_batch(out, overrides=overrides, progress=status.update)
        status.update("evaluating against the ground truth…")
        metrics = run_evaluate(out)
        status.update("rendering the world and a 360° view…")
        view = run_demo(out / "result" / "view", cfg, world=DEFAULT_WORLD, pose=DEFAULT_POSE)
    console = _console()
    console.print(
        f"coopmap demo: {sim.world}, {len(sim.poses)} robots, {sim.steps} leapfrog steps, "
        f"{sim.duration_s:.0f} s of mission simulated, processed and evaluated in "
        f"{time.perf_counter() - started:.1f} s"
    )
    for robot, m in metrics["robots"].items():
        if m.get("poses"):
            console.print(
                f"  robot {robot}: {m['poses']} poses, ATE {m['ate_m'] * 100:.1f} cm / "
                f"{m['ate_deg']:.2f}°"
            )
    quality = metrics["map"]
    console.print(
        f"  mutual observations: {output.report['observations']}; map: "
        f"{output.report.get('occupied_voxels', 0):,} occupied voxels, precision "
        f"{quality['precision']:.3f}, recall {quality['recall']:.3f} "
        f"at {quality['resolution_m']:g} m"
    )
    result = out / "result"
    console.print(f"  dataset: {out}/  result: {result}/  report: {result / 'report.md'}")
    figures = sorted((result / "figures").glob("*.png")) + [
        p for _, p in view.outputs if p.suffix == ".png"
    ]
    console.print("  figures: " + ", ".join(str(p) for p in figures))


@app.command()
@cli_errors
def simulate(
    mission: Annotated[
        Path, typer.Argument(help="A mission YAML file or a built-in mission name.")
    ],
    out: Annotated[Path, typer.Option("--out", "-o", help="Dataset folder to write.")],
    seed: Annotated[int | None, typer.Option(help="Override the mission's seed.")] = None,
    config: ConfigOption = None,
) -> None:
    """Simulate a cooperative mission: world + robots + sensors → a recorded dataset."""
    from estimation.resources import resolve_builtin
    from estimation.simulate import run_simulation
    from sensors.yamlio import read_yaml_mapping

    overrides = read_yaml_mapping(config, ConfigError) if config is not None else None
    path = resolve_builtin("missions", mission)
    err = _console(stderr=True)
    with err.status(f"simulating {path.stem}…", spinner="dots") as status:

        def progress(robot: str, fraction: float) -> None:
            status.update(f"simulating {path.stem}: sensors of robot {robot} ({fraction:.0%})")

        result = run_simulation(path, out, overrides=overrides, seed=seed, progress=progress)
    console = _console()
    poses = ", ".join(f"{name} {count}" for name, count in result.poses.items())
    console.print(
        f"coopmap simulate: {result.mission} in {result.world} (seed {result.seed}): "
        f"{result.steps} leapfrog steps over {result.duration_s:.0f} s; poses per robot: {poses}; "
        f"{sum(result.telegrams.values()):,} LMS telegrams"
        + (f"; {len(result.changed)} objects moved afterwards" if result.changed else "")
    )
    console.print(f"  wrote {result.out_dir}/")


@app.command()
@cli_errors
def batch(
    dataset: Annotated[Path, typer.Argument(help="A dataset folder (coopmap simulate).")],
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Result folder.")] = None,
    config: ConfigOption = None,
) -> None:
    """Batch optimization (Levenberg–Marquardt with GNC), then fusion of the global 3D map."""
    from estimation.pipeline import run_batch
    from sensors.yamlio import read_yaml_mapping

    overrides = read_yaml_mapping(config, ConfigError) if config is not None else None
    err = _console(stderr=True)
    with err.status(f"processing {dataset}…", spinner="dots") as status:
        output = run_batch(dataset, out, overrides=overrides, progress=status.update)
    r = output.report
    poses = ", ".join(f"{name} {s['poses']}" for name, s in r["robots"].items())
    _console().print(
        f"coopmap batch: {r['sweeps']} sweeps, {r['observations']} mutual observations "
        f"({len(r['gate_rejections'])} gated out, {len(r['outlier_factors'])} outliers), "
        f"poses: {poses}; {r.get('occupied_voxels', 0):,} occupied voxels; "
        f"{r['timings_s']['total']:.1f} s"
    )
    _console().print(f"  wrote {output.out_dir}/")


@app.command()
@cli_errors
def isam(
    dataset: Annotated[Path, typer.Argument(help="A dataset folder (coopmap simulate).")],
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Result folder.")] = None,
    resume: Annotated[
        bool, typer.Option(help="Continue from the checkpoint of a cut-short run.")
    ] = False,
    config: ConfigOption = None,
) -> None:
    """Incremental iSAM2 over the same data, event by event, with checkpoints."""
    from estimation.pipeline import run_isam
    from sensors.yamlio import read_yaml_mapping

    overrides = read_yaml_mapping(config, ConfigError) if config is not None else None
    err = _console(stderr=True)
    with err.status(f"processing {dataset} event by event…", spinner="dots") as status:
        output = run_isam(dataset, out, overrides=overrides, resume=resume, progress=status.update)
    assert output is not None
    r = output.report
    _console().print(
        f"coopmap isam: {r['isam2']['events']} events"
        + (" (resumed)" if resume else "")
        + f", iSAM2 update median {r['isam2']['update_median_ms']:.2f} ms, max "
        f"{r['isam2']['update_max_ms']:.2f} ms; {r.get('occupied_voxels', 0):,} occupied voxels"
    )
    _console().print(f"  wrote {output.out_dir}/")


@app.command()
@cli_errors
def evaluate(
    dataset: Annotated[
        Path, typer.Argument(help="A simulated dataset folder (with ground truth).")
    ],
    result: Annotated[
        Path | None, typer.Option(help="Result folder (default DATASET/result).")
    ] = None,
    json_out: JsonOption = False,
) -> None:
    """Accuracy against the dataset's ground truth; writes metrics.json beside the result."""
    import json

    from estimation.evaluate import evaluate as run_evaluate

    metrics = run_evaluate(dataset, result)
    if json_out:
        typer.echo(json.dumps(metrics))
        return
    console = _console()
    for robot, m in metrics["robots"].items():
        if m.get("poses"):
            console.print(
                f"robot {robot}: {m['poses']} poses, ATE {m['ate_m'] * 100:.1f} cm / "
                f"{m['ate_deg']:.2f}°"
                + (f", RPE {m['rpe_m'] * 100:.1f} cm / {m['rpe_deg']:.2f}°" if "rpe_m" in m else "")
            )
    mutual, quality = metrics["mutual"], metrics["map"]
    if mutual["median_m"] is not None:
        console.print(
            f"mutual: {mutual['events']} events, {mutual['rejected']} gated out, median error "
            f"{mutual['median_m'] * 100:.1f} cm / {mutual['median_deg']:.2f}°"
        )
    gate = mutual.get("gate")
    if gate:
        console.print(
            f"gate: accepted {gate['accepted_true']} true / {gate['accepted_false']} false, "
            f"rejected {gate['rejected_true']} true / {gate['rejected_false']} false"
            f" (+{gate['rejected_without_pose']} without a pose)"
        )
    found = metrics.get("global_localization", {})
    for kind, name in (("link", "station links"), ("loop", "loop closures")):
        entry = found.get(kind)
        if entry and entry.get("used"):
            console.print(
                f"{name}: {entry['used']} of {entry['searches']} searches used, "
                f"{entry['used_within_10cm_1deg']} within 10 cm and 1°, median error "
                f"{entry['used_median_m'] * 100:.1f} cm / {entry['used_median_deg']:.2f}°, max "
                f"{entry['used_max_m'] * 100:.1f} cm / {entry['used_max_deg']:.2f}°"
            )
        elif entry:
            console.print(f"{name}: none of {entry['searches']} searches used")
    validation = found.get("validation")
    if validation:
        console.print(
            f"validator: {validation['checks']} search results checked, "
            f"{len(validation['outside'])} outside their region, "
            f"{len(validation['flagged'])} factors flagged"
        )
    console.print(
        f"map at {quality['resolution_m']:g} m: precision {quality['precision']:.3f}, "
        f"recall {quality['recall']:.3f} ({quality['occupied']:,} occupied cells)"
    )


@app.command()
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

    from estimation.localize import localize_files, render_pdf

    cfg = _config(config)
    if pdf_out is not None and pdf_out.suffix.lower() != ".png":
        raise ConfigError(f"{pdf_out}: --pdf-out must name a .png file")
    err = _console(stderr=True)
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
    console = _console()
    console.print(
        f"coopmap localize: x={report['x_m']:.3f} m, y={report['y_m']:.3f} m, "
        f"yaw={report['yaw_deg']:.2f}° (σ {sigma[0] * 100:.1f} cm, {sigma[1] * 100:.1f} cm, "
        f"{math.degrees(sigma[2]):.2f}°); peak ratio {found.result.peak_ratio:.3g}, {verdict}; "
        f"{report['poses_searched']:,} poses in {report['seconds']:.3f} s{windows}"
    )
    if pdf_out is not None:
        console.print(f"  wrote {pdf_out} ({_file_size(pdf_out)})")


@app.command("evaluate-localization")
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

    from estimation.evaluate_localization import (
        DATA_DIR,
        format_report,
        run_evaluation,
        write_figures,
    )

    cfg = _config(config)
    parts = tuple(only or ("sim", "geb079", "carmen"))
    unknown = sorted(set(parts) - {"sim", "geb079", "carmen"})
    if unknown:
        raise ConfigError(f"--only must be sim, geb079 or carmen, got {', '.join(unknown)}")
    err = _console(stderr=True)
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


@world_app.command("show")
@cli_errors
def world_show(
    world: Annotated[str, typer.Argument(help="A built-in world name or a world YAML file.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="PNG file to write.")],
    config: ConfigOption = None,
) -> None:
    """Draw a world: top view with a height colour scale, and its sub-ceiling band."""
    from estimation.figures import render_world
    from estimation.resources import resolve_builtin
    from sensors.sim.world import load_world

    cfg = _config(config)
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
    _console().print(
        f"wrote {path} ({_file_size(path)}): {model.name}, {len(model.rooms)} rooms, "
        f"{len(model.boxes)} boxes, {len(model.cylinders)} cylinders ({movable} movable)"
    )


@world_app.command("list")
@cli_errors
def world_list(config: ConfigOption = None) -> None:
    """List the built-in worlds."""
    from estimation.resources import builtin_names, resolve_builtin
    from sensors.sim.world import load_world

    _config(config)  # validated like every command's, though listing needs none of it
    console = _console()
    for name in builtin_names("worlds"):
        model = load_world(resolve_builtin("worlds", name))
        lower, upper = model.bounds_xy()
        size = upper - lower
        console.print(
            f"{name:16s} {size[0]:5.1f} m × {size[1]:4.1f} m, {len(model.rooms):2d} rooms, "
            f"{len(model.boxes) + len(model.cylinders):3d} objects "
            f"({len(model.movable_names())} movable)"
        )


@lms_app.command("decode")
@cli_errors
def lms_decode(
    file: Annotated[Path, typer.Argument(help="A capture (lms record) or a plain binary dump.")],
    json_out: JsonOption = False,
    direction: Annotated[
        str, typer.Option(help="from_sensor, to_sensor or any (by the address bit).")
    ] = "any",
    config: ConfigOption = None,
) -> None:
    """Decode a raw LMS 2xx byte stream: one line per telegram, then a summary of counts."""
    import json

    from sensors.lms200.capture import CaptureReader, decode_stream

    cfg = _config(config)
    records, summary = decode_stream(CaptureReader(file), cfg.scanner.measuring_mode, direction)
    out = sys.stdout
    for record in records:
        if json_out:
            out.write(json.dumps(record, separators=(",", ":")) + "\n")
        else:
            out.write(_telegram_line(record) + "\n")
    counts = summary.as_dict()
    if json_out:
        out.write(json.dumps({"kind": "summary", **counts}) + "\n")
    else:
        out.write(
            f"{file}: {counts['bytes']:,} bytes, {counts['telegrams']:,} telegrams "
            f"({counts['scans']:,} scans, {counts['replies']:,} replies, "
            f"{counts['commands']:,} commands), {counts['acks']} ACK, {counts['naks']} NAK, "
            f"{counts['checksum_failures']} checksum failures, {counts['undecodable']} "
            f"undecodable, {counts['bytes_skipped']:,} bytes skipped"
            + (
                f", {counts['truncated_bytes']} bytes truncated"
                if counts["truncated_bytes"]
                else ""
            )
            + "\n"
        )


PoseOption = Annotated[
    tuple[float, float, float],
    typer.Option("--pose", help="Robot pose in the world: X_M Y_M YAW_DEG."),
]


@lms_app.command("emulate")
@cli_errors
def lms_emulate(
    world: Annotated[
        str, typer.Option(help="A built-in world name or a world YAML file.")
    ] = "essex_lab",
    pose: PoseOption = (6.0, 4.5, 90.0),
    power_on_baud: Annotated[int, typer.Option(help="Rate after power-on.")] = 9600,
    seconds: Annotated[
        float, typer.Option(help="Run this long, then stop (0: until interrupted).")
    ] = 0.0,
    seed: Annotated[int, typer.Option(help="Seed of the simulated noise and mechanics.")] = 0,
    config: ConfigOption = None,
) -> None:
    """An LMS 200 on a pseudo-terminal, scanning a simulated world; prints its device path."""
    import math
    import time

    from estimation.resources import resolve_builtin
    from estimation.rig import simulated_scan_source
    from sensors.lms200.emulator import Lms200Emulator
    from sensors.sim.world import load_world

    cfg = _config(config)
    model = load_world(resolve_builtin("worlds", world))
    if model.room_at(pose[:2]) is None:
        raise ConfigError(
            f"pose ({pose[0]:g}, {pose[1]:g}) lies outside every room of {model.name}"
        )
    source = simulated_scan_source(model, (pose[0], pose[1], math.radians(pose[2])), cfg, seed)
    emulator = Lms200Emulator(source, power_on_baud=power_on_baud, password=cfg.serial.password)
    path = emulator.start()
    typer.echo(path)
    typer.echo(
        f"coopmap: LMS 200 emulator on {path} (power-on {power_on_baud} Bd), world {model.name}, "
        f"robot at x={pose[0]:g} m, y={pose[1]:g} m, yaw={pose[2]:g}°; Ctrl-C stops it",
        err=True,
    )
    sys.stdout.flush()
    try:
        deadline = time.monotonic() + seconds if seconds > 0 else math.inf
        while time.monotonic() < deadline:
            time.sleep(0.05)
    except KeyboardInterrupt:
        typer.echo("coopmap: interrupted: stopping the emulator", err=True)
    finally:
        emulator.close()
    state = emulator.state
    typer.echo(
        f"coopmap: emulator stopped after {state.commands} commands, {state.scans_sent} scans",
        err=True,
    )


@lms_app.command("record")
@cli_errors
def lms_record(
    port: Annotated[str, typer.Option(help="Device path or pyserial URL (socket://, loop://).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Capture file to create.")],
    scans: Annotated[int, typer.Option(help="Stop after this many scans (0: no limit).")] = 0,
    seconds: Annotated[float, typer.Option(help="Stop after this long (0: no limit).")] = 0.0,
    config: ConfigOption = None,
) -> None:
    """Start an LMS 200 (or the emulator) and record its raw byte stream with receive times."""
    import time

    from estimation.rig import driver_from_config
    from sensors.lms200.capture import CaptureWriter

    cfg = _config(config)
    writer = CaptureWriter(out, {"port": port, "baud_rate": cfg.serial.baud_rate})
    started = time.monotonic()
    driver = driver_from_config(
        cfg, port, tap=lambda stamp, chunk: writer.write(stamp - started, chunk)
    )
    count = 0
    try:
        info = driver.start()
        typer.echo(
            f"coopmap: recording {info.type_text} on {port} at {info.baud_rate} Bd", err=True
        )
        deadline = started + seconds if seconds > 0 else float("inf")
        for _ in driver.scans():
            count += 1
            if (scans and count >= scans) or time.monotonic() >= deadline:
                break
            if count % 50 == 0:
                writer.flush()
    except KeyboardInterrupt:
        typer.echo("coopmap: interrupted: keeping what was recorded", err=True)
    except Exception:
        driver.close()
        # Keep what was recorded before the failure; leave nothing if nothing was.
        if count == 0:
            writer.discard()
        else:
            kept = writer.close()
            typer.echo(f"coopmap: kept {kept} ({count} scans before the failure)", err=True)
        raise
    driver.close()
    path = writer.close()
    typer.echo(f"wrote {path} ({writer.bytes_written:,} bytes, {count} scans)")


@bench_app.command("fusion")
@cli_errors
def bench_fusion(
    json_out: JsonOption = False,
    config: ConfigOption = None,
    repeats: Annotated[
        int, typer.Option(min=1, help="Insertions per tool and scan; the best is kept.")
    ] = 7,
    refusion_scans: Annotated[
        int, typer.Option(min=0, help="Simulated scans re-fused into one map (0: skip).")
    ] = 200,
    data: Annotated[
        Path | None, typer.Option(help="The shared data folder (default: ../shared/data).")
    ] = None,
) -> None:
    """Bayesian 3D fusion of one scan by coopmap and by OctoMap, in one process."""
    import json

    from estimation.bench_fusion import (
        default_data_dir,
        format_fusion_report,
        run_fusion_benchmark,
    )

    cfg = _config(config)
    with _console(stderr=True).status("fusing scans with coopmap and OctoMap…", spinner="dots"):
        result = run_fusion_benchmark(
            cfg, data or default_data_dir(), repeats=repeats, refusion_scans=refusion_scans
        )
    typer.echo(json.dumps(result) if json_out else format_fusion_report(result))


@bench_app.command("scan")
@cli_errors
def bench_scan(json_out: JsonOption = False, config: ConfigOption = None) -> None:
    """Decode + 3D conversion of one full 3D scan (≈250 telegrams), against its 20 s."""
    import json

    from estimation.bench_scan import run_scan_benchmark

    result = run_scan_benchmark(_config(config))
    if json_out:
        typer.echo(json.dumps(result))
        return
    typer.echo(
        f"bench scan: one 3D scan ({result['telegrams']} telegrams, {result['bytes']:,} bytes, "
        f"{result['points']:,} points) decoded and converted in {result['milliseconds']:.1f} ms "
        f"(median of {result['repeats']}, max {result['milliseconds_max']:.1f} ms); the scanner "
        f"takes {result['sweep_seconds']:.1f} s: {result['ratio']:,.0f}× real time"
    )


@bench_app.command("search")
@cli_errors
def bench_search(
    json_out: JsonOption = False,
    config: ConfigOption = None,
    repeats: Annotated[int, typer.Option(min=1, help="Timed searches (median).")] = 5,
) -> None:
    """Exhaustive search, 20 m × 20 m × 360 rotations, full PDF, against the per-pose loop."""
    import json

    from estimation.bench_search import run_search_benchmark
    from estimation.localize import search_params

    cfg = _config(config)
    err = _console(stderr=True)
    with err.status("timing the search and the per-pose loop…", spinner="dots"):
        r = run_search_benchmark(
            search_params(cfg.search), cfg.search.resolution_m, repeats=repeats
        )
    if json_out:
        typer.echo(json.dumps(r))
        return
    rows, cols = r["map_cells"]
    typer.echo(
        f"bench search: {cols * r['resolution_m']:g} m × {rows * r['resolution_m']:g} m map at "
        f"{r['resolution_m']:g} m, {r['rotations']} rotations ({r['poses']:,} poses), local grid "
        f"of {r['local_known_cells']:,} known cells, {r['workers']} threads\n"
        f"  coopmap, full PDF + refined best pose: {r['seconds']:.3f} s (median of "
        f"{r['repeats']}, max {r['seconds_max']:.3f} s); as a PosePdf object +"
        f"{r['posepdf_seconds']:.3f} s\n"
        f"  best pose alone (branch and bound, exact: {r['best_pose_blocks_expanded']:,} of "
        f"{r['best_pose_blocks']:,} blocks expanded; same lattice pose as the full search: "
        f"{'yes' if r['best_pose_same_lattice_pose'] else 'NO'}): "
        f"{r['best_pose_seconds'] * 1000:.1f} ms (max {r['best_pose_seconds_max'] * 1000:.1f} ms)\n"
        f"  per-pose loop (the paper's method): {r['peer_seconds']:,.0f} s, extrapolated from "
        f"{r['peer_poses_timed']:,} poses ({r['peer_rotations_timed']} rotations) timed in "
        f"{r['peer_seconds_measured']:.1f} s; scores agree within "
        f"{r['peer_max_score_difference']:.1e} of the score scale\n"
        f"  ratio: {r['ratio']:,.0f}× faster; pose error {r['error_m'] * 100:.1f} cm, "
        f"{r['error_deg']:.2f}°"
    )


@bench_app.command("graph")
@cli_errors
def bench_graph(
    json_out: JsonOption = False,
    config: ConfigOption = None,
    case: Annotated[
        list[str] | None,
        typer.Option(
            help="Run only this case (repeatable): leapfrog_5000, "
            "leapfrog_5000_loops, intel, ais2klinik."
        ),
    ] = None,
    data: Annotated[
        Path | None, typer.Option(help="The shared data folder (default: ../shared/data).")
    ] = None,
) -> None:
    """Pose graph: batch and iSAM2 per-event times on synthetic and real graphs."""
    import json

    from estimation.bench_graph import CASES, DATA_DIR, format_report, run_bench
    from estimation.pipeline import graph_settings

    cfg = _config(config)
    err = _console(stderr=True)
    with err.status("optimizing pose graphs…", spinner="dots") as status:
        report = run_bench(
            case or CASES,
            graph_settings(cfg),
            robust=cfg.graph.robust,
            relinearize_threshold=cfg.graph.isam2_relinearize_threshold,
            relinearize_skip=cfg.graph.isam2_relinearize_skip,
            data_dir=data or DATA_DIR,
            progress=lambda name: status.update(f"optimizing {name}…"),
        )
    typer.echo(json.dumps(report) if json_out else format_report(report))


def _telegram_line(record: dict[str, Any]) -> str:
    kind = str(record["kind"])
    head = f"{record['offset']:>10}  {kind:<12}"
    if "code" in record:
        head += f" {int(record['code']):02X}"
    if kind == "scan":
        ranges = record["ranges_m"]
        assert isinstance(ranges, list)
        valid = sum(r is not None for r in ranges)
        flagged = sum(1 for f in record["flags"] if f)
        index = record.get("scan_index")
        return (
            f"{head}  {len(ranges)} values, {valid} valid, {flagged} flagged, {record['unit']}"
            + (f", scan index {index}" if index is not None else "")
        )
    if kind == "reply":
        skip = {"offset", "addr", "code", "crc_ok", "kind", "stamp_s", "status", "name"}
        details = {k: v for k, v in record.items() if k not in skip}
        return f"{head}  {record['name']} {details}"
    if kind in ("command", "invalid", "bad_checksum"):
        extra = record.get("error") or record.get("data") or f"length {record.get('length')}"
        return f"{head}  {extra}"
    return head


@config_app.command("show")
@cli_errors
def config_show(config: ConfigOption = None) -> None:
    """Print the effective configuration (defaults merged with --config) as YAML."""
    typer.echo(config_to_yaml(_config(config)), nl=False)


def main() -> None:
    """Console-script entry point."""
    try:
        app()
    except KeyboardInterrupt:
        typer.echo("coopmap: interrupted", err=True)
        sys.exit(130)
