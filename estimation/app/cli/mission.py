"""Mission commands: demo, simulate, batch, isam, evaluate."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from estimation.app.cli.common import (
    ConfigOption,
    FiguresOption,
    JsonOption,
    cli_errors,
    make_console,
    option_config,
    option_overrides,
)
from estimation.app.cli.ros import McapOption, print_export
from estimation.app.config import ConfigError

if TYPE_CHECKING:
    from estimation.app.ros.live_view import LiveView
    from estimation.app.sim.simulate import SimulationResult

ViewOption = Annotated[
    bool,
    typer.Option(
        "--view",
        help='Serve the result live to Foxglove (WebSocket; docs/ros.md, "Live view in '
        'Foxglove") and keep serving until Ctrl-C.',
    ),
]
ViewPortOption = Annotated[
    int,
    typer.Option("--view-port", min=0, max=65535, help="Port of the live view (0: any free port)."),
]
ViewHostOption = Annotated[
    str,
    typer.Option(
        "--view-host",
        help="Interface the live view listens on; anyone who reaches it sees the map "
        "(0.0.0.0: every interface).",
    ),
]
ViewSecondsOption = Annotated[
    float | None,
    typer.Option("--view-seconds", min=0.0, help="Serve this long (s) after the work, then exit."),
]


@cli_errors
def demo(
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")] = Path("runs/demo"),
    config: ConfigOption = None,
    seed: Annotated[int | None, typer.Option(help="Override the mission's seed.")] = None,
) -> None:
    """Simulate the default mission (essex_lab, two robots), optimize, fuse, evaluate, render."""
    import time

    from estimation.app.evaluation.evaluate import evaluate as run_evaluate
    from estimation.app.pipeline import run_batch
    from estimation.app.resources import resolve_builtin
    from estimation.app.sim.demo import DEFAULT_POSE, DEFAULT_WORLD, run_demo
    from estimation.app.sim.simulate import run_simulation

    overrides = option_overrides(config)
    cfg = option_config(config)
    started = time.perf_counter()
    err = make_console(stderr=True)
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
    console = make_console()
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


@cli_errors
def simulate(
    mission: Annotated[
        Path, typer.Argument(help="A mission YAML file or a built-in mission name.")
    ],
    out: Annotated[Path, typer.Option("--out", "-o", help="Dataset folder to write.")],
    seed: Annotated[int | None, typer.Option(help="Override the mission's seed.")] = None,
    config: ConfigOption = None,
    view: ViewOption = False,
    view_port: ViewPortOption = 8765,
    view_host: ViewHostOption = "127.0.0.1",
    view_seconds: ViewSecondsOption = None,
) -> None:
    """Simulate a cooperative mission: world + robots + sensors → a recorded dataset."""
    from estimation.app.resources import resolve_builtin
    from estimation.app.sim.simulate import run_simulation
    from sensors.sim.mission import load_mission

    overrides = option_overrides(config)
    path = resolve_builtin("missions", mission)
    if view:
        spec = load_mission(path)
        if spec.plan != "auto" or spec.auto.planner != "map":
            raise ConfigError(
                f"{path}: --view shows the mission loop's estimate, and this mission is not "
                "flown by it (plan: auto with auto.planner: map); run coopmap batch --view on "
                "the dataset instead"
            )
    with live_view(view, view_host, view_port) as live:
        err = make_console(stderr=True)
        with err.status(f"simulating {path.stem}…", spinner="dots") as status:

            def progress(robot: str, fraction: float) -> None:
                status.update(f"simulating {path.stem}: sensors of robot {robot} ({fraction:.0%})")

            def update(text: str) -> None:
                status.update(f"{path.stem}: {text}")

            result = run_simulation(
                path, out, overrides=overrides, seed=seed, progress=progress, status=update,
                observe=None if live is None else live.publish_loop,
            )  # fmt: skip
        print_simulation(result)
        if result.loop is not None:
            serve_result(live, result.out_dir / "result", result.out_dir, view_seconds)


def print_simulation(result: SimulationResult) -> None:
    """What ``simulate`` flew and where it wrote it."""
    console = make_console()
    poses = ", ".join(f"{name} {count}" for name, count in result.poses.items())
    console.print(
        f"coopmap simulate: {result.mission} in {result.world} (seed {result.seed}): "
        f"{result.steps} leapfrog steps over {result.duration_s:.0f} s; poses per robot: {poses}; "
        f"{sum(result.telegrams.values()):,} LMS telegrams"
        + (f"; {len(result.changed)} objects moved afterwards" if result.changed else "")
    )
    if result.loop is not None:
        loop = result.loop
        work = loop["work_per_dwell_s"]
        late = sum(not item["in_time"] for item in loop["concurrent_localization"])
        console.print(
            f"  mission loop: {loop['stop_reason']}; work per dwell median {work['median']:.2f} s, "
            f"p99 {work['p99']:.2f} s; {len(loop['concurrent_localization'])} concurrent "
            f"localizations ({late} late); {len(loop['retried_observations'])} observations "
            f"retried, {len(loop['refused_goals'])} goals refused"
        )
        console.print(f"  wrote {result.out_dir}/ and its result {result.out_dir / 'result'}/")
        return
    console.print(f"  wrote {result.out_dir}/")


@cli_errors
def batch(
    dataset: Annotated[Path, typer.Argument(help="A dataset folder (coopmap simulate).")],
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Result folder.")] = None,
    config: ConfigOption = None,
    mcap: McapOption = None,
    view: ViewOption = False,
    view_port: ViewPortOption = 8765,
    view_host: ViewHostOption = "127.0.0.1",
    view_seconds: ViewSecondsOption = None,
    figures: FiguresOption = True,
) -> None:
    """Batch optimization (Levenberg–Marquardt with GNC), then fusion of the global 3D map."""
    from estimation.app.pipeline import run_batch

    overrides = option_overrides(config)
    check_mcap(mcap)
    with live_view(view, view_host, view_port) as live:
        err = make_console(stderr=True)
        with err.status(f"processing {dataset}…", spinner="dots") as status:
            output = run_batch(
                dataset, out, overrides=overrides, progress=status.update, figures=figures
            )
        print_batch(output.report, output.out_dir)
        export_mcap(output.out_dir, mcap, dataset)
        serve_result(live, output.out_dir, dataset, view_seconds)
    fail_unplaced(output.report, output.out_dir)


def print_batch(r: dict[str, Any], out_dir: Path) -> None:
    """What ``batch`` found and where it wrote it."""
    poses = ", ".join(f"{name} {s['poses']}" for name, s in r["robots"].items())
    implausible = ", ".join(f"{name} {s['implausible_scans']}" for name, s in r["robots"].items())
    make_console().print(
        f"coopmap batch: {r['sweeps']} sweeps, {r['observations']} mutual observations "
        f"({len(r['gate_rejections'])} gated out, {len(r['outlier_factors'])} outliers), "
        f"poses: {poses}; implausible scans: {implausible}; "
        f"{r.get('occupied_voxels', 0):,} occupied voxels; "
        f"{r['timings_s']['total']:.1f} s"
    )
    if r.get("partial_mission"):
        make_console().print(
            f"  the mission failed under way ({r['partial_mission']}): this result covers its "
            "recording up to the failure"
        )
    unobserved = r.get("stations_without_mutual", [])
    if unobserved:
        make_console().print(
            "  stations without a mutual observation (odometry and station searches only): "
            + ", ".join(
                f"{s['station']} ({s['search_factors']} search factors)" for s in unobserved
            )
        )
    make_console().print(f"  wrote {out_dir}/")


def check_mcap(mcap: Path | None) -> None:
    """Refuse a ``--mcap`` target before the work, not after it."""
    if mcap is not None:
        from estimation.app.ros.bag import check_mcap_replaceable

        check_mcap_replaceable(mcap)


@contextlib.contextmanager
def live_view(wanted: bool, host: str, port: int) -> Iterator[LiveView | None]:
    """The ``--view`` server, listening before the work starts (a taken port fails at once);
    None without ``--view``. Stopped when the command ends."""
    if not wanted:
        yield None
        return
    from estimation.app.ros.live_view import LiveView

    with LiveView(host=host, port=port) as view:
        make_console().print(
            f"live view: {view.url} (Foxglove: Open connection → Foxglove WebSocket)"
        )
        yield view


def serve_result(live: LiveView | None, result: Path, dataset: Path, seconds: float | None) -> None:
    """Publish the finished result to the live view, then serve it for ``seconds`` or, when
    None, until Ctrl-C."""
    if live is None:
        return
    console = make_console()
    for note in live.publish_result(result, dataset_dir=dataset):
        console.print(f"  live view note: {note}")
    if seconds is not None:
        console.print(f"live view: serving the result at {live.url} for {seconds:g} s")
        time.sleep(seconds)
        return
    console.print(f"live view: serving the result at {live.url}; press Ctrl-C to stop")
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        console.print("live view: stopped")


def export_mcap(result: Path, mcap: Path | None, dataset: Path) -> None:
    if mcap is not None:
        from estimation.app.ros.export import export_result

        print_export(export_result(result, mcap, dataset_dir=dataset))


def fail_unplaced(report: dict[str, Any], out_dir: Path) -> None:
    """Exit 2 with one line when a robot ended with no pose (nothing tied it to the map); the
    result of the others stays written."""
    lost = [name for name, s in report["robots"].items() if not s["poses"]]
    if lost:
        who = f"robot {lost[0]} has" if len(lost) == 1 else f"robots {', '.join(lost)} have"
        typer.echo(
            f"coopmap: error: {who} no pose in the result: no mutual observation tied "
            f"{'it' if len(lost) == 1 else 'them'} to the map (see unseen_pairs and "
            f"missing_sweeps in {out_dir / 'report.json'})",
            err=True,
        )
        raise typer.Exit(code=2)


@cli_errors
def isam(
    dataset: Annotated[Path, typer.Argument(help="A dataset folder (coopmap simulate).")],
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Result folder.")] = None,
    resume: Annotated[
        bool, typer.Option(help="Continue from the checkpoint of a cut-short run.")
    ] = False,
    config: ConfigOption = None,
    mcap: McapOption = None,
    view: ViewOption = False,
    view_port: ViewPortOption = 8765,
    view_host: ViewHostOption = "127.0.0.1",
    view_seconds: ViewSecondsOption = None,
    figures: FiguresOption = True,
) -> None:
    """Incremental iSAM2 over the same data, event by event, with checkpoints."""
    from estimation.app.pipeline import run_isam

    overrides = option_overrides(config)
    check_mcap(mcap)
    with live_view(view, view_host, view_port) as live:
        err = make_console(stderr=True)
        with err.status(f"processing {dataset} event by event…", spinner="dots") as status:
            output = run_isam(
                dataset,
                out,
                overrides=overrides,
                resume=resume,
                progress=status.update,
                figures=figures,
            )
        assert output is not None
        r = output.report
        make_console().print(
            f"coopmap isam: {r['isam2']['events']} events"
            + (" (resumed)" if resume else "")
            + f", iSAM2 update median {r['isam2']['update_median_ms']:.2f} ms, max "
            f"{r['isam2']['update_max_ms']:.2f} ms; {r.get('occupied_voxels', 0):,} occupied "
            "voxels"
        )
        make_console().print(f"  wrote {output.out_dir}/")
        export_mcap(output.out_dir, mcap, dataset)
        serve_result(live, output.out_dir, dataset, view_seconds)
    fail_unplaced(output.report, output.out_dir)


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

    from estimation.app.evaluation.evaluate import evaluate as run_evaluate

    metrics = run_evaluate(dataset, result)
    if json_out:
        typer.echo(json.dumps(metrics))
        return
    console = make_console()
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
    for band in ("ceiling", "floor"):
        entry = found.get(f"relocalization_{band}")
        if entry:
            console.print(
                f"relocalization ({band} band): {entry['success']} of {entry['searches']} within "
                f"10 cm and 1°, median error {entry['median_m'] * 100:.1f} cm / "
                f"{entry['median_deg']:.2f}°"
            )
    validation = found.get("validation")
    if validation:
        console.print(
            f"validator: {validation['checks']} search results checked, "
            f"{len(validation['outside'])} outside their region, "
            f"{len(validation['flagged'])} factors flagged"
        )
    coverage = metrics.get("coverage")
    if coverage:
        console.print(
            f"floor coverage: {coverage['coverage']:.1%} of the reachable floor known; rooms "
            f"entered: {len(coverage['rooms_entered'])} of {len(coverage['rooms'])}"
        )
    console.print(
        f"map at {quality['resolution_m']:g} m: precision {quality['precision']:.3f}, "
        f"recall {quality['recall']:.3f} ({quality['occupied']:,} occupied cells)"
    )
