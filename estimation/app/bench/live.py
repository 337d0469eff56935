"""``coopmap bench live``: a mission over the network against the same mission in one process.

The live run is ``coopmap live`` (the base and one agent process per robot, Zenoh on loopback);
its peer is the mission loop flying the same mission with the simulated robots in its own
process (``coopmap simulate`` with ``auto.planner: map``). Both run here, one after the other;
the benchmark prints their wall times and ratio, and from the live run's report the scan → map
latency (a chunk written to the robot's disk → the base's map holds it), the bytes per robot
per second and the command round trips. ``--repeat`` soaks: the live run again and again.
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml

from estimation.app.live.supervisor import LiveOptions, Supervisor
from estimation.errors import EstimationError
from sensors.sim.mission import load_mission

__all__ = ["format_live_report", "peer_mission", "run_live_benchmark"]


def peer_mission(mission: Path, folder: Path) -> Path:
    """The mission as the in-process loop flies it: the base's exploration on its map."""
    spec = load_mission(mission)
    if spec.plan == "auto":
        spec = spec.model_copy(update={"auto": spec.auto.model_copy(update={"planner": "map"})})
    document = spec.model_dump(mode="json")
    world = mission.parent / spec.world
    if world.is_file():
        document["world"] = str(world.resolve())
    path = folder / mission.name
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def run_live_benchmark(mission: Path, *, repeat: int = 1, faults: str | None = None,
                       timeout_s: float = 1800.0) -> dict[str, Any]:  # fmt: skip
    from estimation.app.sim.simulate import run_simulation

    robots = load_mission(mission).robot_names()
    runs = []
    with tempfile.TemporaryDirectory(prefix="coopmap-bench-live-") as tmp:
        root = Path(tmp)
        for k in range(repeat):
            out = root / f"live{k}"
            injected = dict.fromkeys(robots, faults) if faults else {}
            options = LiveOptions(mission, out, robots, faults=injected)
            supervisor = Supervisor(options)
            began = time.perf_counter()
            code = supervisor.run(timeout_s=timeout_s)
            wall = time.perf_counter() - began
            if code != 0:
                tail = supervisor.base_log().strip().splitlines()[-1:] or ["(no output)"]
                raise EstimationError(f"bench live: the live run stopped ({code}): {tail[0]}")
            report = json.loads((out / "result" / "report.json").read_text())
            runs.append({"wall_s": wall, "loop": report["mission_loop"]})
        began = time.perf_counter()
        run_simulation(peer_mission(mission, root), root / "peer")
        peer_s = time.perf_counter() - began
    last = runs[-1]["loop"]
    network = last["network"]
    return {
        "mission": mission.stem, "robots": robots, "faults": faults,
        "live_wall_s": [r["wall_s"] for r in runs], "in_process_wall_s": peer_s,
        "mission_s": last["duration_s"], "dwells": last["dwells"],
        "work_per_dwell_s": last["work_per_dwell_s"], "network": network,
        "clocks": last.get("clocks", {}),
    }  # fmt: skip


def format_live_report(result: dict[str, Any]) -> str:
    live = result["live_wall_s"]
    best = min(live)
    lines = [
        f"coopmap bench live {result['mission']} ({len(result['robots'])} robots, Zenoh on "
        f"loopback{', faults ' + result['faults'] if result['faults'] else ''}): "
        f"{result['dwells']} dwells, {result['mission_s']:.0f} s of mission",
        f"  wall time: live {best:.1f} s"
        + (f" (best of {len(live)}; worst {max(live):.1f} s)" if len(live) > 1 else "")
        + f", in one process {result['in_process_wall_s']:.1f} s: "
        f"{best / result['in_process_wall_s']:.2f}x",
        f"  loop work per dwell: median {result['work_per_dwell_s']['median']:.2f} s, "
        f"p99 {result['work_per_dwell_s']['p99']:.2f} s",
    ]
    for robot, n in result["network"]["robots"].items():
        fused, cmd = n["scan_to_map_s"], n["command_latency_s"]
        lines.append(
            f"  robot {robot}: scan -> map p50 {fused['p50'] * 1e3:.0f} ms, p99 "
            f"{fused['p99'] * 1e3:.0f} ms; {n['bytes_per_s'] / 1e3:.0f} kB/s "
            f"({n['bytes'] / 1e6:.1f} MB in {n['chunks']} chunks); command round trip p50 "
            f"{cmd['p50'] * 1e3:.0f} ms, p99 {cmd['p99'] * 1e3:.0f} ms; "
            f"{n['queried_from_disk']} chunks queried from its disk"
        )
    return "\n".join(lines)
