"""SERVO_OUTPUT_RAW all zeros (outputs disabled) is no throttle information, with a warning; not
throttle 0 with theta stuck at 0 and no word said (issue 12, item 8)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from magcomp.adapters.config import Config
from magcomp.core.types import FLAG_NO_THROTTLE, FLAG_THETA_CONVERGED
from magcomp.service.replay import replay_log
from tests.conftest import split_tlog_records
from tests.faultgen import rewrite


def test_servo_outputs_all_zero_are_no_throttle_information(tmp_path: Path) -> None:
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate

    result = simulate(SimConfig(scenario="paper", duration_s=40.0, seed=5, n_compasses=1))
    write_tlog(result, tmp_path / "c.tlog")
    recs = split_tlog_records((tmp_path / "c.tlog").read_bytes())
    zeros = rewrite(recs, "SERVO_OUTPUT_RAW", **{f"servo{i}_raw": 0 for i in range(1, 17)})
    (tmp_path / "z.tlog").write_bytes(b"".join(zeros))
    cfg = Config()
    rep = replay_log(tmp_path / "z.tlog", cfg, keep_estimates=True)
    warnings = [w for w in rep.summary["warnings"] if "throttle" in w]
    assert len(warnings) == 1 and "\n" not in warnings[0]
    ests = rep.estimates
    late = ests[len(ests) // 10 :]
    assert all(e.flags & FLAG_NO_THROTTLE for e in late)
    assert not any(e.flags & FLAG_THETA_CONVERGED for e in late)
    assert all(e.throttle_01 == 0.0 and not np.any(e.bias_mgauss) for e in late)
    # the same log with its outputs intact: throttle known, no such warning
    clean = replay_log(tmp_path / "c.tlog", cfg)
    assert not [w for w in clean.summary["warnings"] if "throttle" in w]
