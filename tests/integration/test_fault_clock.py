"""Reboots are events and output times stay on the input's clock (issue 12, items 2 and 4): a reboot in
the motors-off calibration never mixes two boots into one calibration; one corrupt timestamp shifts
nothing after it."""

from __future__ import annotations

import itertools
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from magcomp.adapters.config import Config
from magcomp.adapters.state_store import StateStore
from magcomp.core.identity import SIM_UID
from magcomp.service.replay import replay_log
from tests.conftest import split_tlog_records
from tests.faultgen import record_time_s, retime


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> tuple[Any, list[bytes], float, Path]:
    from magcomp.adapters.mavlink_emit import default_start_unix_s, write_tlog
    from magcomp.sim import SimConfig, simulate

    result = simulate(SimConfig(scenario="paper", duration_s=60.0, seed=3, n_compasses=1))
    d = tmp_path_factory.mktemp("clock")
    write_tlog(result, d / "clean.tlog")
    return result, split_tlog_records((d / "clean.tlog").read_bytes()), default_start_unix_s(result), d


def heading_times_ms(path: Path) -> list[int]:
    from magcomp.adapters.dialect import ensure_dialect

    mav = ensure_dialect().MAVLink(None)
    out = []
    for rec in split_tlog_records(path.read_bytes()):
        m = mav.decode(bytearray(rec[8:]))
        if m.get_type() == "MAGCOMP_HEADING":
            out.append(int(m.time_boot_ms))
    return out


@pytest.mark.parametrize("t_reboot", [13.0, 25.0])
def test_reboot_in_the_calibration_window_never_mixes_two_boots(
    flight: tuple[Any, list[bytes], float, Path], tmp_path: Path, t_reboot: float
) -> None:
    result, recs, u0, d = flight
    clean = replay_log(d / "clean.tlog", Config())
    # the autopilot reboots t_reboot s into the log: its clock restarts at 0.3 s
    rebooted = retime(recs, lambda i, old: old - (result.t0_s + t_reboot) + 0.3
                      if record_time_s(recs[i]) - u0 >= t_reboot else old)  # fmt: skip
    path = tmp_path / "reboot.tlog"
    path.write_bytes(b"".join(rebooted))
    rep = replay_log(path, Config(), store=StateStore(tmp_path / "state"), emit=tmp_path / "out.tlog")
    assert rep.summary["counts"]["reboots"] == 1
    assert any("rebooted" in w for w in rep.summary["warnings"])
    cal = rep.summary["compasses"][0]["calibration"]
    ref = clean.summary["compasses"][0]["calibration"]
    # learned from one boot only: as good as the clean log's (37.6 vs 8.5 before); a calibration learned in
    # flight afterwards (the hand rotation cut short) is another estimator, not compared here
    if cal is not None and cal["source"] == "learned":
        assert cal["residual_rms_mgauss"] < 1.3 * ref["residual_rms_mgauss"]
        theta = np.asarray(rep.summary["compasses"][0]["theta_mgauss"])
        truth = np.asarray(result.compasses[0].theta_mgauss)
        assert np.linalg.norm(theta - truth) < 0.25 * np.linalg.norm(truth)
    else:  # too little of the hand rotation left on either side of the reboot: nothing stored
        stored = StateStore(tmp_path / "state").load(1, 0, SIM_UID)
        assert stored is None or stored.calib_l is None
    # MAGCOMP_HEADING.time_boot_ms is the autopilot's clock: after the reboot it restarts too
    times = heading_times_ms(tmp_path / "out.tlog")
    assert max(times) < (result.t0_s + 61.0 - t_reboot) * 1000.0
    assert sum(b < a - 5000 for a, b in itertools.pairwise(times)) == 1  # the restart, once


def test_one_corrupt_timestamp_shifts_nothing_after_it(
    flight: tuple[Any, list[bytes], float, Path], tmp_path: Path
) -> None:
    _result, recs, _u0, d = flight
    clean = replay_log(d / "clean.tlog", Config(), emit=tmp_path / "clean_out.tlog")
    k = len(recs) // 2
    bad = retime(recs, lambda i, old: old + 1e6 if i == k else old)
    (tmp_path / "bad.tlog").write_bytes(b"".join(bad))
    rep = replay_log(tmp_path / "bad.tlog", Config(), emit=tmp_path / "bad_out.tlog")
    assert rep.summary["counts"]["reboots"] == 0
    t_clean = heading_times_ms(tmp_path / "clean_out.tlog")
    t_bad = heading_times_ms(tmp_path / "bad_out.tlog")
    assert max(t_bad) == max(t_clean)  # was ~1e9 ms for every later heading
    assert len(t_clean) - len(t_bad) <= 1 and set(t_bad) <= set(t_clean)
    np.testing.assert_allclose(rep.summary["compasses"][0]["theta_mgauss"],
                               clean.summary["compasses"][0]["theta_mgauss"], atol=1.0)  # fmt: skip


def test_a_rotation_short_of_min_samples_is_fitted_when_its_pairs_carry_the_information(
    flight: tuple[Any, list[bytes], float, Path], tmp_path: Path
) -> None:
    """Issue 25, case 10 of the hostile corpus: a hand rotation with fewer pairs than ``[calibration]
    min_samples`` (here the whole 833-pair rotation against min_samples 900; there 492 pairs left by damaged
    blocks against 500) is fitted when the motors start if its pairs determine the calibration (field error
    dilution 0.22 <= 1), as the reboot test above still refuses the two parts of a rotation split at 13 s
    (2.5 and 3.5)."""
    result, _, _, d = flight
    cfg = Config()
    short = replace(cfg, calibration=replace(cfg.calibration, min_samples=900))
    rep = replay_log(d / "clean.tlog", short)
    cal = rep.summary["compasses"][0]["calibration"]
    assert cal is not None and cal["source"] == "learned" and cal["n"] < 900, cal
    theta = np.asarray(rep.summary["compasses"][0]["theta_mgauss"])
    truth = np.asarray(result.compasses[0].theta_mgauss)
    assert np.linalg.norm(theta - truth) < 0.25 * np.linalg.norm(truth)
