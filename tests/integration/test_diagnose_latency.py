"""The compass's latency against the attitude (a compass held inside a faster RAW_IMU), fitted and removed.

A 20 Hz compass logged in a 40 Hz RAW_IMU from a 50 Hz loop is held: each logged sample is on average
21.8 ms older than its time stamp (the simulator's hold, :func:`magcomp.sim.simulate._hold_index`). Before the
re-timing that staleness was the cause of both held-out misses (``benchmarks/diagnosis_heldout.py``): it
biased the temperature coefficient and gave per-motor vectors on logs without a per-motor effect. Here the
same flight (same seed, so the same trajectory and noise) is logged with and without the hold; the fitted
latencies must differ by the hold's mean staleness. The tolerance, 3 ms, is about three times the spread of
that difference over seeds 3000-3003 (21.2-21.5 ms against 21.8).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters.mavlink_emit import _rate_indices, write_tlog
from magcomp.adapters.mavlink_source import load_log
from magcomp.core.types import LogData
from magcomp.diagnosis.engine import diagnose
from magcomp.diagnosis.gate import EarthReference
from magcomp.diagnosis.inputs import compass_data
from magcomp.diagnosis.latency import MIN_HELD_FRACTION, compass_latency_s, held_fraction
from magcomp.sim import SimConfig, simulate
from magcomp.sim.config import apply_settings
from magcomp.sim.simulate import SimResult, _hold_index

SETTINGS: dict[str, object] = {"raw_imu_hz": 40, "attitude_hz": 20, "lat_deg": 60.2, "lon_deg": 24.9}


def _log(tmp_path: Path, name: str, settings: dict[str, object]) -> tuple[LogData, SimConfig, SimResult]:
    cfg = SimConfig(scenario="paper", duration_s=60.0, seed=3001, vehicle="multirotor", n_compasses=1)
    cfg = apply_settings(cfg, settings)
    res = simulate(cfg)
    path = tmp_path / f"{name}.tlog"
    write_tlog(res, path)
    return load_log(path), cfg, res


def _latency_s(log: LogData) -> float:
    plain = compass_data(log, 0)
    lat, data = compass_latency_s(plain, lambda s: compass_data(log, 0, latency_s=s))
    np.testing.assert_array_equal(data.t_s, plain.t_s)  # the drive stays at the logged times
    np.testing.assert_array_equal(data.drive.throttle_grid, plain.drive.throttle_grid)
    return lat


@pytest.mark.slow
def test_fitted_latency_is_the_hold_of_a_slow_compass(tmp_path: Path) -> None:
    held, cfg, res = _log(tmp_path, "held", {**SETTINGS, "mag_hz": 20})
    fresh, _, _ = _log(tmp_path, "fresh", SETTINGS)
    r = cfg.rates
    n = res.samples.t_s.size
    hold = _hold_index(n, r.imu_hz, r.mag_rate)
    rows = np.asarray(_rate_indices(n, r.imu_hz, r.raw_imu_rate))  # the loop rows RAW_IMU carries
    staleness_s = float(np.mean((rows - hold[rows]) / r.imu_hz))
    assert 0.015 < staleness_s < 0.03  # the hold is what the test is about: about 22 ms here
    diff = _latency_s(held) - _latency_s(fresh)
    assert diff == pytest.approx(staleness_s, abs=0.003)
    # the hold is seen in the data: every other sample repeats (20 Hz in 40 Hz), none without it
    assert held_fraction(held.mag[0].values) == pytest.approx(0.5, abs=0.05)
    assert held_fraction(fresh.mag[0].values) < MIN_HELD_FRACTION / 2
    # the diagnosis re-times the held log and says so; not the other
    earth = EarthReference(res.earth_field_ned_mgauss, "simulated place")
    assert any("attitude re-timed" in s for s in diagnose(held, earth=earth).notes)
    assert not any("attitude re-timed" in s for s in diagnose(fresh, earth=earth).notes)
