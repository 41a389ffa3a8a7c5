"""The age of an unheld compass's samples: its bounds, and a skew or lag that cannot be told from it.

Oracle: the rule's definitions (``latency.unheld_age_bounds_s``, ``search.within_compass_age``) on a seeded
synthetic log (50 Hz compass, logged every 20 ms), and a clean held-out bench log at drawn rates (seed 6001:
a compass updated at 24.7 Hz in a 25 Hz RAW_IMU, about 30 ms old on average, on a vehicle that does not
rotate, so its age cannot be fitted) on which a time skew of 41 ms [1, 65] was named before the rule (the
skew is flat in the data there: 31 ms on an install of numpy 2.4.6 and scipy 1.17.1, 41 ms when this test
was written).
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from magcomp.diagnosis.engine import compass_data
from magcomp.diagnosis.latency import MAX_LATENCY_S, unheld_age_bounds_s
from magcomp.diagnosis.search import within_compass_age
from tests.unit.test_diagnosis_model import synth_log


def test_age_bounds_are_one_compass_period() -> None:
    t = 3.0 + np.arange(200) / 25.0  # logged at 25 Hz
    assert unheld_age_bounds_s(t) == pytest.approx((0.0, 0.05))  # 1.25 messages of 40 ms
    assert unheld_age_bounds_s(np.arange(50) / 4.0) == (0.0, MAX_LATENCY_S)  # 4 Hz: a compass reads >= 10 Hz
    assert unheld_age_bounds_s(np.zeros(1)) == (0.0, 0.0)


@pytest.mark.parametrize(
    ("effect", "ci", "refused"),
    [
        ("time_skew", (0.001, 0.065), True),  # reaches into 0-25 ms
        ("time_skew", (0.02, 0.2), True),
        ("time_skew", (0.13, 0.19), False),  # above any age of a 50 Hz compass
        ("time_skew", (-0.2, -0.05), False),  # the field leads the throttle: no age does that
        ("current_lag", (0.005, 0.089), True),
        ("current_lag", (0.23, 0.4), False),
        ("throttle_offset", (0.0, 0.01), False),  # not a timing effect
    ],
)
def test_timing_effect_within_the_compass_age(effect: str, ci: tuple[float, float], refused: bool) -> None:
    log, _, _ = synth_log(3)
    fitted = compass_data(log, 0)
    assert fitted.attitude_source.startswith("gyro")  # the age is fitted against the gyro's rotation
    assert within_compass_age(effect, fitted, ci) is None
    data = replace(fitted, attitude_source="autopilot")  # an age no rotation can measure
    assert np.array_equal(data.drive.t_s, data.t_s)  # unheld, no age fitted: the drive at the logged times
    why = within_compass_age(effect, data, ci)
    assert (why is not None) == refused, why
    # once the ages are known (read from a hold or fitted), the drive is taken at them: no refusal
    aged = replace(data, drive=replace(data.drive, t_s=data.t_s - 0.01))
    assert within_compass_age(effect, aged, ci) is None


@pytest.mark.slow
def test_clean_bench_log_at_drawn_rates_names_no_timing_effect() -> None:
    sys.path.insert(0, str(Path(__file__).parents[2] / "benchmarks"))
    from diagnosis_heldout import drawn_rates, simulate_case

    from magcomp.diagnosis.engine import diagnose
    from magcomp.diagnosis.gate import EarthReference

    rates = drawn_rates(6001)
    assert rates == {"raw_imu_hz": 25.0, "mag_hz": 24.7, "attitude_hz": 25.0}
    res, log = simulate_case("voltage_sag", 6001, 0.0, None, rates)  # the sag case with the sag off
    c = diagnose(log, earth=EarthReference(res.earth_field_ned_mgauss, "simulated place")).compasses[0]
    assert c.data.attitude_source == "stationary"
    assert not c.findings, [f.label for f in c.findings]
    # refused for what the log's timing cannot resolve: the compass's unknown age, or, where the fit lands
    # below it (31 ms on numpy 2.4.6 / scipy 1.17.1), the throttle's sampling interval
    why = str(c.rejected.get("time_skew", {}).get("why"))
    assert "age of the compass's own samples" in why or "below the throttle's sampling interval" in why, why
