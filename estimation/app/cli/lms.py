"""The lms command group: decode, emulate, record."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated, Any

import typer

from estimation.app.cli.common import (
    ConfigOption,
    JsonOption,
    check_seed,
    cli_errors,
    option_config,
)
from estimation.app.config import ConfigError

lms_app = typer.Typer(help="The SICK LMS 200: decode, emulate, record.", no_args_is_help=True)


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

    from estimation.app.rig import scan_limits
    from sensors.lms200.capture import CaptureReader, decode_stream

    cfg = option_config(config)
    records, summary = decode_stream(
        CaptureReader(file), cfg.scanner.measuring_mode, direction, scan_limits(cfg)
    )
    out = sys.stdout
    for record in records:
        if json_out:
            out.write(json.dumps(record, separators=(",", ":")) + "\n")
        else:
            out.write(_telegram_line(record) + "\n")
    counts = summary.as_dict()
    reasons = ", ".join(f"{why} {n}" for why, n in sorted(counts["implausible_reasons"].items()))
    if json_out:
        out.write(json.dumps({"kind": "summary", **counts}) + "\n")
    else:
        out.write(
            f"{file}: {counts['bytes']:,} bytes, {counts['telegrams']:,} telegrams "
            f"({counts['scans']:,} scans, {counts['replies']:,} replies, "
            f"{counts['commands']:,} commands), {counts['acks']} ACK, {counts['naks']} NAK, "
            f"{counts['checksum_failures']} checksum failures, {counts['undecodable']} "
            f"undecodable, {counts['implausible']} implausible"
            + (f" ({reasons})" if reasons else "")
            + f", {counts['bytes_skipped']:,} bytes skipped"
            + (
                f", {counts['truncated_bytes']} bytes truncated"
                if counts["truncated_bytes"]
                else ""
            )
            + (
                f", {counts['corrupt_bytes']:,} bytes of damaged records lost"
                if counts["corrupt_bytes"]
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

    from estimation.app.resources import resolve_builtin
    from estimation.app.rig import simulated_scan_source
    from sensors.lms200.emulator import Lms200Emulator
    from sensors.sim.world import load_world

    cfg = option_config(config)
    check_seed(seed)
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

    from estimation.app.rig import driver_from_config
    from sensors.lms200.capture import CaptureWriter

    cfg = option_config(config)
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
    if kind in ("command", "invalid", "bad_checksum", "implausible"):
        extra = (
            record.get("error")
            or record.get("reason")
            or record.get("data")
            or f"length {record.get('length')}"
        )
        return f"{head}  {extra}"
    return head
