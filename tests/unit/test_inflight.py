"""In-flight calibration jointly with theta (magcomp.core.inflight, magcomp.service.inflight_stage).

Seeded synthetic flights: random attitudes (yaw turns, +-25 deg tilt), a throttle that varies, noise of a few
mgauss; the estimators must find the truth within tolerances that a wrong model fails.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from magcomp.adapters.config import InflightConfig
from magcomp.core.autopilot_params import calibrated_by_autopilot, yaw_reference
from magcomp.core.inflight import (
    InflightEstimator,
    InflightParams,
    absolute_rows,
    regressors,
    relative_rows,
)
from magcomp.core.rotations import dcm_from_euler, quat_integrate_body_rate, quat_step_body_rate
from magcomp.service.inflight_stage import InflightStage

H_NED = np.array([230.0, 50.0, -530.0])  # Canberra-like field, mgauss
THETA = np.array([-60.0, 25.0, 40.0])  # body frame, mgauss at full throttle


def _flight(n: int, seed: int, throttle_varies: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R_nb (n,3,3), throttle (n,), yaw) of a smooth flight: several full yaw turns, tilt within 25 deg."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.1
    yaw = 0.35 * t + 0.4 * np.sin(0.05 * t)
    roll = np.radians(20.0) * np.sin(0.31 * t + rng.uniform(0, 6))
    pitch = np.radians(15.0) * np.sin(0.23 * t + rng.uniform(0, 6))
    thr = 0.5 + (0.25 * np.sin(0.07 * t) + 0.05 * np.sin(1.3 * t) if throttle_varies else 0.0 * t)
    r = np.array([dcm_from_euler(a, b, c) for a, b, c in zip(roll, pitch, yaw, strict=True)])
    return r, thr, yaw


def _measure(
    r: np.ndarray, thr: np.ndarray, a_mat: np.ndarray, d: np.ndarray, seed: int, noise: float
) -> np.ndarray:
    """y = A R^T h + d + A theta throttle^2 + noise (theta in the calibrated frame, as reported)."""
    rng = np.random.default_rng(seed + 100)
    u = np.einsum("nji,j->ni", r, H_NED) + np.outer(thr**2, THETA)
    return u @ a_mat.T + d + rng.normal(0.0, noise, (len(thr), 3))


def _heading_rms_deg(field_b: np.ndarray, truth_b: np.ndarray, r: np.ndarray) -> float:
    """rms (deg) of the tilt-compensated heading of ``field_b`` against that of ``truth_b``."""
    from magcomp.core.heading import tilt_compensated_heading_deg
    from magcomp.core.rotations import euler_from_dcms

    e = euler_from_dcms(r)
    h1 = tilt_compensated_heading_deg(field_b, e[:, 0], e[:, 1])
    h0 = tilt_compensated_heading_deg(truth_b, e[:, 0], e[:, 1])
    return float(np.sqrt(np.mean(((h1 - h0 + 180.0) % 360.0 - 180.0) ** 2)))


A_TRUE = np.array([[1.03, 0.02, -0.01], [0.02, 0.97, 0.015], [-0.01, 0.015, 1.01]])
D_TRUE = np.array([25.0, -40.0, 15.0])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_absolute_form_recovers_calibration_and_theta(seed: int) -> None:
    r, thr, _ = _flight(3000, seed)
    y = _measure(r, thr, A_TRUE, D_TRUE, seed, noise=3.0)
    est = InflightEstimator("absolute", 0, InflightParams(sigma_a=0.1), float(np.linalg.norm(H_NED)))
    for k in range(len(thr)):
        rows, z = absolute_rows(r[k].T @ H_NED, y[k], regressors(float(thr[k]), None))
        est.add(rows, z, float(thr[k] ** 2))
    sol = est.solve()
    assert np.linalg.norm(sol.theta_mgauss - THETA) < 0.03 * np.linalg.norm(THETA)
    l_true = np.linalg.inv(A_TRUE)
    assert np.allclose(sol.calib_l, l_true, atol=0.01)
    assert np.allclose(sol.calib_d, l_true @ D_TRUE, atol=3.0)
    # the covariance is honest: the error is within 4 sigma per axis
    assert np.all(np.abs(sol.theta_mgauss - THETA) < 4.0 * sol.theta_sigma_mgauss + 0.5)
    assert sol.heading_sigma_deg < 1.0


@pytest.mark.parametrize("seed", [0, 1])
def test_relative_form_recovers_hard_iron_and_theta_without_the_yaw(seed: int) -> None:
    """Only rotations between samples are used: a yaw reference that follows the bias cannot fool it."""
    r, thr, _ = _flight(3000, seed)
    y = _measure(r, thr, np.eye(3), D_TRUE, seed, noise=2.0)
    est = InflightEstimator("relative", 0, InflightParams(), float(np.linalg.norm(H_NED)))
    for k in range(1, len(thr)):
        q = r[k].T @ r[k - 1]
        x0, x1 = regressors(float(thr[k - 1]), None), regressors(float(thr[k]), None)
        rows, z = relative_rows(q, y[k - 1], y[k], x0, x1)
        est.add(rows, z, float(thr[k] ** 2))
    sol = est.solve()
    assert np.linalg.norm(sol.theta_mgauss - THETA) < 0.05 * np.linalg.norm(THETA)
    # what heading needs: the corrected field's heading over the flight (in level turns a mount tilt and a
    # horizontal hard iron look alike, so neither is checked alone). Uncorrected: ~10 deg rms.
    u = np.einsum("nji,j->ni", r, H_NED)
    y_clean = u + np.outer(thr**2, THETA) + D_TRUE
    corrected = y_clean @ sol.calib_l.T - sol.calib_d - np.outer(thr**2, sol.theta_mgauss)
    assert _heading_rms_deg(corrected, u, r) < 0.5


def test_constant_throttle_leaves_theta_at_its_prior_and_the_stage_says_why() -> None:
    """Hard iron and theta are told apart only by throttle changes: with none, theta is not claimed."""
    r, thr, _ = _flight(1500, 3, throttle_varies=False)
    y = _measure(r, thr, np.eye(3), D_TRUE, 3, noise=2.0)
    cfg = InflightConfig()
    st = InflightStage(0, cfg, "relative", "test", True, float(np.linalg.norm(H_NED)))
    for k in range(len(thr)):
        st.feed(0.1 * k, y[k], float(thr[k]), (), None, None, r[k])
        st.output(0.1 * k, tuple(y[k]), float(thr[k]), ())
    sol = st.solution
    assert sol is not None
    assert np.all(sol.theta_sigma_mgauss > 100.0)  # no information: the prior's 600 mgauss, barely reduced
    doc = st.summary()
    thr2_std = doc["throttle2_std"]
    assert isinstance(thr2_std, float) and thr2_std < 0.02
    if not st.applied:
        assert "throttle" in str(doc["why_not_applied"])


def test_glitch_does_not_move_a_converged_estimate() -> None:
    r, thr, _ = _flight(3000, 4)
    y = _measure(r, thr, A_TRUE, D_TRUE, 4, noise=3.0)
    est = InflightEstimator("absolute", 0, InflightParams(sigma_a=0.1), float(np.linalg.norm(H_NED)))
    for k in range(len(thr)):
        rows, z = absolute_rows(r[k].T @ H_NED, y[k], regressors(float(thr[k]), None))
        est.add(rows, z, float(thr[k] ** 2))
        if k % 50 == 0:
            est.solve()
    before = est.solve().theta_mgauss.copy()
    rows, z = absolute_rows(r[0].T @ H_NED, y[0] + np.array([900.0, -700.0, 400.0]), regressors(0.9, None))
    est.add(rows, z, 0.81)
    assert est.n_gated == 1
    assert np.allclose(est.solve().theta_mgauss, before)


def test_warm_start_reproduces_the_stored_estimate() -> None:
    r, thr, _ = _flight(1500, 5)
    y = _measure(r, thr, A_TRUE, D_TRUE, 5, noise=3.0)
    est = InflightEstimator("absolute", 0, InflightParams(sigma_a=0.1), 580.0)
    for k in range(len(thr)):
        rows, z = absolute_rows(r[k].T @ H_NED, y[k], regressors(float(thr[k]), None))
        est.add(rows, z, float(thr[k] ** 2))
    mean, sd = est.state()
    again = InflightEstimator("absolute", 0, InflightParams(sigma_a=0.1), 580.0, warm=(mean, sd))
    sol, sol2 = est.solve(), again.solve()
    assert np.allclose(sol2.theta_mgauss, sol.theta_mgauss, atol=1e-6)
    assert np.allclose(sol2.calib_l, sol.calib_l, atol=1e-9)
    assert np.all(sol2.theta_sigma_mgauss >= sol.theta_sigma_mgauss)  # widened, never narrower


@pytest.mark.parametrize(
    ("params", "idx", "mode"),
    [
        ({}, 0, "relative"),
        ({"COMPASS_PRIMARY": 0.0, "COMPASS_EXTERNAL": 1.0}, 0, "relative"),
        ({"COMPASS_PRIMARY": 0.0, "COMPASS_EXTERNAL": 1.0}, 1, "absolute"),
        ({"COMPASS_PRIMARY": 0.0, "COMPASS_EXTERNAL": 0.0}, 1, "relative"),
        ({"COMPASS_PRIMARY": 1.0, "COMPASS_EXTERN2": 2.0}, 0, "absolute"),
        ({"EK3_SRC1_YAW": 2.0, "COMPASS_PRIMARY": 0.0}, 0, "absolute"),
        ({"EK3_SRC1_YAW": 8.0, "COMPASS_EXTERNAL": 0.0}, 0, "absolute"),  # GSF: GPS velocity and IMU
        ({"EK3_SRC1_YAW": 6.0}, 0, "absolute"),  # external navigation (vision)
        ({"EK3_SRC1_YAW": 1.0, "COMPASS_EXTERNAL": 0.0}, 0, "relative"),  # the compass
        ({"EK3_SRC1_YAW": 8.0, "AHRS_EKF_TYPE": 2.0}, 0, "relative"),  # EKF3 not the one flying
        ({"EKF2_GPS_CTRL": 15.0}, 0, "absolute"),
        ({"EKF2_GPS_CTRL": 7.0}, 0, "relative"),
        # ArduPilot 4.1+: no COMPASS_PRIMARY; the first compass used for yaw is the primary
        ({"COMPASS_EXTERNAL": 0.0, "COMPASS_EXTERN2": 1.0, "COMPASS_USE": 0.0}, 0, "absolute"),
        ({"COMPASS_EXTERNAL": 0.0, "COMPASS_EXTERN2": 1.0, "COMPASS_USE": 0.0}, 1, "relative"),
        ({"COMPASS_EXTERNAL": 1.0, "COMPASS_USE": 1.0}, 1, "absolute"),
        ({"EKF2_GPS_CTRL": 7.0, "EKF2_MAG_TYPE": 5.0}, 0, "absolute"),  # PX4 fusing no magnetometer
        ({"EKF2_GPS_CTRL": 7.0, "EKF2_MAG_TYPE": 0.0}, 0, "relative"),
    ],
)
def test_yaw_reference_from_parameters(params: dict[str, float], idx: int, mode: str) -> None:
    got, why = yaw_reference(params, idx)
    assert got == mode
    assert why


def test_calibrated_by_autopilot() -> None:
    p = {"COMPASS_OFS_X": -97.8, "COMPASS_OFS_Y": 118.1, "COMPASS_OFS_Z": 213.2}
    p |= {"COMPASS_OFS3_X": 0.0, "COMPASS_OFS3_Y": 0.0, "COMPASS_OFS3_Z": 0.0}
    assert calibrated_by_autopilot(p, 0) is True
    assert calibrated_by_autopilot(p, 2) is False
    assert calibrated_by_autopilot(p, 1) is None
    assert calibrated_by_autopilot({"CAL_MAG1_XOFF": 0.1, "CAL_MAG1_YOFF": 0.0, "CAL_MAG1_ZOFF": 0.0}, 1)


def test_scalar_gyro_step_matches_the_vectorised_integrator() -> None:
    rng = np.random.default_rng(7)
    q = (1.0, 0.0, 0.0, 0.0)
    qv = np.array(q)
    for _ in range(500):
        w = rng.normal(0.0, 2.0, 3)
        q = quat_step_body_rate(q, w.tolist(), 0.01)
        qv = quat_integrate_body_rate(qv, w, 0.01)
    assert np.allclose(q, qv, atol=1e-9)
    assert math.isclose(float(np.linalg.norm(q)), 1.0, abs_tol=1e-12)


def _autopilot_yaw_drift(r: np.ndarray, thr: np.ndarray, dt_s: float, kp: float) -> np.ndarray:
    """The yaw error (rad) of an autopilot that steers its yaw toward this (disturbed) compass: a first-order
    lag (gain ``kp``, 1/s) on the compass's own heading error from the hard iron and theta * throttle^2."""
    u = np.einsum("nji,j->ni", r, H_NED)
    b = np.outer(thr**2, THETA) + D_TRUE
    psi_c = (u[:, 0] * b[:, 1] - u[:, 1] * b[:, 0]) / float(H_NED[0] ** 2 + H_NED[1] ** 2)
    psi = np.zeros_like(psi_c)
    for k in range(1, len(psi)):
        psi[k] = psi[k - 1] + dt_s * kp * (psi_c[k - 1] - psi[k - 1])
    return psi


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_relative_form_with_the_yaw_rate_nuisance_is_not_fooled_by_an_autopilot_yaw_that_follows_the_bias(
    seed: int,
) -> None:
    """Rotations from an autopilot whose yaw follows the disturbed compass at 0.5/s: over a 0.3 s pair its
    yaw moves with the bias, i.e. with the throttle. Without the windowed yaw-rate nuisance theta comes out
    ~20 % off and the heading ~2 deg; with it (2 s windows), within a few %."""
    from magcomp.core.inflight import rotation_error_rows

    dt, lag = 0.1, 3
    r, thr, _ = _flight(3000, seed)
    y = _measure(r, thr, np.eye(3), D_TRUE, seed, noise=2.0)
    psi = _autopilot_yaw_drift(r, thr, dt, kp=0.5)
    src = np.array([dcm_from_euler(0.0, 0.0, float(p)) @ rk for p, rk in zip(psi, r, strict=True)])
    u = np.einsum("nji,j->ni", r, H_NED)
    y_clean = u + np.outer(thr**2, THETA) + D_TRUE
    results = {}
    for nuisance in (False, True):
        est = InflightEstimator("relative", 0, InflightParams(), float(np.linalg.norm(H_NED)))
        for k in range(lag, len(thr)):
            q = src[k].T @ src[k - lag]
            x0, x1 = regressors(float(thr[k - lag]), None), regressors(float(thr[k]), None)
            v0, v1 = est.uncalibrated(y[k - lag], x0), est.uncalibrated(y[k], x1)
            rows, z = relative_rows(q, y[k - lag], y[k], x0, x1, v0, v1)
            if nuisance:
                cols = rotation_error_rows(q, v0, lag * dt) @ src[k][2].reshape(3, 1)
                est.add(rows, z, float(thr[k] ** 2), cols, math.floor(k * dt / 2.0))
            else:
                est.add(rows, z, float(thr[k] ** 2))
        sol = est.solve()
        corrected = y_clean @ sol.calib_l.T - sol.calib_d - np.outer(thr**2, sol.theta_mgauss)
        th_err = float(np.linalg.norm(sol.theta_mgauss - THETA) / np.linalg.norm(THETA))
        results[nuisance] = (th_err, _heading_rms_deg(corrected, u, r))
    assert results[False][0] > 0.10 and results[False][1] > 1.0  # the mechanism is real
    assert results[True][0] < 0.08 and results[True][1] < 0.6, results


@pytest.mark.parametrize("seed", [0, 1])
def test_absolute_form_does_not_inherit_the_reference_compass_yaw_error(seed: int) -> None:
    """The absolute form's yaw reference is another (external) compass with a residual hard iron of its own:
    its yaw error (~2 deg, varying with heading) is what an absolute fit would copy. With the windowed
    reference-yaw nuisance (2 s, prior 2 deg) the corrected heading stays on the truth."""
    from magcomp.core.inflight import reference_yaw_error_rows

    dt = 0.1
    r, thr, _ = _flight(3000, seed)
    y = _measure(r, thr, A_TRUE, D_TRUE, seed, noise=3.0)
    u = np.einsum("nji,j->ni", r, H_NED)
    ref_bias = np.array([12.0, -6.0, 0.0])  # the reference compass's residual hard iron, body axes
    h2 = float(H_NED[0] ** 2 + H_NED[1] ** 2)
    yaw_err = (u[:, 0] * ref_bias[1] - u[:, 1] * ref_bias[0]) / h2
    ref = np.array([dcm_from_euler(0.0, 0.0, float(e)) @ rk for e, rk in zip(yaw_err, r, strict=True)])
    y_clean = u @ A_TRUE.T + np.outer(thr**2, THETA) @ A_TRUE.T + D_TRUE
    results = {}
    for nuisance in (False, True):
        est = InflightEstimator("absolute", 0, InflightParams(sigma_a=0.1), float(np.linalg.norm(H_NED)))
        for k in range(len(thr)):
            rows, z = absolute_rows(ref[k].T @ H_NED, y[k], regressors(float(thr[k]), None))
            if nuisance:
                cols = reference_yaw_error_rows(ref[k], H_NED)
                est.add(rows, z, float(thr[k] ** 2), cols, math.floor(k * dt / 2.0), prior_sd=0.035)
            else:
                est.add(rows, z, float(thr[k] ** 2))
        sol = est.solve()
        corrected = y_clean @ sol.calib_l.T - sol.calib_d - np.outer(thr**2, sol.theta_mgauss)
        results[nuisance] = _heading_rms_deg(corrected, u, r)
    assert results[False] > 0.8  # the reference's error, (mostly) copied
    assert results[True] < 0.5 * results[False] and results[True] < 0.8, results


def test_stage_matches_a_field_with_the_attitude_and_throttle_of_its_own_time_when_they_arrive_late() -> None:
    """On a telemetry link the ATTITUDE and the throttle of an instant arrive after its RAW_IMU: each field is
    fed with those of one interval earlier. Given their times, the stage waits and uses the right ones: the
    estimate equals that of a feed with on-time values (all but the last sample); without the times it
    differs."""
    r, thr, _ = _flight(1200, 5)
    y = _measure(r, thr, np.eye(3), D_TRUE, 5, noise=2.0)
    h = float(np.linalg.norm(H_NED))

    def run(stale: bool, with_times: bool) -> np.ndarray:
        st = InflightStage(0, InflightConfig(), "relative", "test", True, h)
        for k in range(1, len(thr)):
            j = k - 1 if stale else k
            t_src = 0.1 * j if with_times else None
            st.feed(0.1 * k, y[k], float(thr[j]), (), None, None, r[j], t_src, t_src)
        assert st.est is not None
        return st.est.solve().theta_mgauss

    on_time = run(stale=False, with_times=False)
    matched = float(np.linalg.norm(run(stale=True, with_times=True) - on_time))  # one sample fewer
    stale = float(np.linalg.norm(run(stale=True, with_times=False) - on_time))
    assert matched < 0.3 and stale > 4.0 * matched, (matched, stale)


def _ar1(n: int, dt_s: float, tau_s: float, sd: float, seed: int) -> np.ndarray:
    """(n, 3) stationary AR(1) noise: a field error that lasts ``tau_s`` (an attitude or field error)."""
    rng = np.random.default_rng(seed + 200)
    a = math.exp(-dt_s / tau_s)
    e = np.empty((n, 3))
    e[0] = rng.normal(0.0, sd, 3)
    w = rng.normal(0.0, sd * math.sqrt(1.0 - a * a), (n, 3))
    for k in range(1, n):
        e[k] = a * e[k - 1] + w[k]
    return e


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_variance_inflation_is_one_for_white_residuals_and_large_for_lasting_ones(seed: int) -> None:
    """The rows' errors that last tens of seconds (an autopilot's tilt or yaw error) make 10 Hz samples far
    from independent: the white-noise covariance would claim theta to a fraction of its real error. The
    batch-means inflation is ~1 on white noise, and with a 10 s AR(1) error the reported sigma covers the
    error while the white one does not."""
    dt = 0.1
    r, thr, _ = _flight(3000, seed)
    y_white = _measure(r, thr, A_TRUE, D_TRUE, seed, noise=3.0)
    y_slow = _measure(r, thr, A_TRUE, D_TRUE, seed, noise=1.0) + _ar1(len(thr), dt, 10.0, 6.0, seed)
    out = {}
    ests: dict[str, InflightEstimator] = {}
    for name, y in (("white", y_white), ("slow", y_slow)):
        est = InflightEstimator("absolute", 0, InflightParams(sigma_a=0.1), float(np.linalg.norm(H_NED)))
        for k in range(len(thr)):
            rows, z = absolute_rows(r[k].T @ H_NED, y[k], regressors(float(thr[k]), None))
            cols = np.zeros((3, 1))  # windows without a nuisance of their own: batches only
            est.add(rows, z, float(thr[k] ** 2), cols, math.floor(k * dt / 2.0), prior_sd=0.035)
            if k % 100 == 99:
                est.solve()  # as the stage does: batches start once the estimate has settled
        out[name] = est.solve()
        ests[name] = est
    assert 1.0 <= out["white"].variance_inflation < 2.0, out["white"].variance_inflation
    slow = out["slow"]
    assert slow.variance_inflation > 10.0, slow.variance_inflation
    # the state a later run starts from carries the inflated sd too: A's third column (entries 2, 5, 8 of
    # 15) has a white sd under the state's floor (a tenth of the prior's) and an inflated one well above it
    est_slow = ests["slow"]
    assert est_slow._cov is not None
    _, sd = est_slow.state(inflate=1.0)
    white_sd = np.sqrt(np.diag(est_slow._cov))[[2, 5, 8]]
    floor = 0.1 * 0.1  # InflightParams(sigma_a=0.1)
    assert np.all(white_sd < floor) and np.all(sd[[2, 5, 8]] > 1.5 * floor), (sd[[2, 5, 8]], white_sd)
    err = np.abs(slow.theta_mgauss - THETA)
    assert np.all(err < 3.5 * slow.theta_sigma_mgauss), (err, slow.theta_sigma_mgauss)
