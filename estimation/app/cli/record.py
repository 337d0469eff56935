"""The recording commands: record (on each robot), clock (serve, query), replay (rehearsal)."""

from __future__ import annotations

import signal
import sys
from pathlib import Path
from types import FrameType
from typing import Annotated

import typer

from estimation.app.cli.common import ConfigOption, cli_errors, option_config

clock_app = typer.Typer(help="The reference clock: serve it, query it.", no_args_is_help=True)

OdometryClock = Annotated[
    str,
    typer.Option(
        help="How odometry lines are stamped: arrival (on receipt), or the line's own t_s on "
        "the monotonic, unix or reference clock."
    ),
]


def _interrupt_on_sigterm() -> None:
    """SIGTERM stops a recording as Ctrl-C does: the files are finished, not cut short."""

    def handler(signum: int, frame: FrameType | None) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, handler)


@cli_errors
def record(
    robot: Annotated[str, typer.Option(help="This robot's name (one letter).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Recording folder to create.")],
    lms_port: Annotated[
        str | None, typer.Option(help="LMS 200 device path or pyserial URL (as lms record).")
    ] = None,
    odometry: Annotated[
        str | None,
        typer.Option(help="Odometry source: tcp://HOST:PORT, serial://PATH?baud=N or a device."),
    ] = None,
    odometry_clock: OdometryClock = "arrival",
    clock_server: Annotated[
        str | None, typer.Option(help="Reference clock server HOST:PORT (coopmap clock serve).")
    ] = None,
    clock_offset: Annotated[
        float | None,
        typer.Option(help="No server: reference = this robot's unix time + OFFSET seconds."),
    ] = None,
    events: Annotated[
        Path | None,
        typer.Option(help="Mission file (events, JSON lines, mission clock); default: prompt."),
    ] = None,
    robots: Annotated[
        str, typer.Option(help="Robots the operator prompt tracks, e.g. a,b (default: --robot).")
    ] = "",
    mission_start: Annotated[
        float | None, typer.Option(help="Reference-clock time of mission time 0.")
    ] = None,
    until: Annotated[
        float | None,
        typer.Option(help="Stop at this mission time (default with --events: its end + 1 s)."),
    ] = None,
    seconds: Annotated[float, typer.Option(help="Stop after this long (0: no limit).")] = 0.0,
    sync_interval: Annotated[float, typer.Option(help="Seconds between clock exchanges.")] = 1.0,
    config: ConfigOption = None,
) -> None:
    """Record one robot's mission: LMS capture, odometry, events and its clock mapping."""
    from estimation.app.record import RecordOptions, build_recorder, prompt_lines
    from sensors.errors import RecordingError
    from sensors.recording.recorder import run_recorder

    cfg = option_config(config)
    options = RecordOptions(
        robot=robot, out_dir=out, lms_port=lms_port, odometry=odometry,
        odometry_clock=odometry_clock, clock_server=clock_server, clock_offset_s=clock_offset,
        events_file=events, robots=tuple(r for r in robots.replace(" ", "").split(",") if r),
        mission_start_ref_s=mission_start, until_mission_s=until, sync_interval_s=sync_interval,
    )  # fmt: skip
    recorder = build_recorder(cfg, options)
    _interrupt_on_sigterm()
    recorder.start()
    mapping = recorder.mapping()
    typer.echo(
        f"coopmap: recording robot {robot} into {out} (clock {mapping.source}: rate "
        f"{mapping.rate:.6f}, ±{mapping.uncertainty_s * 1e3:.2f} ms)"
        + ("; commands: start, depart, arrive, dwell, end, roles, note, quit" if events is None
           else f"; events from {events}"),
        err=True,
    )  # fmt: skip
    sys.stderr.flush()
    lines = prompt_lines(sys.stdin) if events is None else None
    summary = run_recorder(
        recorder,
        lines=lines,
        seconds=seconds,
        answer=lambda r: typer.echo(("" if r.ok else "error: ") + r.message, err=True),
    )
    typer.echo(
        f"wrote {out} ({summary.reason}): {summary.lms_telegrams} LMS telegrams, "
        f"{summary.odometry_poses} odometry poses ({summary.odometry_malformed} malformed lines "
        f"skipped), {summary.events} events, {summary.clock_samples} clock exchanges "
        f"({summary.clock_lost} lost)"
    )
    if summary.error:
        raise RecordingError(f"the recording stopped on an error (kept {out}): {summary.error}")


@clock_app.command("serve")
@cli_errors
def clock_serve(
    listen: Annotated[str, typer.Option(help="HOST:PORT to answer on (UDP).")] = "127.0.0.1:8123",
    seconds: Annotated[float, typer.Option(help="Stop after this long (0: until Ctrl-C).")] = 0.0,
) -> None:
    """Serve this computer's unix time as the mission's reference clock (NTP-style exchange)."""
    import math
    import time

    from sensors.recording.clock import ClockServer, parse_endpoint

    host, port = parse_endpoint(listen)
    _interrupt_on_sigterm()
    with ClockServer(time.time, host, port) as server:
        typer.echo(f"{server.host}:{server.port}")
        typer.echo(f"coopmap: serving the reference clock on {server.host}:{server.port} "
                   "(UDP); Ctrl-C stops it", err=True)  # fmt: skip
        sys.stdout.flush()
        deadline = time.monotonic() + seconds if seconds > 0 else math.inf
        try:
            while time.monotonic() < deadline:
                time.sleep(0.05)
        except KeyboardInterrupt:
            typer.echo("coopmap: interrupted: stopping the clock server", err=True)
    typer.echo(f"coopmap: answered {server.answered} exchanges, ignored {server.ignored}", err=True)


@clock_app.command("query")
@cli_errors
def clock_query(
    server: Annotated[str, typer.Argument(help="HOST:PORT of a clock server.")],
    count: Annotated[int, typer.Option(help="Exchanges to make.")] = 8,
    timeout: Annotated[float, typer.Option(help="Seconds to wait for each answer.")] = 0.2,
) -> None:
    """Exchange with a clock server: the offset of this computer's unix time, and the delay."""
    import time

    from sensors.recording.clock import ClockSync, parse_endpoint

    sync = ClockSync(parse_endpoint(server), local_clock=time.time, timeout_s=timeout)
    try:
        got = sync.burst(count, tries=max(count, 1) * 2)
    finally:
        sync.close()
    best = min(sync.samples, key=lambda s: s.round_trip_s)
    typer.echo(
        f"{server}: {got} exchanges, best round trip {best.round_trip_s * 1e3:.3f} ms, offset "
        f"{best.reference_s - best.local_s:+.6f} s (reference − this clock) "
        f"± {best.round_trip_s / 2 * 1e3:.3f} ms"
    )


@cli_errors
def replay(
    dataset: Annotated[Path, typer.Argument(help="A dataset folder (docs/dataset.md).")],
    robot: Annotated[list[str], typer.Option(help="A robot to serve (repeat for several).")],
    speed: Annotated[float, typer.Option(help="Simulated seconds per real second.")] = 1.0,
    lead: Annotated[float, typer.Option(help="Simulated seconds before mission time 0.")] = 30.0,
    tail: Annotated[float, typer.Option(help="Simulated seconds after the end.")] = 30.0,
    host: Annotated[str, typer.Option(help="Address to serve on.")] = "127.0.0.1",
    clock_port: Annotated[int, typer.Option(help="UDP port of the clock (0: any).")] = 0,
    config: ConfigOption = None,
) -> None:
    """Serve recorded robots as hardware: LMS emulator ptys, odometry ports and one clock."""
    import time

    from sensors.sim.replay import Replay

    cfg = option_config(config)
    _interrupt_on_sigterm()
    session = Replay(
        dataset, robot, speed=speed, lead_s=lead, tail_s=tail, host=host,
        clock_port=clock_port, measuring_mode=cfg.scanner.measuring_mode,
    )  # fmt: skip
    try:
        endpoints = session.start()
        typer.echo(f"clock {host}:{session.clock_port}")
        for point in endpoints.values():
            typer.echo(
                f"robot {point.robot} {point.device_path} tcp://{host}:{point.odometry_port}"
            )
        sys.stdout.flush()
        typer.echo(
            f"coopmap: replaying {dataset} at {speed:g}x from mission time {-lead:g} s to "
            f"{session.end_s + tail:.1f} s; Ctrl-C stops it",
            err=True,
        )
        while not session.finished:
            time.sleep(0.05)
    except KeyboardInterrupt:
        typer.echo("coopmap: interrupted: stopping the replay", err=True)
    finally:
        session.close()
