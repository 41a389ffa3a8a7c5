"""The measured third-party logs in ../shared/data/measured read into physically sensible samples."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters.mavlink_source import load_log, open_source
from magcomp.core.types import MagSample, ThrottleSample

MEASURED = Path(__file__).parents[2].parent / "shared" / "data" / "measured"
BIN = MEASURED / "dronekit_log171_copter33_quad.bin"
TEXT = MEASURED / "ardupilot_loganalyzer_nan_copter311.log"
ULOG = MEASURED / "pyulog_sample_px4_disarmed.ulg"

pytestmark = pytest.mark.needs_shared


def _need(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"measured log {path.name} not available (expected in {MEASURED})")
    return path


@pytest.fixture(scope="module")
def log171() -> object:
    return load_log(_need(BIN))


def test_dataflash_bin_has_three_compasses_with_earth_field_magnitudes(log171: object) -> None:
    data = log171
    assert sorted(data.mag) == [0, 1, 2]  # type: ignore[attr-defined]
    for index, series in data.mag.items():  # type: ignore[attr-defined]
        assert len(series) >= 2380
        flying = series.t_s < 225.0  # before the crash (SOURCES.md)
        norm = np.linalg.norm(series.values[flying], axis=1)
        median = float(np.median(norm))
        assert 450.0 < median < 800.0, (index, median)
        assert np.all(np.diff(series.t_s) >= 0)
        assert 240.0 < series.t_s[-1] - series.t_s[0] < 245.0  # 242.6 s of log


def test_dataflash_bin_current_voltage_throttle_ranges(log171: object) -> None:
    data = log171
    assert data.vehicle_type == 2 and data.throttle_source == "motors:1,2,3,4"  # type: ignore[attr-defined]
    cur = data.current_a.values  # type: ignore[attr-defined]
    volt = data.voltage_v.values  # type: ignore[attr-defined]
    assert 0.3 < cur.min() < 1.0 and 25.0 < cur.max() < 30.0
    assert volt.min() > 14.5 and volt.max() < 17.0
    thr = data.throttle_01.values  # type: ignore[attr-defined]
    assert thr.min() == 0.0 and 0.6 < thr.max() < 0.7
    assert data.motors_01.values.shape[1] == 4  # type: ignore[attr-defined]
    # throttle and current move together in this log (SOURCES.md)
    t_c = data.current_a.t_s  # type: ignore[attr-defined]
    thr_at_c = np.interp(t_c, data.throttle_01.t_s, thr)  # type: ignore[attr-defined]
    assert np.corrcoef(thr_at_c, cur)[0, 1] > 0.8


def test_dataflash_bin_imu_gravity_and_attitude_in_radians(log171: object) -> None:
    data = log171
    still = data.imu_t_s < 50.0  # type: ignore[attr-defined]
    g = np.linalg.norm(data.accel_m_s2[still], axis=1)  # type: ignore[attr-defined]
    assert np.median(g) == pytest.approx(9.81, abs=0.3)
    assert np.median(np.abs(data.gyro_rad_s[still])) < 0.02  # type: ignore[attr-defined]
    att = data.attitude_rad.values[data.attitude_rad.t_s < 225.0]  # type: ignore[attr-defined]
    assert np.radians(30.0) < np.abs(att[:, :2]).max() < np.radians(50.0)  # +-46 deg in flight (SOURCES.md)
    assert att[:, 2].min() >= 0.0 and att[:, 2].max() <= 2 * np.pi
    assert data.params["FRAME"] == 1.0  # type: ignore[attr-defined]
    assert 15.0 < np.median(data.temperature_degc.values) < 60.0  # type: ignore[attr-defined]


def test_dataflash_text_log_reads_into_the_same_samples() -> None:
    data = load_log(_need(TEXT))
    assert sorted(data.mag) == [0, 1] and data.vehicle_type == 2
    norm = np.linalg.norm(data.mag[1].values, axis=1)
    assert 300.0 < np.median(norm) < 700.0
    assert np.nanmin(data.current_a.values) > 0.3 and np.nanmax(data.current_a.values) < 10.0
    assert 14.0 < np.nanmin(data.voltage_v.values) < 16.0
    assert data.throttle_01.values.min() >= 0.0 and data.throttle_01.values.max() < 0.6
    assert len(data.attitude_rad) > 100 and data.imu_t_s.size > 600


def test_streaming_a_dataflash_log_matches_load_log(log171: object) -> None:
    with open_source(_need(BIN), mag_index=2) as src:
        mags = thr = 0
        for s in src.samples():
            if isinstance(s, MagSample):
                assert s.mag_index == 2
                mags += 1
            elif isinstance(s, ThrottleSample):
                thr += 1
    assert mags == len(log171.mag[2])  # type: ignore[attr-defined]
    assert thr == len(log171.throttle_01)  # type: ignore[attr-defined]


def test_ulog_control_case_reads_magnetometer_in_mgauss() -> None:
    pytest.importorskip("pyulog")
    data = load_log(_need(ULOG))
    norm = np.linalg.norm(data.mag[0].values, axis=1)
    assert 400.0 < np.median(norm) < 600.0  # ~0.48 gauss
    assert data.throttle_01.values.max() == 0.0  # disarmed throughout
