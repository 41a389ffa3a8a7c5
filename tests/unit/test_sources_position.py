"""Position and UTC date from every source: GPS_RAW_INT, GLOBAL_POSITION_INT, SYSTEM_TIME, DataFlash GPS."""

from __future__ import annotations

import math
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters.gnss_time import decimal_year_from_gps, decimal_year_from_unix
from magcomp.adapters.mavlink_source import load_log, open_source
from magcomp.core.types import PositionSample, TimeSample
from tests.unit.test_sources import TlogWriter

MEASURED = Path(__file__).parents[2].parent / "shared" / "data" / "measured"


def test_decimal_year_from_unix_and_gps_week_agree() -> None:
    when = datetime(2024, 7, 2, 12, 0, tzinfo=UTC)  # 2024 is a leap year: day 183.5 of 366
    assert decimal_year_from_unix(when.timestamp()) == pytest.approx(2024 + 183.5 / 366, abs=1e-9)
    # GPS week 2321 began on 2024-06-30 (Sunday); + 2.5 days = 2024-07-02 12:00 (leap seconds ignored)
    assert decimal_year_from_gps(2321, 2.5 * 86400e3) == pytest.approx(2024 + 183.5 / 366, abs=1e-6)
    for unset in (0.0, 315964800.0, math.nan, 1e12):  # 1970, 1980 (GPS epoch), NaN, year ~33000
        assert math.isnan(decimal_year_from_unix(unset))
    assert math.isnan(decimal_year_from_gps(0, 1000.0))


def _gps_log(tmp_path: Path) -> Path:
    rng = np.random.default_rng(3)
    w = TlogWriter()
    w.heartbeat()
    unix_us = int(datetime(2025, 3, 1, tzinfo=UTC).timestamp() * 1e6)
    lat0, lon0 = 29.6516, -82.3248
    for k in range(20):
        t_ms = 1000 + 200 * k
        w.raw_imu(t_ms * 1000, (0, 0, -1000), (0, 0, 0), (200, 0, 400))
        fix = 1 if k < 5 else 3  # no fix for the first second
        lat = lat0 + 1e-5 * rng.standard_normal()
        w.add("GPS_RAW_INT", time_usec=t_ms * 1000, fix_type=fix, lat=int(lat * 1e7), lon=int(lon0 * 1e7),
              alt=45_000, eph=100, epv=100, vel=0, cog=0, satellites_visible=10)  # fmt: skip
        w.add("GLOBAL_POSITION_INT", time_boot_ms=t_ms, lat=int(lat0 * 1e7), lon=int(lon0 * 1e7), alt=46_000,
              relative_alt=0, vx=0, vy=0, vz=0, hdg=0)  # fmt: skip
        w.add("SYSTEM_TIME", time_unix_usec=0 if k < 3 else unix_us + t_ms * 1000, time_boot_ms=t_ms)
    return w.write(tmp_path / "gps.tlog")


def test_mavlink_gps_global_position_and_system_time(tmp_path: Path) -> None:
    path = _gps_log(tmp_path)
    with open_source(path) as src:
        samples = list(src.samples())
    pos = [s for s in samples if isinstance(s, PositionSample)]
    times = [s for s in samples if isinstance(s, TimeSample)]
    assert len(pos) == 40
    assert sum(not p.fix_ok for p in pos) == 5  # GPS_RAW_INT fix_type 1
    assert all(abs(p.lat_deg - 29.6516) < 1e-3 and abs(p.lon_deg + 82.3248) < 1e-6 for p in pos)
    assert {round(p.alt_m) for p in pos} == {45, 46}  # mm -> m
    assert len(times) == 17  # time_unix_usec 0 is "not set"
    assert all(2025.16 < t.decimal_year < 2025.17 for t in times)  # 1 March 2025 = day 59 of 365
    data = load_log(path)
    assert len(data.position) == 15  # the receiver's 3D fixes win over the estimator's position
    assert np.all(np.abs(data.position.values[:, 2] - 45.0) < 1e-6)
    assert 2025.16 < data.decimal_year < 2025.17


def test_dataflash_gps_of_log171_is_plausible() -> None:
    path = MEASURED / "dronekit_log171_copter33_quad.bin"
    if not path.exists():
        pytest.skip(f"measured log {path.name} not available (expected in {MEASURED})")
    data = load_log(path)
    assert len(data.position) > 100
    lat, lon, alt = data.position.values.T
    assert np.all(np.abs(lat) <= 90) and np.all(np.abs(lon) <= 180)
    # one flight: the positions stay within a few km and a few hundred m of altitude of each other
    assert np.ptp(lat) < 0.05 and np.ptp(lon) < 0.05 and np.ptp(alt) < 500
    assert 2015.0 < data.decimal_year < 2017.0  # ArduCopter 3.3 was current in 2015-2016
