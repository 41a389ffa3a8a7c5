"""State that survives: a replay learns calibration and theta and stores them per vehicle and compass;
a later run on a log without any hand rotation starts calibrated and corrected; a damaged state file
gives a warning and a fresh start."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters.state_store import StateStore
from magcomp.core.identity import SIM_UID
from magcomp.core.types import FLAG_CALIBRATED
from magcomp.service.demo import heading_errors
from magcomp.service.replay import replay_log
from tests.configs import QUICK_CALIBRATION
from tests.faultgen import record_msgid, record_time_s


@pytest.fixture(scope="module")
def logs(
    tmp_path_factory: pytest.TempPathFactory, split_tlog: Callable[[bytes], list[bytes]]
) -> tuple[Path, Path, object]:
    from magcomp.adapters.mavlink_emit import default_start_unix_s, write_tlog
    from magcomp.sim import SimConfig, simulate

    d = tmp_path_factory.mktemp("state")
    result = simulate(SimConfig(scenario="paper", duration_s=40.0, seed=7))
    whole = d / "whole.tlog"
    write_tlog(result, whole)
    # the part after the spin: pan, ramp and step only (no hand rotation to calibrate from)
    m = result.motion
    pan_start = result.t0_s + m.t_s[np.flatnonzero(np.array(m.segment_names)[m.segment] == "pan")[0]] - 0.5
    t_unix0 = default_start_unix_s(result)
    recs = split_tlog(whole.read_bytes())
    tail = d / "tail.tlog"
    # (and the AUTOPILOT_VERSION naming the board, as the autopilot answers a ground station at connect)
    tail.write_bytes(
        b"".join(r for r in recs if record_time_s(r) - t_unix0 >= pan_start or record_msgid(r) == 148)
    )
    return whole, tail, result


def test_state_survives_restart_and_corrects_from_the_first_sample(
    logs: tuple[Path, Path, object], tmp_path: Path
) -> None:
    whole, tail, result = logs
    first = replay_log(whole, QUICK_CALIBRATION, store=StateStore(tmp_path))
    assert {c["calibration"]["source"] for c in first.summary["compasses"]} == {"learned"}
    stored = StateStore(tmp_path).load(1, 0, SIM_UID)
    assert stored is not None and stored.calib_l is not None
    np.testing.assert_allclose(stored.theta_mgauss, first.summary["compasses"][0]["theta_mgauss"])

    again = replay_log(tail, QUICK_CALIBRATION, store=StateStore(tmp_path), keep_estimates=True)
    assert {c["calibration"]["source"] for c in again.summary["compasses"]} == {"stored"}
    assert again.estimates[0].flags & FLAG_CALIBRATED
    np.testing.assert_allclose(again.estimates[0].theta_mgauss, stored.theta_mgauss)
    errs = {s.name: s for s in heading_errors(result, again.estimates)}
    assert errs["pan"].max_corrected_deg * 2.0 < errs["pan"].max_raw_deg

    # no state and no hand rotation in the tail: whatever calibration there is was learned in flight
    fresh = replay_log(tail, QUICK_CALIBRATION, keep_estimates=True)
    for c in fresh.summary["compasses"]:
        assert c["calibration"] is None or c["calibration"]["source"] == "in-flight"
        assert (c["status"] == "corrected") == (c["calibration"] is not None)


def test_damaged_state_warns_and_starts_fresh(logs: tuple[Path, Path, object], tmp_path: Path) -> None:
    _, tail, _ = logs
    store = StateStore(tmp_path)
    bad = '{"format": "magcomp-state", "version": 1, "sha256": "00", "state": {}}'
    store.path_for(1, 0, SIM_UID).write_text(bad)
    rep = replay_log(tail, QUICK_CALIBRATION, store=store, keep_estimates=True)
    assert any("damaged" in w and f"vehicle-1-{SIM_UID}-compass-0" in w for w in rep.summary["warnings"])
    assert rep.n_estimates > 0
    assert StateStore(tmp_path).load(1, 0, SIM_UID) is not None  # rewritten, readable again
