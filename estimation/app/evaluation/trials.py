"""Localization trials: one search against the truth, and what a set of trials says (success,
strict, dominance, the calibrated β)."""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from estimation.errors import EstimationError
from estimation.search.exhaustive import SearchParams, SearchResult, search, windowed_search
from mapping.band import Band

BETAS = np.geomspace(0.002, 0.5, 25)
Progress = Callable[[str], None]


@dataclass(frozen=True)
class Trial:
    """One search: the truth, the answer, and how well the PDF scored the truth."""

    case: str
    band: str
    truth: tuple[float, float, float]  # x_m, y_m, yaw_rad
    estimate: tuple[float, float, float]
    error_m: float
    error_deg: float
    peak_ratio: float
    seconds: float
    log_likelihood: tuple[float, ...]  # per β of BETAS: log P(true cell); () if not computed
    dominant: bool = True  # the search's own verdict: trust the answer
    room: str = ""  # the simulated world's room holding the truth

    @property
    def success(self) -> bool:
        return self.error_m < 0.1 and self.error_deg < 1.0

    @property
    def strict(self) -> bool:
        return self.error_m < 0.05 and self.error_deg < 0.5


def log_likelihoods(result: SearchResult, truth: np.ndarray) -> tuple[float, ...]:
    """log P(cell holding the truth) under exp(β·score), for each β of BETAS (−inf off the
    lattice)."""
    x_m, y_m, yaw = result.x_m, result.y_m, result.yaw_rad
    ix = round((truth[0] - x_m[0]) / (x_m[1] - x_m[0]))
    iy = round((truth[1] - y_m[0]) / (y_m[1] - y_m[0]))
    it = round(((truth[2] - yaw[0]) % (2 * math.pi)) / (yaw[1] - yaw[0])) % len(yaw)
    if not (0 <= ix < len(x_m) and 0 <= iy < len(y_m)):
        return tuple(-math.inf for _ in BETAS)
    scores = result.scores
    assert scores is not None
    top = float(result.best_score)
    at_truth = float(scores[it, iy, ix])
    out = []
    for beta in BETAS:
        shifted = np.float32(beta) * (scores - np.float32(top))
        np.maximum(shifted, np.float32(-87.0), out=shifted)
        total = float(np.exp(shifted).sum(dtype=np.float64))
        out.append(beta * (at_truth - top) - math.log(total))
    return tuple(out)


def run_trial(
    case: str,
    band: str,
    local: Band,
    global_: Band,
    truth: np.ndarray,
    params: SearchParams,
    calibrate: bool = False,
    prior: tuple[np.ndarray, float, float] | None = None,
    room: str = "",
) -> Trial:
    """Search (the whole map, or given ``prior`` = (position, window_m, max_window_m) a window
    around it that grows) and score the answer against the truth."""
    if prior is None:
        result = search(local, global_, params, keep_scores=calibrate)
        dominant = result.is_dominant(params.dominance_ratio)
        seconds = result.seconds
    else:
        found = windowed_search(local, global_, params, *prior)
        result, dominant = found.result, found.dominant
        seconds = sum(step.seconds for step in found.steps)
    d = result.pose - truth
    return Trial(
        case=case,
        band=band,
        truth=(float(truth[0]), float(truth[1]), float(truth[2])),
        estimate=(float(result.pose[0]), float(result.pose[1]), float(result.pose[2])),
        error_m=math.hypot(d[0], d[1]),
        error_deg=abs(math.degrees(math.remainder(d[2], 2 * math.pi))),
        peak_ratio=result.peak_ratio,
        seconds=seconds,
        log_likelihood=log_likelihoods(result, truth) if calibrate else (),
        dominant=dominant,
        room=room,
    )


# -- simulated worlds --------------------------------------------------------------------------


def calibrate_beta(trials: list[Trial]) -> tuple[float, list[float]]:
    """The β of BETAS maximising the mean log P(true cell) over the trials, and that mean per β
    (trials whose truth lies off the lattice are left out)."""
    table = np.array(
        [
            t.log_likelihood
            for t in trials
            if t.log_likelihood and np.isfinite(t.log_likelihood).all()
        ]
    )
    if len(table) == 0:
        raise EstimationError("no trial to calibrate β on")
    mean = table.mean(axis=0)
    return float(BETAS[int(np.argmax(mean))]), [float(v) for v in mean]


def summarise(trials: list[Trial]) -> dict[str, Any]:
    errors_m = [t.error_m for t in trials]
    errors_deg = [t.error_deg for t in trials]
    return {
        "trials": len(trials),
        "success": sum(t.success for t in trials) / len(trials),
        "strict": sum(t.strict for t in trials) / len(trials),
        "median_m": statistics.median(errors_m),
        "median_deg": statistics.median(errors_deg),
        "p95_m": float(np.percentile(errors_m, 95)),
        "p95_deg": float(np.percentile(errors_deg, 95)),
        "median_seconds": statistics.median(t.seconds for t in trials),
        "dominant": sum(t.dominant for t in trials) / len(trials),
        "dominant_correct": (
            sum(t.success for t in trials if t.dominant) / max(1, sum(t.dominant for t in trials))
        ),
    }


def by_room_kind(trials: list[Trial]) -> list[Trial]:
    """The trials again, each case split by the kind of room holding the truth (the room name
    up to its first "_": office_loop's "corridor" and "office")."""
    import dataclasses

    return [
        dataclasses.replace(t, case=f"{t.case}: truth in {t.room.split('_')[0] or 'room'}s")
        for t in trials
    ]
