"""Issue 9, honest output on short ordinary flights (~90 s flying, the autopilot's yaw from the disturbed
compass): the reported heading sigma must cover what the in-flight estimate adds to the oracle's error.

Before the split-half check (docs/inflight.md "Short flights") the estimate's sigma was the white-noise
one (too few 30 s batches for the variance inflation): seed 33's compass 1 claimed 0.34 deg while its
heading was 1.55 deg (rms, in quadrature) beyond the oracle's, 4.5 sigmas."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from magcomp.service.demo import oracle_replay, rms_after_learning
from magcomp.service.replay import replay_log
from tests.configs import ESTIMATOR_ONLY

#: a reported 1-sigma that the error beyond the oracle exceeds threefold is a false claim (a Gaussian
#: error does so 0.3 % of the time)
MAX_SIGMAS = 3.0


@pytest.mark.slow
@pytest.mark.parametrize("seed", [30, 31, 32, 33])
def test_short_flight_heading_sigma_covers_the_error_beyond_the_oracle(tmp_path: Path, seed: int) -> None:
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate
    from magcomp.sim.config import apply_settings

    result = simulate(apply_settings(SimConfig(scenario="ordinary", seed=seed, duration_s=150.0),
                                     ["telemetry_hz=10"]))  # fmt: skip
    path = tmp_path / "short.tlog"
    write_tlog(result, path)
    cfg = ESTIMATOR_ONLY
    two = replay_log(path, cfg, keep_estimates=True, two_pass=True)
    orc = oracle_replay(result, path, tmp_path / "oracle", cfg)
    for j in range(len(result.compasses)):
        comp = two.summary["compasses"][j]
        if comp["status"] != "corrected":  # honestly not corrected: the why says so
            assert comp["why"], comp
            continue
        inf = comp["inflight"]
        sigma = float(inf["heading_sigma_deg"])
        assert inf["heading_split_deg"] is not None and inf["heading_split_deg"] > 0.0
        corrected, _ = rms_after_learning(result, two.estimates, j, 0.0)
        oracle, _ = rms_after_learning(result, orc.estimates, j, 0.0)
        beyond = math.sqrt(max(corrected**2 - oracle**2, 0.0))
        assert beyond <= MAX_SIGMAS * sigma, (j, corrected, oracle, sigma)
