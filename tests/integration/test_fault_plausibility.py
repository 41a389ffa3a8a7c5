"""Issue 25 (6): plausibility gates shared by all commands. An attitude no vehicle can have (roll 50 rad,
pitch 7 rad: a garbage ATTITUDE) was tilt-compensated into every heading until the next one (up to 12 deg
off, unflagged, uncounted); it is now dropped and counted in replay, fit and diagnose alike."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters.config import Config
from magcomp.core.types import LogData, Series
from magcomp.service.align import gate_log_inputs
from magcomp.service.replay import replay_log
from tests.faultgen import rewrite_some


@pytest.mark.slow
@pytest.mark.parametrize("fields", [{"roll": 50.0, "pitch": 7.0}, {"roll": 1e30, "pitch": -1e30}])
def test_impossible_attitudes_change_no_heading(
    tmp_path: Path, split_tlog: Callable[[bytes], list[bytes]], fields: dict[str, float]
) -> None:
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate

    clean = tmp_path / "clean.tlog"
    write_tlog(simulate(SimConfig(scenario="paper", duration_s=40.0, seed=5, n_compasses=1)), clean)
    records = split_tlog(clean.read_bytes())
    n_att = sum(1 for r in records if r[8 + 7 : 8 + 10] == b"\x1e\x00\x00")  # message id 30: ATTITUDE
    hits = set(range(n_att // 4, n_att, n_att // 20))  # ~15 ATTITUDE messages in the flight
    damaged = tmp_path / "damaged.tlog"
    damaged.write_bytes(b"".join(rewrite_some(records, "ATTITUDE", lambda k: k in hits, **fields)))
    ref = {e.t_s: e.heading_deg for e in replay_log(clean, Config(), keep_estimates=True).estimates}
    rep = replay_log(damaged, Config(), keep_estimates=True)
    assert rep.counts["implausible"] == len(hits)
    assert len(rep.estimates) == len(ref)
    diff = [abs((e.heading_deg - ref[e.t_s] + 180.0) % 360.0 - 180.0) for e in rep.estimates]
    # a dropped attitude holds the previous one for one update: a fraction of a degree at most
    assert max(diff) < 1.0, max(diff)


def test_the_column_gates_drop_what_the_pipeline_drops() -> None:
    t = np.arange(10, dtype=np.float64)
    mag = np.tile([200.0, -50.0, 400.0], (10, 1))
    mag[3] = [8000.0, 0.0, 0.0]  # at the default saturation
    mag[6] = [200.0 + 600.0, -50.0, 400.0]  # a jump: it and the sample after it go
    att = np.zeros((10, 3))
    att[2] = [0.1, 3.0, 0.0]  # pitch beyond 90 deg
    log = LogData(source="x", mag={0: Series(t, mag)}, attitude_rad=Series(t, att))
    dropped = gate_log_inputs(log, Config().input.saturation_mgauss)
    assert dropped == {"saturated": 1, "mag_jumps": 2, "implausible": 1}
    assert log.mag[0].t_s.tolist() == [0, 1, 2, 4, 5, 8, 9]
    assert 2 not in log.attitude_rad.t_s.tolist()
