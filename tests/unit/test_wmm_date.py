"""The WMM is taken at the log's date (issue 23, item 7): a date that comes after the first fix, a GPS record
that has the date but no fix yet, and a log without any fix (the configured place at the log's date)."""

from __future__ import annotations

import numpy as np
import pytest

from magcomp.adapters.config import Config
from magcomp.core.types import PositionSample, TimeSample
from magcomp.geomag import earth_field_ned_mgauss
from magcomp.service.pipeline import Pipeline

LAT, LON, ALT = 52.1712, 4.4105, 10.0
YEAR = 2016.6  # the log's date; the configuration's default is 2025.5


def _field(p: Pipeline) -> tuple[dict[str, object], np.ndarray]:
    ef = p.summary()["earth_field"]
    assert isinstance(ef, dict)
    return ef, np.asarray(ef["ned_mgauss"], dtype=float)


def test_a_date_after_the_first_fix_re_takes_the_field() -> None:
    """SYSTEM_TIME after the first GPS_RAW_INT fix (whose time_usec is time since boot: no date)."""
    p = Pipeline(Config())
    p.feed(PositionSample(1.0, LAT, LON, ALT))
    assert Config().location.decimal_year == 2025.5
    p.feed(TimeSample(1.2, YEAR))
    ef, ned = _field(p)
    assert ef["source"] == "gps" and ef["decimal_year"] == pytest.approx(YEAR)
    assert ef["date_source"] == "log"
    np.testing.assert_allclose(ned, earth_field_ned_mgauss(LAT, LON, ALT, YEAR), atol=1e-9)
    # the 2025.5 field differs by much more than the test's tolerance (secular change over 9 years)
    assert np.linalg.norm(ned - earth_field_ned_mgauss(LAT, LON, ALT, 2025.5)) > 5.0


def test_a_gps_record_without_a_fix_still_gives_the_date() -> None:
    """DataFlash: POS (no date) fixes the place first; a GPS record with its week and time but no 3D fix."""
    p = Pipeline(Config())
    p.feed(PositionSample(1.0, LAT, LON, ALT))  # POS
    p.feed(PositionSample(1.1, 0.0, 0.0, 0.0, decimal_year=YEAR, fix_ok=False))
    ef, ned = _field(p)
    assert ef["decimal_year"] == pytest.approx(YEAR)
    np.testing.assert_allclose(ned, earth_field_ned_mgauss(LAT, LON, ALT, YEAR), atol=1e-9)


def test_no_fix_at_all_the_configured_place_at_the_log_date() -> None:
    cfg = Config()
    p = Pipeline(cfg)
    p.feed(TimeSample(0.5, YEAR))
    ef, ned = _field(p)
    loc = cfg.location
    assert ef["source"] == "config" and ef["decimal_year"] == pytest.approx(YEAR)
    want = earth_field_ned_mgauss(loc.lat_deg, loc.lon_deg, loc.alt_m, YEAR)
    np.testing.assert_allclose(ned, want, atol=1e-9)


def test_no_date_keeps_the_configured_date_and_a_close_one_changes_nothing() -> None:
    p = Pipeline(Config())
    p.feed(PositionSample(1.0, LAT, LON, ALT))
    ef, _ = _field(p)
    assert ef["decimal_year"] == 2025.5 and ef["date_source"] == "config"
    p.feed(TimeSample(1.2, 2025.45))  # within RETAKE_YEARS: the field stays
    ef, ned = _field(p)
    assert ef["decimal_year"] == 2025.5 and ef["date_source"] == "log"
    np.testing.assert_allclose(ned, earth_field_ned_mgauss(LAT, LON, ALT, 2025.5), atol=1e-9)
