"""``coopmap bench batch``: ``coopmap batch`` as a user runs it, timed from the outside.

Each run is a fresh ``coopmap batch`` process on the same dataset (a built-in mission simulated
once, office_loop unless told otherwise, or a dataset given), its result written to a temporary
folder. The benchmark measures what the user waits for and what the machine gives: the wall
time from start to exit, the process's CPU time and its peak resident memory (``wait4``'s
``ru_maxrss``), with the figures drawn and without (``--no-figures``), alternating, after one
run to warm the caches that is not counted. The result's ``report.json`` splits ``run_batch``'s
time into its steps; what is left of the wall time is starting Python, importing, writing the
result files and drawing the figures. The targets are absolute (``TARGET_SECONDS``,
``TARGET_RSS_MB``): there is no peer that does this job.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from estimation.errors import EstimationError

__all__ = ["TARGET_RSS_MB", "TARGET_SECONDS", "format_batch_report", "run_batch_benchmark"]

#: The targets for office_loop: wall seconds and peak resident megabytes of one run.
TARGET_SECONDS = 4.0
TARGET_RSS_MB = 400.0
#: A run that takes longer than this is killed and the benchmark fails.
RUN_TIMEOUT_S = 900.0
_POLL_S = 0.002


def run_batch_benchmark(
    dataset: Path | None = None,
    *,
    mission: str = "office_loop",
    repeats: int = 3,
    warm_up: bool = True,
    progress: Any = None,
) -> dict[str, Any]:
    """Time ``coopmap batch`` on ``dataset`` (or on ``mission`` simulated into a temporary
    folder) ``repeats`` times with figures and as many without, alternating; first one run
    that is not counted, unless ``warm_up`` is False."""
    if repeats < 1:
        raise EstimationError(f"bench batch: repeats must be at least 1, got {repeats}")
    with tempfile.TemporaryDirectory(prefix="coopmap-bench-batch-") as tmp:
        root = Path(tmp)
        if dataset is None:
            from estimation.app.resources import resolve_builtin
            from estimation.app.sim.simulate import run_simulation

            if progress is not None:
                progress(f"simulating {mission}…")
            dataset = root / mission
            run_simulation(resolve_builtin("missions", Path(mission)), dataset)
            source = f"{mission} (built-in, simulated with its seed)"
        else:
            dataset = Path(dataset)
            if not dataset.is_dir():
                raise EstimationError(f"bench batch: {dataset}: no such dataset folder")
            source = str(dataset)
        out = root / "result"
        if warm_up:
            if progress is not None:
                progress("warming up (one run, not counted)…")
            _timed_run(dataset, out, figures=True)
        runs = []
        for k in range(repeats):
            for figures in (True, False):
                if progress is not None:
                    progress(f"run {k + 1} of {repeats}, {'with' if figures else 'without'} "
                             "figures…")  # fmt: skip
                runs.append(_timed_run(dataset, out, figures=figures))
    return {
        "benchmark": "batch",
        "dataset": source,
        "sweeps": runs[-1]["sweeps"],
        "telegrams": runs[-1]["telegrams"],
        "repeats": repeats,
        "warm_up": warm_up,
        "runs": runs,
        "with_figures": _summary([r for r in runs if r["figures"]]),
        "without_figures": _summary([r for r in runs if not r["figures"]]),
        "target_seconds": TARGET_SECONDS,
        "target_rss_mb": TARGET_RSS_MB,
    }


def _timed_run(dataset: Path, out: Path, *, figures: bool) -> dict[str, Any]:
    """One ``coopmap batch`` process: wall, CPU, peak RSS and the report's step times."""
    command = [sys.executable, "-m", "estimation.app.cli.main", "batch", str(dataset),
               "--out", str(out), "--figures" if figures else "--no-figures"]  # fmt: skip
    with tempfile.TemporaryFile() as errors:
        began = time.perf_counter()
        process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=errors)
        deadline = began + RUN_TIMEOUT_S
        try:
            while True:
                # wait4, not Popen.wait: it also gives the child's resource usage.
                pid, status, usage = os.wait4(process.pid, os.WNOHANG)
                if pid:
                    wall = time.perf_counter() - began
                    break
                if time.perf_counter() > deadline:
                    raise EstimationError(f"bench batch: a run took longer than "
                                          f"{RUN_TIMEOUT_S:.0f} s")  # fmt: skip
                time.sleep(_POLL_S)
        except BaseException:  # the timeout, or Ctrl-C: no batch is left running
            process.send_signal(signal.SIGKILL)
            os.wait4(process.pid, 0)
            process.returncode = -signal.SIGKILL
            raise
        process.returncode = os.waitstatus_to_exitcode(status)
        if process.returncode != 0:
            errors.seek(0)
            lines = errors.read().decode("utf-8", "replace").strip().splitlines() or ["no output"]
            raise EstimationError(f"bench batch: coopmap batch failed ({process.returncode}): "
                                  f"{lines[-1]}")  # fmt: skip
    report = json.loads((out / "report.json").read_text())
    steps = {k: float(v) for k, v in report["timings_s"].items() if k != "total"}
    return {
        "figures": figures,
        "wall_s": wall,
        "cpu_s": usage.ru_utime + usage.ru_stime,
        "peak_rss_mb": usage.ru_maxrss / 1024.0,  # kB on Linux
        "steps_s": steps,
        # Starting Python and importing, writing the result files and, with them, the figures.
        "outside_steps_s": wall - sum(steps.values()),
        "sweeps": int(report["sweeps"]),
        "telegrams": int(sum(r["telegrams"] for r in report["robots"].values())),
    }


def _summary(runs: list[dict[str, Any]]) -> dict[str, Any]:
    walls = np.array([r["wall_s"] for r in runs])
    rss = np.array([r["peak_rss_mb"] for r in runs])
    steps = {k: float(np.median([r["steps_s"][k] for r in runs])) for k in runs[0]["steps_s"]}
    wall = float(np.median(walls))
    peak = float(np.median(rss))
    return {
        "wall_s": wall,
        "wall_min_s": float(walls.min()),
        "wall_max_s": float(walls.max()),
        "cpu_s": float(np.median([r["cpu_s"] for r in runs])),
        "peak_rss_mb": peak,
        "peak_rss_max_mb": float(rss.max()),
        "steps_s": steps,
        "outside_steps_s": float(np.median([r["outside_steps_s"] for r in runs])),
        "met": bool(wall <= TARGET_SECONDS and peak <= TARGET_RSS_MB),
    }


def format_batch_report(result: dict[str, Any]) -> str:
    """The benchmark's figures as text."""
    runs = f"{result['repeats']} run{'s' if result['repeats'] != 1 else ''}"
    lines = [
        f"bench batch: coopmap batch on {result['dataset']} ({result['telegrams']:,} telegrams, "
        f"{result['sweeps']} sweeps), {runs} each way, alternating"
        + (", after one not counted" if result["warm_up"] else "")
    ]
    for key, label in (("with_figures", "with figures"), ("without_figures", "--no-figures")):
        s = result[key]
        steps = ", ".join(f"{k.replace('_', ' ')} {v:.2f}" for k, v in s["steps_s"].items())
        lines += [
            f"  {label}: wall {s['wall_s']:.2f} s median (min {s['wall_min_s']:.2f}, max "
            f"{s['wall_max_s']:.2f}), CPU {s['cpu_s']:.2f} s, peak RSS {s['peak_rss_mb']:.0f} MB "
            f"(max {s['peak_rss_max_mb']:.0f})",
            f"    steps (s): {steps}; start, import, files"
            + (" and figures" if key == "with_figures" else "")
            + f" {s['outside_steps_s']:.2f}",
        ]
    s = result["with_figures"]
    verdict = "met" if s["met"] else "not met"
    lines.append(
        f"target ≤ {result['target_seconds']:g} s and ≤ {result['target_rss_mb']:.0f} MB per run "
        f"(with figures): {verdict}; without figures: "
        + ("met" if result["without_figures"]["met"] else "not met")
    )
    return "\n".join(lines)
