"""Held-out conditions: a hidden effect in a log simulated with settings the other diagnosis tests never use.

``test_diagnose_effects.py`` hides each effect in the simulator's default rates (50 Hz), white compass noise
and default autopilot. Here the compass runs at 75 Hz inside a 100 Hz RAW_IMU, its noise is coloured (a
random walk, or AR(1) with an 8 s correlation time), the quantisation, the autopilot's filter gains, the
attitude noise and the place on Earth differ (the same cases as the benchmark). The diagnosis must still
name the effect first and bracket the simulated value with its 95 % interval (all seven effects:
``benchmarks/diagnosis_heldout.py``).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, cast

import numpy as np
import pytest

from magcomp.adapters.mavlink_emit import write_tlog
from magcomp.adapters.mavlink_source import load_log
from magcomp.diagnosis.effects import EFFECTS
from magcomp.diagnosis.engine import diagnose
from magcomp.diagnosis.gate import EarthReference
from magcomp.sim import SimConfig, simulate
from magcomp.sim.config import apply_settings

# effect -> (scenario, vehicle, VALUE, seed, held-out settings)
CASES: dict[str, tuple[str, str, float, int, dict[str, object]]] = {
    "throttle_exponent": (
        "bench",
        "fixedwing",
        3.0,
        102,
        {
            "mag_hz": 75,
            "raw_imu_hz": 100,
            "attitude_hz": 25,
            "mag_rw_mgauss_per_sqrt_s": 0.3,
            "mag_lsb_mgauss": 3,
            "ap_kp_tilt": 3,
            "att_noise_deg": 0.3,
            "lat_deg": 64.1,
            "lon_deg": -21.9,
        },
    ),
    "time_skew": (
        "paper",
        "fixedwing",
        0.15,
        104,
        {
            "mag_hz": 75,
            "raw_imu_hz": 100,
            "mag_ar1_sigma_mgauss": 3,
            "mag_ar1_tau_s": 8,
            "ap_kp_yaw": 1.5,
            "mag_noise_scale": 0.5,
            "lat_deg": -45.9,
            "lon_deg": 170.5,
        },
    ),
}


@pytest.mark.slow
@pytest.mark.parametrize("effect", list(CASES))
def test_heldout_effect_is_top_finding_inside_its_interval(tmp_path: Path, effect: str) -> None:
    scenario, vehicle, value, seed, settings = CASES[effect]
    cfg = SimConfig(
        scenario=scenario, duration_s=60.0, seed=seed, effects={effect: value}, vehicle=vehicle, n_compasses=1
    )
    res = simulate(apply_settings(cfg, dict(settings)))
    path = tmp_path / "heldout.tlog"
    write_tlog(res, path)
    earth = EarthReference(res.earth_field_ned_mgauss, "simulated place")
    c = diagnose(load_log(path), earth=earth).to_json()["compasses"][0]
    assert c["observable"], c["unobservable_why"]
    assert c["findings"], f"no finding; rejected: {c['rejected']}"
    top = c["findings"][0]
    names = top.get("candidates", [top["effect"]])
    assert effect in names, f"top finding {top['effect']}, not {effect}"
    params = top["params"] if top["effect"] == effect else top["candidate_params"][effect]
    param = EFFECTS[effect].param
    assert param is not None
    lo, hi = params[f"{param}_ci95"]
    assert lo <= value <= hi, f"{param} {params[param]} [{lo}, {hi}] does not bracket {value}"



def _heldout_case(
    tmp_path: Path, effect: str, seed: int | None = None, value: float | None = None
) -> tuple[Any, dict[str, Any], float]:
    """The held-out benchmark's case for ``effect`` (its own seed and value unless given): the simulation,
    diagnose's JSON of its one compass and the effect's simulated value."""
    sys.path.insert(0, str(Path(__file__).parents[2] / "benchmarks"))
    from diagnosis_heldout import CASES as HELD_OUT  # the benchmark's case, one definition

    scenario, vehicle, duration_s, case_value, case_seed, settings = HELD_OUT[effect]
    value = case_value if value is None else value
    cfg = SimConfig(
        scenario=scenario,
        duration_s=duration_s,
        seed=case_seed if seed is None else seed,
        effects={effect: value},
        vehicle=vehicle,
        n_compasses=1,
    )
    res = simulate(apply_settings(cfg, settings))
    path = tmp_path / "heldout.tlog"
    write_tlog(res, path)
    earth = EarthReference(res.earth_field_ned_mgauss, "simulated place")
    return res, diagnose(load_log(path), earth=earth).to_json()["compasses"][0], float(value)

@pytest.mark.slow
def test_heldout_per_motor_spread_interval_brackets_the_drawn_spread(tmp_path: Path) -> None:
    """The benchmark's per-motor case (60 s quad, compass 20 Hz held in 40 Hz RAW_IMU, AR(1) noise, the
    autopilot's calibration): the spread the seed drew, in the logged field's frame, lies inside the
    reported 95 % interval, and the reported spread is below the plain mean of norms (noise bias removed,
    :mod:`magcomp.diagnosis.spread`)."""
    res, c, _ = _heldout_case(tmp_path, "per_motor")
    assert c["findings"] and c["findings"][0]["effect"] == "per_motor", c["rejected"]
    params = c["findings"][0]["params"]
    l_matrix, _ = res.true_calibration(0)
    drawn = np.array(cast(list[list[list[float]]], res.effect_params["per_motor_theta_mgauss"])[0])
    theta_i = np.linalg.solve(l_matrix, drawn.T).T
    theta = theta_i.mean(axis=0)
    truth = float(np.mean(np.linalg.norm(theta_i - theta, axis=1)) / np.linalg.norm(theta))
    lo, hi = params["spread_ci95"]
    assert lo <= truth <= hi, (params["spread"], lo, hi, truth)
    assert params["spread"] < params["spread_raw"]


@pytest.mark.slow
def test_heldout_sag_named_in_a_set_with_the_exponent_it_cannot_be_told_from(tmp_path: Path) -> None:
    """The sag case at 0.8 (the benchmark's until 2026-11-28) on seed 5018: the throttle exponent passes on
    its own (effective delta BIC -56), the sag only just misses the margin (-25), and the two fits differ
    directly by 7.7-10.9 effective BIC depending on whose residual is taken as the noise. The data do not tell
    them apart, so the finding is the set, with the sag's interval bracketing the simulated 0.8 (before: the
    exponent alone)."""
    _, c, value = _heldout_case(tmp_path, "voltage_sag", seed=5018, value=0.8)
    assert c["findings"], c["rejected"]
    top = c["findings"][0]
    assert set(top.get("candidates", [top["effect"]])) == {"throttle_exponent", "voltage_sag"}, top
    sag = top["candidate_params"]["voltage_sag"]
    lo, hi = sag["sag_ci95"]
    assert lo <= value <= hi, sag
    assert "reported as a set" in c["rejected"]["voltage_sag"]["why"]
