"""`magcomp fit` on a freshly simulated bench log: theta in the compass frame (K theta) within error bars."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from magcomp.adapters.mavlink_emit import write_tlog
from magcomp.cli import main
from magcomp.sim import SimConfig, simulate


def test_fit_recovers_simulated_theta_raw_and_noise_eq14(tmp_path: Path) -> None:
    result = simulate(SimConfig(scenario="bench", seed=23, n_compasses=1))
    log = tmp_path / "bench.tlog"
    write_tlog(result, log)
    out = tmp_path / "fit.json"
    assert main(["fit", str(log), "--json", str(out)]) == 0
    fit = json.loads(out.read_text())
    # the whole stationary run is used: the autopilot's compass-fused yaw swings with throttle on the bench,
    # which must not split the window (core.segments)
    assert fit["t_end_s"] - fit["t_start_s"] > 0.9 * (result.t_s[-1] - result.t_s[0]) - 2.0, fit
    comp = result.compasses[0]
    theta_raw = np.asarray(comp.theta_raw_mgauss)
    theta = np.asarray(fit["theta"])
    std = np.asarray(fit["theta_std"])
    assert np.all(np.abs(theta - theta_raw) < 4.0 * std + 0.5), (theta, theta_raw, std)
    # sigma-hat of eq. (15) estimates the simulated sensor noise (plus quantisation)
    assert np.all(np.abs(np.asarray(fit["sigma"]) / comp.noise_mgauss - 1.0) < 0.2), fit["sigma"]
    for r2, (mean, two_sd) in zip(fit["r2"], fit["benchmark_r2"], strict=True):
        assert mean - 1.5 * two_sd - 0.01 <= r2 <= mean + 1.5 * two_sd + 0.01
