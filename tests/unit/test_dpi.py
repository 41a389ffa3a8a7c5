"""DPI calibration, eqs. (1)-(3): recovery of K and b, Table I heading check, refusal on thin data."""

from __future__ import annotations

import datetime as dt

import numpy as np
import pytest

from magcomp.core.dpi import (
    CalibrationError,
    DpiParams,
    apply_calibration,
    calibrate_dpi,
    calibrate_dpi_from_imu,
    dpi_design,
    field_error_dilution,
    pack,
    unpack,
)
from magcomp.core.heading import tilt_compensated_heading_deg, wrap_deg_180
from magcomp.core.mahony import STANDARD_GRAVITY_M_S2
from magcomp.core.rotations import (
    dcm_from_euler,
    dcm_from_quat,
    down_b_from_quat,
    quat_from_euler,
    quat_integrate_body_rate,
)
from magcomp.geomag import (
    DEFAULT_LOCATION,
    decimal_year,
    declination_deg,
    earth_field_ned_mgauss,
)

U_N = earth_field_ned_mgauss(*DEFAULT_LOCATION, decimal_year=2025.5)  # Gainesville FL, mgauss NED
F_N = float(np.linalg.norm(U_N))


def _distortion(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A plausible K (scale 0.85-1.15, cross-coupling/misalignment a few %) and hard iron b (mgauss)."""
    k = np.diag(rng.uniform(0.85, 1.15, 3)) + 0.04 * rng.standard_normal((3, 3))
    return k, rng.uniform(-250.0, 250.0, 3)


def _measure(
    r_nb: np.ndarray, k: np.ndarray, b: np.ndarray, rng: np.random.Generator, noise: float
) -> np.ndarray:
    u_b = np.einsum("nji,j->ni", r_nb, U_N)  # R_nb^T u^e: eq. (13) inverted
    return u_b @ k.T + b + noise * rng.standard_normal(u_b.shape)  # eq. (1)


def _random_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    e = np.c_[rng.uniform(-np.pi, np.pi, n), np.arcsin(rng.uniform(-1, 1, n)), rng.uniform(-np.pi, np.pi, n)]
    return np.array([dcm_from_euler(*row) for row in e])


def test_geomag_matches_noaa_reference_point() -> None:
    """stack-notes sec. 6: WMM-2025 at 47.40 N, 8.55 E, 0.5 km, 2026-11-21 -> 21524.5/1376.3/43333.8 nT."""
    f = earth_field_ned_mgauss(47.40, 8.55, 500.0, decimal_year(dt.date(2026, 11, 21)))
    np.testing.assert_allclose(f * 100.0, [21524.5, 1376.3, 43333.8], atol=3.0)
    assert abs(decimal_year(dt.date(2024, 7, 2)) - 2024.5) < 1e-3  # leap year: day 183 of 366
    assert -7.0 < declination_deg(U_N) < -5.0  # Gainesville 2025: about 6.4 deg W


def test_pack_unpack_round_trip_and_design_reproduces_eq3() -> None:
    rng = np.random.default_rng(0)
    L, d = rng.standard_normal((3, 3)), rng.standard_normal(3)
    L2, d2 = unpack(pack(L, d))
    np.testing.assert_array_equal(L, L2)
    np.testing.assert_array_equal(d, d2)
    w, v = rng.standard_normal((5, 3)), rng.standard_normal((5, 3))
    direct = np.einsum("ni,ij,nj->n", w, L, v) - w @ d  # w^T L v - w^T d
    np.testing.assert_allclose(dpi_design(w, v) @ pack(L, d), direct, atol=1e-12)


def test_dpi_recovers_known_K_and_b_eq1_eq2() -> None:
    rng = np.random.default_rng(11)
    k, b = _distortion(rng)
    r_nb = _random_rotations(rng, 3000)
    v = _measure(r_nb, k, b, rng, noise=1.5)
    res = calibrate_dpi(r_nb[:, 2, :], v, U_N[2], F_N)
    assert res.success, res.message
    np.testing.assert_allclose(res.L, np.linalg.inv(k), atol=2e-3)  # L = K^-1
    np.testing.assert_allclose(res.d, np.linalg.inv(k) @ b, atol=1.0)  # d = K^-1 b, mgauss
    assert 1.0 < res.residual_rms_mgauss < 2.0  # ~ the noise projected on w through L
    assert res.coverage.down_spread > 0.9 and res.coverage.octant_fraction == 1.0
    # eq. (2) inverts eq. (1)
    u_b = np.einsum("nji,j->ni", r_nb[:5], U_N)
    np.testing.assert_allclose(apply_calibration(res.L, res.d, u_b @ k.T + b), u_b, atol=2.0)


def _hand_rotation_imu(rng: np.random.Generator, duration_s: float, rate_hz: float) -> tuple[np.ndarray, ...]:
    """Smooth tumbling through all attitudes, IMU with gyro bias and noise. Returns t, q_true, gyro, accel."""
    dt_s = 1.0 / rate_hz
    t = np.arange(0.0, duration_s, dt_s)
    omega = 1.2 * np.sin(2 * np.pi * np.array([0.11, 0.07, 0.05]) * t[:, None] + rng.uniform(0, 6.3, 3))
    q = np.empty((len(t), 4))
    q[0] = quat_from_euler(0.0, 0.0, 0.5)
    for i in range(1, len(t)):
        q[i] = quat_integrate_body_rate(q[i - 1], omega[i - 1], dt_s)
    down = np.array([down_b_from_quat(qi) for qi in q])
    bias = np.array([0.01, -0.01, 0.005])
    gyro = np.vstack([omega[:1], omega[:-1]]) + bias + 0.003 * rng.standard_normal(omega.shape)
    accel = -STANDARD_GRAVITY_M_S2 * down + 0.03 * rng.standard_normal(omega.shape)
    return t, q, gyro, accel


def test_dpi_with_mahony_reference_and_table1_cardinal_headings_within_1deg() -> None:
    """Sec. II-A + Table I: reference from the Mahony filter, then level headings N/E/S/W within 1 deg."""
    rng = np.random.default_rng(5)
    k, b = _distortion(rng)
    t, q_true, gyro, accel = _hand_rotation_imu(rng, 200.0, 50.0)
    mag_idx = np.arange(0, len(t), 2)  # compass at 25 Hz, IMU at 50 Hz
    r_true = np.array([dcm_from_quat(q_true[i]) for i in mag_idx])
    v = _measure(r_true, k, b, rng, noise=0.5)
    res = calibrate_dpi_from_imu(t, gyro, accel, t[mag_idx], v, U_N).raise_if_failed()
    assert res.n == int(np.sum(t[mag_idx] >= 20.0))
    np.testing.assert_allclose(res.L, np.linalg.inv(k), atol=0.01)
    dec = declination_deg(U_N)
    worst_cal, worst_raw = 0.0, 0.0
    for mag_heading in (0.0, 90.0, 180.0, 270.0):
        r = dcm_from_euler(0.0, 0.0, np.radians(mag_heading + dec))
        v_level = _measure(r[None], k, b, rng, noise=0.5)[0]
        h_cal = float(tilt_compensated_heading_deg(apply_calibration(res.L, res.d, v_level), 0.0, 0.0))
        h_raw = float(tilt_compensated_heading_deg(v_level, 0.0, 0.0))
        worst_cal = max(worst_cal, abs(float(wrap_deg_180(h_cal - mag_heading))))
        worst_raw = max(worst_raw, abs(float(wrap_deg_180(h_raw - mag_heading))))
    assert worst_cal < 1.0, worst_cal
    assert worst_raw > 10.0  # control: the uncalibrated compass is far off


@pytest.mark.parametrize(
    ("name", "max_tilt_rad"),
    [("yaw only", 0.0), ("small tilts", np.radians(8.0))],
)
def test_dpi_refuses_data_without_enough_rotation(name: str, max_tilt_rad: float) -> None:
    rng = np.random.default_rng(2)
    k, b = _distortion(rng)
    n = 2000
    tilt = rng.uniform(-max_tilt_rad, max_tilt_rad, (n, 2))
    yaw = rng.uniform(-np.pi, np.pi, n)
    r_nb = np.array([dcm_from_euler(a, c, y) for (a, c), y in zip(tilt, yaw, strict=True)])
    res = calibrate_dpi(r_nb[:, 2, :], _measure(r_nb, k, b, rng, 1.0), U_N[2], F_N)
    assert not res.success, name
    assert "too little rotation" in res.message
    assert np.all(np.isnan(res.L))
    with pytest.raises(CalibrationError, match="refused"):
        res.raise_if_failed()


def test_dpi_refuses_too_few_samples_and_horizontal_field() -> None:
    rng = np.random.default_rng(4)
    k, b = _distortion(rng)
    r_nb = _random_rotations(rng, 50)
    res = calibrate_dpi(r_nb[:, 2, :], _measure(r_nb, k, b, rng, 1.0), U_N[2], F_N)
    assert not res.success and "samples" in res.message
    r_nb = _random_rotations(rng, 500)
    res2 = calibrate_dpi(r_nb[:, 2, :], _measure(r_nb, k, b, rng, 1.0), 5.0, 300.0)
    assert not res2.success and "horizontal" in res2.message
    with pytest.raises(CalibrationError):
        calibrate_dpi(np.zeros((10, 2)), np.zeros((10, 3)), U_N[2])


def test_norm_refinement_reduces_error_from_noisy_reference_vectors() -> None:
    """With ~2 deg errors in w (a poor attitude reference), adding |L v - d| = F helps L."""
    rng = np.random.default_rng(9)
    k, b = _distortion(rng)
    r_nb = _random_rotations(rng, 3000)
    v = _measure(r_nb, k, b, rng, noise=1.0)
    w_noisy = r_nb[:, 2, :] + 0.035 * rng.standard_normal((3000, 3))
    lin = calibrate_dpi(w_noisy, v, U_N[2], F_N)
    ref = calibrate_dpi(w_noisy, v, U_N[2], F_N, DpiParams(refine_with_norm=True))
    assert lin.success and ref.success and ref.refined
    l_true = np.linalg.inv(k)
    err_lin = np.abs(lin.L - l_true).max()
    err_ref = np.abs(ref.L - l_true).max()
    assert err_ref < err_lin
    assert ref.norm_residual_rms_mgauss < lin.norm_residual_rms_mgauss


@pytest.mark.parametrize("start", ["linear", "identity"])
def test_norm_refinement_solver_matches_scipy_least_squares(start: str) -> None:
    """The in-core Levenberg-Marquardt (analytic Jacobian of eq. (3) and the |L v - d| = F rows) reaches the
    minimum scipy's MINPACK ``lm`` finds, from the eq. (3) solution and from ``L = I, d = 0``."""
    from scipy.optimize import least_squares

    from magcomp.core.dpi import _residuals, refine_with_norm_lm

    for seed in (3, 4):
        rng = np.random.default_rng(seed)
        k, b = _distortion(rng)
        r_nb = _random_rotations(rng, 2000)
        v = _measure(r_nb, k, b, rng, noise=1.0)
        w = r_nb[:, 2, :] + 0.035 * rng.standard_normal((2000, 3))
        w /= np.linalg.norm(w, axis=1, keepdims=True)
        if start == "linear":
            lin = calibrate_dpi(w, v, U_N[2], F_N)
            x0 = pack(lin.L, lin.d)
        else:
            x0 = pack(np.eye(3), np.zeros(3))
        ref = least_squares(_residuals, x0, args=(w, v, U_N[2], F_N, 2.0), method="lm", x_scale="jac")
        ours = refine_with_norm_lm(x0, w, v, U_N[2], F_N, 2.0)
        assert ref.success and ours.converged
        L_ref, d_ref = unpack(ref.x)
        L_ours, d_ours = unpack(ours.x)
        np.testing.assert_allclose(L_ours, L_ref, rtol=0, atol=1e-7)  # L dimensionless, entries ~1
        np.testing.assert_allclose(d_ours, d_ref, rtol=0, atol=1e-4)  # mgauss, entries ~250
        cost_ref, cost_ours = float(ref.fun @ ref.fun), float(ours.fun @ ours.fun)
        assert cost_ours <= cost_ref * (1 + 1e-12)
        np.testing.assert_allclose(ours.fun, _residuals(ours.x, w, v, U_N[2], F_N, 2.0), atol=1e-9)


def test_field_error_dilution_predicts_the_calibrations_error_and_falls_with_more_pairs() -> None:
    """field_error_dilution x eq. (3)'s residual = the rms standard error of the calibrated field (eq. (2))
    at the samples: checked against 300 refits of the same rotation with fresh noise; 1 / sqrt(n) for more
    pairs of the same rotation; larger for a rotation that tilts little."""
    rng = np.random.default_rng(21)
    k, b = _distortion(rng)
    r_nb = _random_rotations(rng, 300)
    clean = _measure(r_nb, k, b, rng, noise=0.0)
    l_true, d_true = np.linalg.inv(k), np.linalg.inv(k) @ b
    errs, resid = [], []
    for _ in range(300):
        res = calibrate_dpi(r_nb[:, 2, :], clean + 3.0 * rng.standard_normal(clean.shape), U_N[2], F_N)
        assert res.success, res.message
        errs.append(clean @ (res.L - l_true).T - (res.d - d_true))  # error of u = L v - d at each sample
        resid.append(res.residual_rms_mgauss)
    measured = float(np.sqrt(np.mean(np.square(errs))))  # over refits, samples and axes
    predicted = field_error_dilution(r_nb[:, 2, :], clean) * float(np.mean(resid))
    assert abs(measured / predicted - 1.0) < 0.15, (measured, predicted)
    # four times the pairs of the same rotation: half the dilution
    r4 = _random_rotations(rng, 1200)
    v4 = _measure(r4, k, b, rng, noise=0.0)
    ratio = field_error_dilution(r4[:, 2, :], v4) / field_error_dilution(r_nb[:, 2, :], clean)
    assert 0.4 < ratio < 0.6, ratio
    # the same number of pairs tilted by at most 20 deg: far less information
    tilt = rng.uniform(-np.radians(20.0), np.radians(20.0), (300, 2))
    r_flat = np.array(
        [dcm_from_euler(a, c, y) for (a, c), y in zip(tilt, rng.uniform(-np.pi, np.pi, 300), strict=True)]
    )
    flat = field_error_dilution(r_flat[:, 2, :], _measure(r_flat, k, b, rng, noise=0.0))
    assert flat > 3.0 * field_error_dilution(r_nb[:, 2, :], clean)
