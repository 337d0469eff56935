"""The factor-form study behind the choice of the mutual-observation factor."""

from __future__ import annotations

import pytest

from estimation.app.bench.factor_study import accuracy_study, speed_study


@pytest.fixture(scope="module")
def accuracy():  # type: ignore[no-untyped-def]
    return {row.form: row for row in accuracy_study(150, seed=2)}


def test_raw_measurement_forms_and_the_ml_between_factor_agree(accuracy) -> None:  # type: ignore[no-untyped-def]
    ml = accuracy["between_ml"]
    for form in ("bearing_range", "custom"):
        assert accuracy[form].rms_m == pytest.approx(ml.rms_m, rel=0.02)
        assert accuracy[form].rms_yaw_rad == pytest.approx(ml.rms_yaw_rad, rel=0.02)
    # all of them at the Cramér–Rao bound of the four measurements
    assert ml.rms_m == pytest.approx(ml.crb_m, rel=0.15)
    assert ml.rms_yaw_rad == pytest.approx(ml.crb_yaw_rad, rel=0.15)


def test_the_closed_form_between_factor_is_less_accurate(accuracy) -> None:  # type: ignore[no-untyped-def]
    assert accuracy["between_closed_form"].rms_m > 1.05 * accuracy["between_ml"].rms_m


def test_the_native_between_factor_is_fastest() -> None:
    # Each form's best of three runs: a machine busy with other work slows single runs unevenly.
    runs = [{row.form: row for row in speed_study(10, 9, seed=1)} for _ in range(3)]
    rows = runs[0]
    ml, custom, native = rows["between_ml"], rows["custom"], rows["bearing_range"]

    def best(form: str, field: str) -> float:
        return min(float(getattr(run[form], field)) for run in runs)

    assert ml.variables == ml.poses == 100
    assert native.variables > 1.8 * ml.variables  # beacon points
    assert best("custom", "linearize_ms") > 10 * best("between_ml", "linearize_ms")
    assert best("custom", "batch_seconds") > 5 * best("between_ml", "batch_seconds")
    assert best("bearing_range", "batch_seconds") > best("between_ml", "batch_seconds")
    assert custom.ate_m == pytest.approx(ml.ate_m, abs=1e-4)
    assert native.ate_m == pytest.approx(ml.ate_m, abs=2e-3)
