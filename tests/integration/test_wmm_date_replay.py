"""A replay takes the WMM at the log's own date (issue 23, item 7): a simulated 2016 flight whose first
GPS_RAW_INT fix (time since boot: no date) comes before its SYSTEM_TIME."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters.config import Config
from magcomp.geomag import earth_field_ned_mgauss
from magcomp.service.replay import replay_log


def test_replay_of_a_2016_log_takes_the_wmm_in_2016(tmp_path: Path) -> None:
    import datetime as dt

    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate

    result = simulate(SimConfig(scenario="ordinary", duration_s=20.0, seed=2))
    path = tmp_path / "f2016.tlog"
    boot = dt.datetime(2016, 7, 2, tzinfo=dt.UTC)  # the simulator's field is 2025's: only the date is 2016
    write_tlog(result, path, start_unix_s=boot.timestamp())
    year = 2016.5
    assert Config().location.decimal_year == 2025.5
    ef = replay_log(path, Config(), two_pass=False).summary["earth_field"]
    assert ef["decimal_year"] == pytest.approx(year, abs=2.0 / 365.0)  # before: the configured 2025.5
    assert ef["source"] == "gps" and ef["date_source"] == "log"
    want = earth_field_ned_mgauss(ef["lat_deg"], ef["lon_deg"], ef["alt_m"], ef["decimal_year"])
    np.testing.assert_allclose(ef["ned_mgauss"], want, atol=1e-6)
