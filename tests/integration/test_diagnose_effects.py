"""Hide an effect in a simulated log, require `diagnose` to find it.

simulate -> tlog -> load_log -> diagnose.

Every log is generated fresh by the simulator with a seeded random effect parameter drawn from a physical
range; nothing here is a stored answer. The oracle is the simulator's truth: the effect name, its parameter
and the magnetometer noise it added.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from magcomp.adapters.mavlink_emit import write_tlog
from magcomp.adapters.mavlink_source import load_log
from magcomp.diagnosis.engine import diagnose
from magcomp.sim import SimConfig, simulate

THETA_PAPER = (-61.0, 26.4, -1.2)  # Table II, mgauss
THETA_STRONG = tuple(3.0 * v for v in THETA_PAPER)  # a compass close to the battery leads of a quad
THETA_QUAD = tuple(2.0 * v for v in THETA_PAPER)

# effect -> (scenario, vehicle, duration s, theta, parameter range, fitted parameter name, tolerance)
CASES: dict[str, tuple[str, str, float, tuple[float, ...], tuple[float, float], str, float | None]] = {
    "throttle_offset": ("bench", "fixedwing", 50.0, THETA_PAPER, (0.1, 0.3), "offset", 0.03),
    "throttle_exponent": ("bench", "fixedwing", 50.0, THETA_PAPER, (2.6, 3.4), "exponent", 0.25),
    "current_lag": ("paper", "fixedwing", 50.0, THETA_PAPER, (0.2, 1.0), "tau_s", 0.30),  # relative
    "time_skew": ("paper", "fixedwing", 50.0, THETA_PAPER, (0.1, 0.4), "skew_s", 0.04),
    "voltage_sag": ("bench", "multirotor", 50.0, THETA_STRONG, (0.6, 1.0), "sag", None),
    "temperature_drift": ("paper", "fixedwing", 50.0, THETA_PAPER, (2.0, 4.0), "mgauss_per_degc", None),
    "per_motor": ("paper", "multirotor", 50.0, THETA_QUAD, (1.0, 2.0), "spread", 0.4),  # relative
}


def _run(
    tmp_path: Path,
    scenario: str,
    vehicle: str,
    duration: float,
    theta: tuple[float, ...],
    effects: dict[str, float],
    seed: int,
) -> tuple[dict[str, Any], Any]:
    cfg = SimConfig(
        scenario=scenario,
        duration_s=duration,
        seed=seed,
        effects=effects,
        vehicle=vehicle,
        n_compasses=1,
        theta_mgauss=(theta[0], theta[1], theta[2]),
    )
    res = simulate(cfg)
    path = tmp_path / f"{scenario}.tlog"
    write_tlog(res, path)
    log = load_log(path)
    d = diagnose(log, heading_reference=(res.t_s, res.euler_rad[:, 2]))
    return d.to_json(), res


@pytest.mark.parametrize("effect", list(CASES))
def test_hidden_effect_is_named_strongest_and_recovered(tmp_path: Path, effect: str) -> None:
    scenario, vehicle, duration, theta, (lo, hi), param, tol = CASES[effect]
    seed = 100 + list(CASES).index(effect)
    value = float(np.random.default_rng(seed).uniform(lo, hi))
    out, res = _run(tmp_path, scenario, vehicle, duration, theta, {effect: value}, seed)
    noise = res.compasses[0].noise_mgauss
    assert out["findings"], f"{effect}={value:.3f} not found; rejected: {out['compasses'][0]['rejected']}"
    top = out["findings"][0]
    # partly collinear causes (offset / exponent / sag, lag / skew) are reported as a set when the data cannot
    # tell them apart; the hidden one must then be in the set, with its own fitted parameter
    names = top.get("candidates", [top["effect"]])
    assert effect in names, f"strongest finding {top['effect']} instead of {effect}={value:.3f}"
    params = top["candidate_params"][effect] if "candidates" in top else top["params"]
    fitted = params[param]
    if effect == "per_motor":  # against the spread the seed drew (its VALUE only scales random offsets)
        theta_i = np.asarray(res.effect_params["per_motor_theta_mgauss"][0], dtype=float)
        theta_true = theta_i.mean(axis=0)
        value = float(np.mean(np.linalg.norm(theta_i - theta_true, axis=1)) / np.linalg.norm(theta_true))
    ci = params.get(f"{param}_ci95")
    if ci is not None:  # the interval (profile likelihood; the spread's Neyman one) covers the truth
        assert ci[0] <= value <= ci[1], (ci, value)
    assert tol is not None or effect not in ("current_lag", "per_motor")
    if effect in ("current_lag", "per_motor"):
        assert tol is not None
        assert abs(fitted - value) <= tol * value, (fitted, value)
    elif tol is not None:
        assert abs(fitted - value) <= tol, (fitted, value)
    # the extended model leaves the sensor's own noise (per axis), within 10 %
    assert out["residual_rms_extended"] <= 1.1 * noise, (out["residual_rms_extended"], noise)
    assert out["residual_rms_extended"] < out["residual_rms_baseline"]


def test_clean_log_gives_no_finding_and_theta_eq11(tmp_path: Path) -> None:
    out, res = _run(tmp_path, "paper", "fixedwing", 50.0, THETA_PAPER, {}, 7)
    assert out["findings"] == []
    c = out["compasses"][0]
    # theta in the compass (raw) frame is K theta of the truth, eq. (1) applied to eq. (11)
    np.testing.assert_allclose(c["theta"], res.compasses[0].theta_raw_mgauss, atol=4.0)
    assert out["residual_rms_baseline"] <= 1.1 * res.compasses[0].noise_mgauss


def test_two_hidden_effects_are_both_found(tmp_path: Path) -> None:
    out, _ = _run(
        tmp_path, "paper", "fixedwing", 50.0, THETA_PAPER, {"current_lag": 0.6, "temperature_drift": 3.0}, 11
    )
    names = [f["effect"] for f in out["findings"]]
    assert set(names) == {"current_lag", "temperature_drift"}, names
    lag = next(f for f in out["findings"] if f["effect"] == "current_lag")
    assert abs(lag["params"]["tau_s"] - 0.6) <= 0.18


def test_extended_model_reduces_heading_error_against_truth(tmp_path: Path) -> None:
    out, _ = _run(tmp_path, "paper", "fixedwing", 50.0, THETA_PAPER, {"time_skew": 0.3}, 13)
    g = out["gain"]
    assert g["heading_reference"] == "truth"
    assert g["heading_error_rms_deg"]["extended"] < g["heading_error_rms_deg"]["paper"]
    assert g["heading_error_rms_deg"]["paper"] < g["heading_error_rms_deg"]["uncompensated"]
