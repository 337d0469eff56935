"""The live commands: robot (an agent per robot), base (the base station), live (both, here)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated, Any

import typer

from estimation.app.cli.common import ConfigOption, cli_errors, make_console, option_overrides
from estimation.app.cli.mission import ViewHostOption, ViewOption, ViewPortOption, live_view
from estimation.app.config import ConfigError

MissionArgument = Annotated[
    Path, typer.Argument(help="A mission YAML file or a built-in mission name.")
]
LiveViewSecondsOption = Annotated[
    float,
    typer.Option(
        "--view-seconds",
        min=0.0,
        help="With --view: keep serving the mission's final state this long (s), then exit.",
    ),
]


def _say(text: str) -> None:
    make_console(stderr=True).print(f"[{time.strftime('%H:%M:%S')}] {text}")


@cli_errors
def robot(
    mission: MissionArgument,
    name: Annotated[str, typer.Option("--name", help="This robot's name in the mission.")],
    simulate: Annotated[
        bool,
        typer.Option("--simulate", help="The robot is the simulator's (its world, its sensors)."),
    ] = False,
    emulate: Annotated[
        bool,
        typer.Option(
            "--emulate",
            help="A simulated robot whose LMS 200 telegrams go through the "
            "device emulator on a pseudo-terminal and the real driver (implies "
            "--simulate).",
        ),
    ] = False,
    connect: Annotated[
        str, typer.Option(help="The base station's endpoint (tcp/HOST:PORT).")
    ] = "tcp/127.0.0.1:7447",
    folder: Annotated[
        Path | None,
        typer.Option(
            "--dir", help="The robot's own disk copy (default runs/robots/<mission>-<r>)."
        ),
    ] = None,
    seed: Annotated[int | None, typer.Option(help="Override the mission's seed.")] = None,
    faults: Annotated[
        str | None,
        typer.Option(
            help="Inject faults into what this robot publishes, for tests: "
            "drop=P,duplicate=P,reorder=P,seed=N."
        ),
    ] = None,
    clock_offset: Annotated[
        float, typer.Option(help="Simulated robots: their clock's offset from mission time (s).")
    ] = 0.0,
    clock_drift_ppm: Annotated[
        float, typer.Option(help="Simulated robots: their clock's drift (ppm).")
    ] = 0.0,
    port: Annotated[
        str | None,
        typer.Option(
            help="A real robot: its LMS 200's serial port (/dev/ttyUSB0) or pyserial URL."
        ),
    ] = None,
    odometry: Annotated[
        str | None,
        typer.Option(
            help="A real robot: its base's odometry lines (tcp://HOST:PORT, "
            "serial://PATH?baud=N or a device path; docs/recording.md)."
        ),
    ] = None,
    drive: Annotated[
        str | None,
        typer.Option(
            help="A real robot: its base's goal endpoint (tcp://HOST:PORT; docs/live.md)."
        ),
    ] = None,
    move_timeout: Annotated[
        float, typer.Option(min=1.0, help="A real robot: how long a goal may take (s).")
    ] = 600.0,
    config: ConfigOption = None,
) -> None:
    """A robot agent: records to its own disk, publishes numbered chunks, executes the base's
    goals (docs/live.md). The robot is simulated (--simulate, --emulate) or real (--port,
    --odometry, --drive)."""
    from estimation.app.live.agent import AgentFaults
    from estimation.app.live.station import HardwareOptions, run_hardware_robot, run_robot
    from estimation.app.resources import resolve_builtin

    real = [o for o, v in (("--port", port), ("--odometry", odometry), ("--drive", drive)) if v]
    if real and (simulate or emulate):
        raise ConfigError(f"coopmap robot: {', '.join(real)} name a real robot; --simulate and "
                          "--emulate a simulated one: choose one")  # fmt: skip
    if not real and not (simulate or emulate):
        raise ConfigError("coopmap robot: a real robot needs --port, --odometry and --drive; "
                          "a simulated one --simulate or --emulate")  # fmt: skip
    path = resolve_builtin("missions", mission)
    if real:
        if not (port and odometry and drive):
            missing = [o for o in ("--port", "--odometry", "--drive") if o not in real]
            raise ConfigError(f"coopmap robot: a real robot needs {', '.join(missing)} too")
        if faults or seed is not None or clock_offset or clock_drift_ppm:
            raise ConfigError("coopmap robot: --faults, --seed and --clock-* are for "
                              "simulated robots")  # fmt: skip
        run_hardware_robot(path, name, folder or Path("runs/robots") / f"{path.stem}-{name}",
                           HardwareOptions(port, odometry, drive, move_timeout), connect=connect,
                           overrides=option_overrides(config), say=_say)  # fmt: skip
        return
    run_robot(
        path,
        name,
        folder or Path("runs/robots") / f"{path.stem}-{name}",
        connect=connect,
        overrides=option_overrides(config),
        seed=seed,
        faults=AgentFaults.parse(faults) if faults else None,
        clock_offset_s=clock_offset,
        clock_drift_ppm=clock_drift_ppm,
        emulate=emulate,
        say=_say,
    )


@cli_errors
def base(
    mission: MissionArgument,
    out: Annotated[Path, typer.Option("--out", "-o", help="Dataset folder the base rebuilds.")],
    listen: Annotated[
        str, typer.Option(help="Endpoint the base listens on (tcp/HOST:PORT).")
    ] = "tcp/127.0.0.1:7447",
    state: Annotated[
        Path | None,
        typer.Option(
            help="Checkpoint folder (default: .<out>.base beside --out); a base "
            "started again with it resumes the mission."
        ),
    ] = None,
    join_timeout: Annotated[
        float, typer.Option(min=1.0, help="How long to wait for every robot to join (s).")
    ] = 60.0,
    view: ViewOption = False,
    view_port: ViewPortOption = 8765,
    view_host: ViewHostOption = "127.0.0.1",
    view_seconds: LiveViewSecondsOption = 0.0,
    config: ConfigOption = None,
) -> None:
    """The base station: runs the mission loop with the robots on the network, rebuilds the
    dataset from their chunks, publishes estimate, map and mission state (docs/live.md)."""
    from estimation.app.live.station import BaseOptions, run_base
    from estimation.app.resources import resolve_builtin

    path = resolve_builtin("missions", mission)
    options = BaseOptions(path, out, state, listen, option_overrides(config), join_timeout)
    with live_view(view, view_host, view_port) as foxglove:
        observe = None if foxglove is None else foxglove.publish_loop
        result = run_base(options, say=_say, observe=observe)
        if foxglove is not None:  # the final state, for a viewer still watching
            for note in foxglove.publish_result(out / "result", dataset_dir=out):
                _say(f"live view note: {note}")
            _linger(foxglove.url, view_seconds)
    print_live(result.loop, out)


def _linger(url: str, seconds: float) -> None:
    """Serve the final state for ``seconds`` (Ctrl-C ends it early: the result is written)."""
    if seconds <= 0:
        return
    _say(f"live view: serving the final state at {url} for {seconds:g} s")
    try:
        time.sleep(seconds)
    except KeyboardInterrupt:
        _say("live view: stopped")


def print_live(loop: dict[str, Any], out: Path) -> None:
    console = make_console()
    work = loop["work_per_dwell_s"]
    console.print(
        f"coopmap base: {loop['stop_reason']}; {loop['dwells']} dwells over "
        f"{loop['duration_s']:.0f} s of mission; work per dwell median {work['median']:.2f} s, "
        f"p99 {work['p99']:.2f} s"
    )
    network = loop.get("network", {})
    for r, n in network.get("robots", {}).items():
        lat = n["command_latency_s"]
        console.print(
            f"  robot {r}: {n['chunks']} chunks, {n['bytes'] / 1e6:.1f} MB "
            f"({n['bytes_per_s'] / 1e3:.0f} kB/s); {n['queried_from_disk']} queried from its "
            f"disk, {n['duplicates_dropped']} duplicates dropped; command round trip p50 "
            f"{lat['p50']:.2f} s, p99 {lat['p99']:.2f} s"
        )
    if network.get("malformed_dropped") or network.get("foreign_dropped"):
        console.print(f"  dropped {network['malformed_dropped']} malformed and "
                      f"{network['foreign_dropped']} foreign messages")  # fmt: skip
    console.print(f"  wrote {out}/ and its result {out / 'result'}/")


@cli_errors
def live(
    mission: MissionArgument,
    out: Annotated[Path, typer.Option("--out", "-o", help="Dataset folder (with result/).")] = Path(
        "runs/live"
    ),
    port: Annotated[int, typer.Option(min=0, max=65535, help="Loopback port (0: any free).")] = 0,
    seed: Annotated[int | None, typer.Option(help="Override the mission's seed.")] = None,
    emulate: Annotated[
        bool,
        typer.Option(
            "--emulate",
            help="Each robot's LMS 200 telegrams go through the device "
            "emulator on a pseudo-terminal and the real driver.",
        ),
    ] = False,
    view: ViewOption = False,
    view_port: ViewPortOption = 8765,
    view_seconds: LiveViewSecondsOption = 0.0,
    config: ConfigOption = None,
) -> None:
    """The base and one simulated robot agent per robot as processes on this machine, over
    Zenoh on loopback; a robot that dies is restarted (docs/live.md)."""
    import json

    from estimation.app.live.supervisor import LiveOptions, Supervisor
    from estimation.app.resources import resolve_builtin
    from estimation.app.sim.simulate import mission_config
    from sensors.sim.mission import load_mission

    path = resolve_builtin("missions", mission)
    spec = load_mission(path)
    mission_config(spec, option_overrides(config), str(path))  # a bad --config fails here, once
    options = LiveOptions(path, out, spec.robot_names(), port, config, seed, emulate=emulate,
                          view_port=view_port if view else None,
                          view_seconds=view_seconds)  # fmt: skip
    supervisor = Supervisor(options, say=_say)
    _say(f"live {path.stem}: base on {supervisor.endpoint}, robots "
         f"{', '.join(spec.robot_names())}; logs in {supervisor.logs}/")  # fmt: skip
    code = supervisor.run()
    if code == 130:
        _say(f"interrupted: the base's checkpoint and the robots' disks stay beside {out}; "
             "the same command resumes the mission")  # fmt: skip
        raise typer.Exit(130)
    if code != 0:
        tail = supervisor.base_log().strip().splitlines()[-1:] or ["(no output)"]
        raise ConfigError(f"the base stopped with exit code {code}: {tail[0]}")
    report = json.loads((out / "result" / "report.json").read_text())
    print_live(report["mission_loop"], out)
