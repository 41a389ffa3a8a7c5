"""A held compass (updated slower than its message, each value repeated until the next update) measured
each sample before its logged time: the drive signals and the rotation are taken at each sample's
measurement time (magcomp/diagnosis/inputs.py, measured_times_s), so the hold's age does not end up in a
fitted delay, nor its spread over the samples in the forward model's rotation.

Oracle: the hold built here (each update measured halfway between the sample that first shows it and the
one before, as an update at a uniform time between two messages is on average), and the simulator's hidden
lag for the held-out case.
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from magcomp.core.types import Series
from magcomp.diagnosis.inputs import compass_data, measured_times_s
from tests.unit.test_diagnosis_model import LAST_R, synth_log


def test_measured_times_of_a_hold() -> None:
    t = 0.02 * np.arange(10, dtype=np.float64)
    v = np.repeat(np.arange(4.0, dtype=np.float64), [1, 3, 3, 3])[:, None] * np.ones((1, 3))
    got = measured_times_s(t, v)
    # runs start at samples 0, 1, 4, 7: measured halfway to the sample before (the first: at itself)
    np.testing.assert_allclose(got, [0.0, 0.01, 0.01, 0.01, 0.07, 0.07, 0.07, 0.13, 0.13, 0.13])
    unheld = np.arange(30.0, dtype=np.float64).reshape(10, 3)
    want = np.concatenate([[0.0], t[1:] - 0.01])
    np.testing.assert_allclose(measured_times_s(t, unheld), want)


def test_a_value_repeated_longer_than_any_compass_period_is_not_a_hold() -> None:
    """4 Hz telemetry of a compass whose reading does not change (a still vehicle): a compass is read at
    10 Hz or faster, so a value repeated 0.25 s later was read again, not held: each sample at its own time
    (before the bound: 0.125-0.625 s before it). A 50 Hz hold of 3 samples is unchanged by the bound."""
    t = 0.25 * np.arange(8, dtype=np.float64)
    v = np.repeat(np.array([1.0, 2.0, 2.0, 2.0, 3.0, 3.0, 3.0, 3.0])[:, None], 3, axis=1)
    np.testing.assert_allclose(measured_times_s(t, v), t)
    fast = 0.02 * np.arange(7, dtype=np.float64)
    w = np.repeat(np.array([1.0, 2.0, 2.0, 2.0, 3.0, 3.0, 3.0])[:, None], 3, axis=1)
    np.testing.assert_allclose(measured_times_s(fast, w), [0.0, 0.01, 0.01, 0.01, 0.07, 0.07, 0.07])


def _held(field: np.ndarray, every: int) -> np.ndarray:
    """Each update (every ``every`` samples) measured halfway between its first sample and the one before,
    then held."""
    out = np.empty_like(field)
    for u in range(0, field.shape[0], every):
        out[u : u + every] = field[u] if u == 0 else 0.5 * (field[u - 1] + field[u])
    return out


def test_the_drive_of_a_held_compass_is_taken_when_it_measured() -> None:
    """The throttle column of a compass held 4 samples (12.5 Hz in 50 Hz) is evaluated at the updates'
    measurement times; an unheld compass's at its logged times."""
    log, _, _ = synth_log(3)
    m = log.mag[0]
    d0 = compass_data(log, 0)
    np.testing.assert_allclose(d0.drive.t_s, d0.t_s)
    held = replace(log, mag={0: Series(m.t_s, _held(np.asarray(m.values, dtype=float), 4))})
    d = compass_data(held, 0)
    age = d.t_s - d.drive.t_s
    np.testing.assert_allclose(age.mean(), 0.04, atol=0.002)
    # ages 10, 30, 50, 70 ms after the first update (measured at the log's first sample: 0, 20, 40, 60)
    assert set(np.round(age[4:] * 1e3).astype(int).tolist()) == {10, 30, 50, 70}


def test_the_rotation_of_a_held_compass_is_taken_when_it_measured() -> None:
    """The forward model's rotation at a held sample is the vehicle's at that sample's measurement time.

    Oracle: the synthetic log's true rotation (4x the IMU rate), its down vector at each update's
    measurement time (halfway between the update's first sample and the one before, as _held measures). The
    hold (4 samples at 50 Hz) makes the samples 10-70 ms old at ~1 rad/s: taken at the logged times (before)
    the down vector is 43 mrad rms off; at the measurement times only the tilt filter's own error is left
    (0.2 mrad). The tolerance, 5 mrad (2.5 mgauss on a 500 mgauss field), is 8x below the hold's error and
    25x above the filter's."""
    log, _, _ = synth_log(3)
    r_true = LAST_R[0].copy()
    m = log.mag[0]
    held = replace(log, mag={0: Series(m.t_s, _held(np.asarray(m.values, dtype=float), 4))})
    d = compass_data(held, 0)
    n = m.t_s.size
    first = (np.arange(n) // 4) * 4  # the sample where each held value first appears
    down = r_true[:, 2, :]
    before = down[np.maximum(first - 1, 0)]
    at_meas = np.where((first == 0)[:, None], down[first], 0.5 * (before + down[first]))
    at_meas /= np.linalg.norm(at_meas, axis=1, keepdims=True)
    k = np.searchsorted(m.t_s, d.t_s)
    err = np.arccos(np.clip(np.sum(d.r_nb[:, 2, :] * at_meas[k], axis=1), -1.0, 1.0))
    assert float(np.sqrt(np.mean(err**2))) < 0.005
    # the log does rotate: at the logged times the same rotation is far off (the hold's age matters)
    late = np.arccos(np.clip(np.sum(d.r_nb[:, 2, :] * down[k], axis=1), -1.0, 1.0))
    assert float(np.sqrt(np.mean(late**2))) > 0.02


@pytest.mark.slow
def test_held_out_lag_with_a_held_compass_is_inside_its_interval() -> None:
    """The held-out current_lag case (a 20 Hz compass held in a 40 Hz RAW_IMU, lag 0.3 s), seeds 5000-5003:
    the true lag inside every 95 % interval (before: 0.380 [0.308, 0.459] and 0.392 [0.313, 0.478] on
    5000 and 5002, both missing it)."""
    sys.path.insert(0, str(Path(__file__).parents[2] / "benchmarks"))
    from diagnosis_heldout import run_case

    for seed in range(5000, 5004):
        r = run_case("current_lag", seed, None)
        assert r["is_top"], r["findings"]
        lo, hi = r["params"]["tau_s_ci95"]
        assert lo <= 0.3 <= hi, (seed, r["params"])
