"""Does theta repeat, and does the gate say when its interval is a lower bound? (issue 10)

simulate -> tlog -> load_log -> diagnose, seeded. The oracle is the simulator's truth and what was added to
the log here (a field offset on the motors-off samples); nothing is a stored answer.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from magcomp.adapters.mavlink_emit import write_tlog
from magcomp.adapters.mavlink_source import load_log
from magcomp.core.types import Series
from magcomp.diagnosis.engine import diagnose
from magcomp.sim import SimConfig, simulate
from magcomp.sim.config import Rates

THETA = (-122.0, 52.8, -2.4)  # 2x Table II, mgauss


def _log(tmp_path: Path, cfg: SimConfig) -> Any:
    path = tmp_path / f"s{cfg.seed}.tlog"
    write_tlog(simulate(cfg), path)
    return load_log(path)


def _compass(log: Any) -> dict[str, Any]:
    c: dict[str, Any] = diagnose(log).to_json()["compasses"][0]
    assert c["observable"], c["unobservable_why"]
    return c


def test_motors_off_offset_is_measured_and_theta_without_it_stays(tmp_path: Path) -> None:
    """A field offset present only while the motors are off (a different field on the ground, an idle
    current that starts at arming) pulls eq. (11)'s theta, which leans on the motors-off samples for its
    zero; the consistency check measures the offset and gives theta with it free."""
    cfg = SimConfig(
        scenario="flight", duration_s=90.0, seed=313, vehicle="fixedwing", n_compasses=1, theta_mgauss=THETA
    )
    log = _log(tmp_path, cfg)
    clean = _compass(log)
    s = log.mag[0]
    off = np.interp(s.t_s, log.throttle_01.t_s, log.throttle_01.values) <= 0.05
    assert 0.05 < float(np.mean(off)) < 0.95
    added = np.array([0.0, 0.0, -40.0])
    shifted = _compass(replace(log, mag={0: Series(s.t_s, s.values + np.outer(off, added))}))
    g0, g1 = clean["gate"], shifted["gate"]
    d_off = np.subtract(g1["theta_motors_off_offset_mgauss"], g0["theta_motors_off_offset_mgauss"])
    np.testing.assert_allclose(d_off, added, atol=2.0)  # the added offset, measured
    assert g1["theta_motors_off_ratio"] > 1.0 and not g1["theta_consistent"]
    # theta with the offset free does not move; the plain theta moves along z beyond its own interval
    np.testing.assert_allclose(g1["theta_motors_off_free"], g0["theta_motors_off_free"], atol=2.0)
    dz = abs(shifted["theta"][2] - clean["theta"][2])
    assert dz > clean["theta_ci95_halfwidth"][2], (dz, clean["theta_ci95_halfwidth"])


def _same_compass(log: Any, res: Any, ref: Any) -> Any:
    """``log`` (simulated by ``res``) with its raw readings mapped into ``ref``'s simulated compass (K, b of
    eq. (1)): the simulator draws a compass per seed, a vehicle keeps its compass between flights."""
    k_own, b_own = res.compasses[0].k_matrix, res.compasses[0].b_mgauss
    k_ref, b_ref = ref.compasses[0].k_matrix, ref.compasses[0].b_mgauss
    s = log.mag[0]
    v = (s.values.astype(float) - b_own) @ (k_ref @ np.linalg.inv(k_own)).T + b_ref
    return replace(log, mag={0: Series(s.t_s, v)})


def _flight(tmp_path: Path, cfg: SimConfig) -> tuple[Any, Any]:
    res = simulate(cfg)
    path = tmp_path / f"s{cfg.seed}.tlog"
    write_tlog(res, path)
    return load_log(path), res


def test_two_flights_of_one_vehicle_give_the_same_theta(tmp_path: Path) -> None:
    """Same vehicle (theta, place, compass), two flights with other seeds, rates and paths: theta's direction
    and size repeat, the two 95 % intervals overlap on every axis and each holds the simulated theta (in the
    logged frame, K theta). benchmarks/diagnosis_flight_pairs.py measures the overlap rate over varied
    pairs."""
    slow = Rates(imu_hz=100.0, attitude_hz=25.0, servo_hz=25.0, power_hz=5.0, rc_hz=10.0, vfr_hud_hz=10.0)
    log_a, res_a = _flight(
        tmp_path, SimConfig(scenario="paper", duration_s=60.0, seed=321, n_compasses=1, theta_mgauss=THETA)
    )
    log_b, res_b = _flight(
        tmp_path,
        SimConfig(scenario="paper", duration_s=80.0, seed=322, n_compasses=1, theta_mgauss=THETA, rates=slow),
    )
    a, b = _compass(log_a), _compass(_same_compass(log_b, res_b, res_a))
    ta, tb = np.array(a["theta"]), np.array(b["theta"])
    ha, hb = np.array(a["theta_ci95_halfwidth"]), np.array(b["theta_ci95_halfwidth"])
    cos = float(ta @ tb) / float(np.linalg.norm(ta) * np.linalg.norm(tb))
    assert cos > 0.99, (ta, tb)
    assert float(np.linalg.norm(ta - tb)) < 0.2 * float(np.linalg.norm(ta)), (ta, tb)
    # the intervals overlap on every axis (the block jackknife covers the between-manoeuvre model error)
    assert np.all(np.abs(ta - tb) <= ha + hb), (ta, ha, tb, hb)
    truth = res_a.compasses[0].k_matrix @ np.array(THETA)
    for c, th, hw in ((a, ta, ha), (b, tb, hb)):
        assert np.all(np.abs(th - truth) <= hw), (th, hw, truth)
        # and they do not cover it by being huge: within 15 % of |theta| per axis
        assert np.all(hw < 0.15 * float(np.linalg.norm(truth))), hw
        assert c["gate"]["theta_identifiable"]
        assert c["gate"]["theta_model_error_bound_mgauss"] < float(np.linalg.norm(c["theta"]))
