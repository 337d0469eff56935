"""The bench command group: coopmap and its peer side by side."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from estimation.app.cli.common import (
    ConfigOption,
    JsonOption,
    cli_errors,
    make_console,
    option_config,
)
from estimation.app.resources import DATA_DIR

bench_app = typer.Typer(
    help="Side-by-side benchmarks: coopmap and its peer in one process, with their ratio.",
    no_args_is_help=True,
)


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

    from estimation.app.bench.fusion import (
        format_fusion_report,
        run_fusion_benchmark,
    )

    cfg = option_config(config)
    with make_console(stderr=True).status("fusing scans with coopmap and OctoMap…", spinner="dots"):
        result = run_fusion_benchmark(
            cfg, data or DATA_DIR, repeats=repeats, refusion_scans=refusion_scans
        )
    typer.echo(json.dumps(result) if json_out else format_fusion_report(result))


@bench_app.command("scan")
@cli_errors
def bench_scan(json_out: JsonOption = False, config: ConfigOption = None) -> None:
    """Decode + 3D conversion of one full 3D scan (≈250 telegrams), against its 20 s."""
    import json

    from estimation.app.bench.scan import run_scan_benchmark

    result = run_scan_benchmark(option_config(config))
    if json_out:
        typer.echo(json.dumps(result))
        return
    typer.echo(
        f"bench scan: one 3D scan ({result['telegrams']} telegrams, {result['bytes']:,} bytes, "
        f"{result['points']:,} points) decoded and converted in {result['milliseconds']:.1f} ms "
        f"(median of {result['repeats']}, max {result['milliseconds_max']:.1f} ms); the scanner "
        f"takes {result['sweep_seconds']:.1f} s: {result['ratio']:,.0f}× real time"
    )


@bench_app.command("decode")
@cli_errors
def bench_decode(
    json_out: JsonOption = False,
    config: ConfigOption = None,
    capture: Annotated[
        Path | None, typer.Option(help="An LMS capture (.cap) to decode (default: simulated).")
    ] = None,
    telegrams: Annotated[
        int, typer.Option(min=1, help="Telegrams of the simulated capture (office_loop: 38,000).")
    ] = 38_000,
    repeats: Annotated[int, typer.Option(min=1, help="Runs per path; the best is kept.")] = 3,
) -> None:
    """LMS capture decoding: the per-telegram reference and the vectorised decoder, µs/telegram."""
    import json

    from estimation.app.bench.decode import format_decode_report, run_decode_benchmark

    cfg = option_config(config)
    with make_console(stderr=True).status("decoding the capture both ways…", spinner="dots"):
        result = run_decode_benchmark(cfg, capture, telegrams, repeats)
    typer.echo(json.dumps(result) if json_out else format_decode_report(result))


@bench_app.command("batch")
@cli_errors
def bench_batch(
    dataset: Annotated[
        Path | None,
        typer.Option(help="A dataset folder (default: the mission simulated, in a temporary one)."),
    ] = None,
    mission: Annotated[
        str, typer.Option(help="The built-in mission to simulate when no dataset is given.")
    ] = "office_loop",
    repeats: Annotated[int, typer.Option(min=1, help="Runs with figures and without.")] = 3,
    json_out: JsonOption = False,
) -> None:
    """coopmap batch as a user runs it (a fresh process each time): wall time, CPU, peak RSS and
    the steps, with figures and without, against the targets."""
    import json

    from estimation.app.bench.batch import format_batch_report, run_batch_benchmark

    with make_console(stderr=True).status("timing coopmap batch…", spinner="dots") as status:
        result = run_batch_benchmark(
            dataset, mission=mission, repeats=repeats, progress=lambda t: status.update(t)
        )
    typer.echo(json.dumps(result) if json_out else format_batch_report(result))


@bench_app.command("stations")
@cli_errors
def bench_stations(
    out: Annotated[Path, typer.Option(help="Folder for the building, dataset and result.")],
    json_out: JsonOption = False,
    seed: Annotated[int, typer.Option(min=0, help="Seed of the generated building.")] = 2,
    rooms: Annotated[int, typer.Option(min=3, max=40, help="Rooms of the building.")] = 32,
    stations: Annotated[int, typer.Option(min=16, max=500, help="Station budget.")] = 160,
) -> None:
    """Per-station work of the station searches against mission length (4 robots, a large
    generated building): the growth exponent of per-station work and the batch's time."""
    import json

    from estimation.app.bench.stations import format_stations_report, run_stations_benchmark

    err = make_console(stderr=True)
    with err.status("generating, simulating and processing the mission…", spinner="dots") as s:
        result = run_stations_benchmark(
            out, seed, rooms, stations, progress=lambda text: s.update(text)
        )
    typer.echo(json.dumps(result) if json_out else format_stations_report(result))


@bench_app.command("search")
@cli_errors
def bench_search(
    json_out: JsonOption = False,
    config: ConfigOption = None,
    repeats: Annotated[int, typer.Option(min=1, help="Timed searches (median).")] = 5,
) -> None:
    """Exhaustive search, 20 m × 20 m × 360 rotations, full PDF, against the per-pose loop;
    coarse to fine on 100 m × 100 m, and beside the exhaustive search on 40 m × 40 m."""
    import json
    import math

    from estimation.app.bench.search import run_coarse_to_fine_case, run_search_benchmark
    from estimation.app.rig import search_params

    cfg = option_config(config)
    params = search_params(cfg.search)
    resolution = cfg.search.resolution_m
    err = make_console(stderr=True)
    with err.status("timing coarse to fine on 100 m × 100 m…", spinner="dots") as status:
        # First, while the process is small: its peak RSS is then this case's.
        large = run_coarse_to_fine_case(params, 100.0, 8.0, resolution, repeats=repeats)
        status.update("coarse to fine beside the exhaustive search on 40 m × 40 m…")
        both = run_coarse_to_fine_case(params, 40.0, 8.0, resolution, repeats=3, compare=True)
        status.update("timing the search and the per-pose loop…")
        r = run_search_benchmark(params, resolution, repeats=repeats)
    r["coarse_to_fine"] = [large, both]
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
    typer.echo("  best pose alone vs the full search (median / max, ms):")
    for c in r["best_pose_cases"]:
        typer.echo(
            f"    {c['case']:<38s} full {c['full_seconds'] * 1e3:7.1f} / "
            f"{c['full_seconds_max'] * 1e3:7.1f}   best pose {c['best_pose_seconds'] * 1e3:7.1f} / "
            f"{c['best_pose_seconds_max'] * 1e3:7.1f}   {c['best_over_full']:.2f}× the full "
            f"search{'' if c['same_score'] else ' (DIFFERENT SCORE)'}"
        )
    for c in r["coarse_to_fine"]:
        side, poses = c["side_m"], c["poses"]
        typer.echo(
            f"  coarse to fine, {side:g} m × {side:g} m office floor, {c['radius_m']:g} m view "
            f"({c['local_known_cells']:,} cells), {poses:,} poses: {c['seconds']:.3f} s median "
            f"of {c['repeats']} (max {c['seconds_max']:.3f} s, first run {c['first_seconds']:.3f} "
            f"s); peak memory {c['peak_numpy_bytes'] / 1e6:.0f} MB numpy, "
            f"{c['peak_rss_bytes'] / 1e6:.0f} MB process RSS; F = {c['coarse_factor']}, "
            f"{c['poses_evaluated']:,} poses at full resolution in {c['patches']} patches, "
            f"estimated unevaluated mass {c['unevaluated_mass']:.1e}\n"
            f"    pose ({c['pose'][0]:.3f}, {c['pose'][1]:.3f}) m, "
            f"{math.degrees(c['pose'][2]):.2f}° vs truth ({c['truth'][0]:.3f}, "
            f"{c['truth'][1]:.3f}) m, {math.degrees(c['truth'][2]):.2f}°: "
            f"{c['error_m'] * 100:.1f} cm, {c['error_deg']:.2f}°"
        )
        if "exhaustive_seconds" in c:
            typer.echo(
                f"    exhaustive search on the same lattice: {c['exhaustive_seconds']:.3f} s; "
                f"same lattice pose: {'yes' if c['same_lattice_pose'] else 'NO'}; refined poses "
                f"{c['pose_difference_m'] * 1e3:.3f} mm apart; exhaustive PDF's mass outside the "
                f"evaluated poses {c['exhaustive_mass_outside']:.1e}, total variation "
                f"{c['total_variation']:.1e}"
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

    from estimation.app.bench.graph import CASES, format_report, run_bench
    from estimation.app.rig import graph_settings

    cfg = option_config(config)
    err = make_console(stderr=True)
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


@bench_app.command("live")
@cli_errors
def bench_live(
    mission: Annotated[
        Path, typer.Argument(help="A mission YAML file or a built-in mission name.")
    ] = Path("essex_lab"),
    repeat: Annotated[int, typer.Option(min=1, help="Live runs (a soak); the best is kept.")] = 1,
    faults: Annotated[
        str | None,
        typer.Option(help="Faults every robot injects: drop=P,duplicate=P,reorder=P,seed=N."),
    ] = None,
    json_out: JsonOption = False,
) -> None:
    """A mission live (processes over Zenoh on loopback) and in one process: wall times and
    their ratio, scan → map latency, bytes per robot per second."""
    import json

    from estimation.app.bench.live import format_live_report, run_live_benchmark
    from estimation.app.live.agent import AgentFaults
    from estimation.app.resources import resolve_builtin

    if faults:
        AgentFaults.parse(faults)  # a bad --faults fails here, not in every robot
    path = resolve_builtin("missions", mission)
    with make_console(stderr=True).status(f"flying {path.stem} live and in one process…"):
        result = run_live_benchmark(path, repeat=repeat, faults=faults)
    typer.echo(json.dumps(result) if json_out else format_live_report(result))
