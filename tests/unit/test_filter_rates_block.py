"""The two-pass replay's second pass takes the heading filters' rates a block at a time from the sample log's
gyro columns (service/heading.py ``filter_rates_block``): the same numbers, bit for bit, as the live stage's
``filter_rates`` of each sample."""

from __future__ import annotations

import math

import numpy as np

from magcomp.core.selfcheck import MOTORS_RUNNING_01
from magcomp.service.heading import MIN_COS_PITCH, STILL_RATE_RAD_S, filter_rates, filter_rates_block
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


def test_filter_rates_block_equals_the_live_rates_bit_for_bit() -> None:
    recs = _records(3000, 0)
    col = lambda f: np.array([f(r) for r in recs], dtype=float)  # noqa: E731
    rate, turn, bias = filter_rates_block(
        (col(lambda r: r.gyro_raw[0]), col(lambda r: r.gyro_raw[1]), col(lambda r: r.gyro_raw[2])),
        (col(lambda r: r.gyro[1]), col(lambda r: r.gyro[2])),
        (col(lambda r: r.tilt[0]), col(lambda r: r.tilt[1]), col(lambda r: r.tilt[2])),
        np.array([r.down is not None for r in recs]),
        np.array([r.have_throttle for r in recs]),
        col(lambda r: r.throttle_01),
    )
    want = np.array([filter_rates(r) for r in recs])
    got = np.column_stack((rate, turn, bias))
    # every case is there: no yaw rate (steep pitch), a turn rate (beyond 30 deg), a trusted bias
    assert np.isnan(want[:, 0]).any() and (np.abs(np.array([r.tilt[2] for r in recs])) < MIN_COS_PITCH).any()
    assert (want[:, 1] > 0.0).any() and (want[:, 1] == 0.0).any()
    assert np.isfinite(want[:, 2]).sum() > 50 and np.isnan(want[:, 2]).sum() > 50
    assert np.array_equal(got, want, equal_nan=True)
