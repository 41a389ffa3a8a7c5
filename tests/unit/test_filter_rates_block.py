"""The two-pass replay's second pass takes the heading filters' rates a block at a time from the sample log's
gyro columns (service/heading.py ``filter_rates_block``): the same numbers, bit for bit, as the live stage's
``filter_rates`` of each sample."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.typing import NDArray

from magcomp.core.heading_filter import STEEP_COS_TILT
from magcomp.core.selfcheck import MOTORS_RUNNING_01
from magcomp.service.heading import (
    MIN_COS_PITCH,
    STILL_RATE_RAD_S,
    bias_trusted,
    filter_rates,
    filter_rates_block,
)
from magcomp.service.record import MagRecord, Tilt


def _records(n: int, seed: int) -> list[MagRecord]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        rec = MagRecord(None, float(i), 0, (200.0, 10.0, 400.0), None, False, False, 0.0, False, 0)  # type: ignore[arg-type]
        roll, pitch = rng.uniform(-1.4, 1.4), rng.uniform(-1.55, 1.55)  # past MIN_COS_PITCH and 30 deg
        rec.tilt = Tilt(math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch))
        scale = STILL_RATE_RAD_S * (0.3 if i % 3 == 0 else 3.0)  # at rest and moving
        g = rng.normal(0.0, scale, 3)
        rec.gyro_raw = (float(g[0]), float(g[1]), float(g[2]))
        b = rng.normal(0.0, 0.01, 3)
        rec.gyro = (float(g[0] - b[0]), float(g[1] - b[1]), float(g[2] - b[2]))
        rec.down = None if i % 7 == 0 else (0.0, 0.0, 1.0)
        rec.have_throttle = i % 5 != 0
        rec.throttle_01 = float(rng.choice([0.0, MOTORS_RUNNING_01, 0.5]))
        out.append(rec)
    return out


def _block(recs: list[MagRecord]) -> NDArray[np.float64]:
    """filter_rates_block of the records' columns: (yaw rate, turn rate, bias) per record, (n, 3)."""
    col = lambda f: np.array([f(r) for r in recs], dtype=float)  # noqa: E731
    rate, turn, bias = filter_rates_block(
        (col(lambda r: r.gyro_raw[0]), col(lambda r: r.gyro_raw[1]), col(lambda r: r.gyro_raw[2])),
        (col(lambda r: r.gyro[1]), col(lambda r: r.gyro[2])),
        (col(lambda r: r.tilt[0]), col(lambda r: r.tilt[1]), col(lambda r: r.tilt[2])),
        np.array([r.down is not None for r in recs]),
        np.array([r.have_throttle for r in recs]),
        col(lambda r: r.throttle_01),
    )
    return np.column_stack((rate, turn, bias))


def test_filter_rates_block_equals_the_live_rates_bit_for_bit() -> None:
    recs = _records(3000, 0)
    want = np.array([filter_rates(r) for r in recs])
    got = _block(recs)
    # every case is there: no yaw rate (steep pitch), a turn rate (beyond 30 deg), a trusted bias
    assert np.isnan(want[:, 0]).any() and (np.abs(np.array([r.tilt[2] for r in recs])) < MIN_COS_PITCH).any()
    assert (want[:, 1] > 0.0).any() and (want[:, 1] == 0.0).any()
    assert np.isfinite(want[:, 2]).sum() > 50 and np.isnan(want[:, 2]).sum() > 50
    assert np.array_equal(got, want, equal_nan=True)


def test_filter_rates_at_the_exact_thresholds() -> None:
    """On the thresholds themselves: cos(tilt) == STEEP_COS_TILT is not beyond 30 deg (no turn rate), and
    |cos(pitch)| == MIN_COS_PITCH still has a yaw rate; one ulp further each flips. Live and block agree."""
    steep_in = math.nextafter(STEEP_COS_TILT, 0.0)
    pitch_out = math.nextafter(MIN_COS_PITCH, 0.0)
    # (cos roll, sin roll, cos pitch): cos(tilt) = cos roll x cos pitch, exact with cos roll = 1
    tilts = [(1.0, 0.0, STEEP_COS_TILT), (1.0, 0.0, steep_in), (1.0, 0.0, MIN_COS_PITCH),
             (1.0, 0.0, -MIN_COS_PITCH), (1.0, 0.0, pitch_out), (1.0, 0.0, -pitch_out)]  # fmt: skip
    recs = _records(len(tilts), 1)
    for rec, (cr, sr, cp) in zip(recs, tilts, strict=True):
        rec.tilt = Tilt(cr, sr, cp, math.sqrt(1.0 - cp * cp))
        rec.gyro_raw = (0.3, -0.2, 0.4)  # moving: a turn rate wherever the tilt is steep
    live = np.array([filter_rates(r) for r in recs])
    assert np.array_equal(_block(recs), live, equal_nan=True)
    norm = float(np.linalg.norm(recs[0].gyro_raw))
    assert live[0, 1] == 0.0  # exactly 30 deg: not beyond it
    assert live[1, 1] == pytest.approx(norm, rel=1e-12)  # one ulp beyond
    for k in (2, 3):  # |cos(pitch)| exactly at the limit: defined, r / cos(pitch) with roll 0
        assert live[k, 0] == pytest.approx(0.4 / tilts[k][2], rel=1e-12)
    assert np.isnan(live[4:, 0]).all()  # one ulp inside the limit: undefined


def test_bias_trusted_rule_per_sample_and_per_block() -> None:
    """The attitude filter's bias is trusted only settled, motors off, at rest; the same for floats and
    arrays, including a throttle exactly at MOTORS_RUNNING_01 (not running) and a rate exactly at rest."""
    still, moving = (STILL_RATE_RAD_S, 0.0, 0.0), (math.nextafter(STILL_RATE_RAD_S, 1.0), 0.0, 0.0)
    cases = [
        (True, False, 0.9, still, True),  # no throttle known: motors taken as off
        (True, True, MOTORS_RUNNING_01, still, True),  # at the threshold: not running
        (True, True, math.nextafter(MOTORS_RUNNING_01, 1.0), still, False),
        (True, True, 0.0, moving, False),
        (False, True, 0.0, still, False),  # not settled
    ]
    for settled, have, thr, g, want in cases:
        assert bias_trusted(settled, have, thr, g) is want
    cols = list(zip(*cases, strict=True))
    gx, gy, gz = (np.array([g[k] for g in cols[3]]) for k in range(3))
    got = bias_trusted(np.array(cols[0]), np.array(cols[1]), np.array(cols[2]), (gx, gy, gz))
    assert np.array_equal(got, np.array(cols[4]))
