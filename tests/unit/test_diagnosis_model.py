"""Diagnosis library on synthetic arrays (no simulator, no files): forward model, fit, selection, suspects."""

from __future__ import annotations

import math

import numpy as np
import pytest

from magcomp.core.rotations import dcm_from_euler, euler_from_dcm, quat_from_dcm, quat_integrate_body_rate
from magcomp.core.types import LogData, Series
from magcomp.diagnosis.compensation import linearise, px4_params
from magcomp.diagnosis.engine import compass_data, diagnose, diagnose_compass
from magcomp.diagnosis.model import fit_model, initial_fit
from magcomp.diagnosis.suspects import find_step, relate

NOISE = 2.0  # mgauss per axis
LAST_R: list[np.ndarray] = [np.zeros((0, 3, 3))]


def synth_log(
    seed: int,
    duration_s: float = 40.0,
    effects: dict[str, float] | None = None,
    step_at_s: float | None = None,
) -> tuple[LogData, np.ndarray, np.ndarray]:
    """A small hand-rotated, throttle-stepped log: (LogData, truth t, truth yaw)."""
    effects = effects or {}
    rng = np.random.default_rng(seed)
    dt = 0.02
    n = int(duration_s / dt)
    t = 10.0 + dt * np.arange(n, dtype=np.float64)
    # smooth random body rates (hand rotation) up to ~1 rad/s
    raw = rng.normal(size=(n + 200, 3))
    k = np.ones(100) / 100
    smooth = [np.convolve(np.convolve(raw[:, j], k, mode="same"), k, mode="same") for j in range(3)]
    w = np.column_stack(smooth)[100 : 100 + n] * 8.0
    q = quat_from_dcm(dcm_from_euler(0.1, -0.2, 0.5))
    qs = np.empty((n, 4))
    for i in range(n):
        qs[i] = q
        if i + 1 < n:  # truth at 4x the IMU rate, rates sampled instantaneously at the IMU times
            for j in range(4):
                q = quat_integrate_body_rate(q, w[i] + (j + 0.5) / 4 * (w[i + 1] - w[i]), dt / 4)
    r = np.stack([_dcm(qi) for qi in qs])
    LAST_R[0] = r
    # throttle: steps every 4 s between random levels + a ramp
    levels = rng.uniform(0.1, 1.0, size=int(duration_s / 4) + 2)
    thr = levels[((t - t[0]) // 4).astype(int)]
    thr[: int(4 / dt)] = np.linspace(0.0, 1.0, int(4 / dt))
    m_n = np.array([230.0, -20.0, 410.0])
    kmat = np.array([[1.05, 0.03, -0.02], [0.01, 0.97, 0.04], [-0.03, 0.02, 1.02]])
    b = np.array([40.0, -25.0, 60.0])
    theta = np.array([-61.0, 26.4, -12.0])
    speed = thr.copy()
    if "throttle_offset" in effects:
        o = effects["throttle_offset"]
        speed = np.clip((thr - o) / (1 - o), 0, None)
    if "time_skew" in effects:
        speed = np.interp(t - effects["time_skew"], t, speed)
    if "current_lag" in effects:
        a = math.exp(-dt / effects["current_lag"])
        out = np.empty_like(speed)
        y = speed[0]
        for i in range(n):
            y = a * y + (1 - a) * speed[i]
            out[i] = y
        speed = out
    p = effects.get("throttle_exponent", 2.0)
    temp = 25.0 + 10.0 * (t - t[0]) / duration_s + 2.0 * np.sin(t / 3.0)
    h_b = np.einsum("nji,j->ni", r, m_n)
    field = h_b @ kmat.T + b + np.outer(speed**p, theta)
    if "temperature_drift" in effects:
        field += np.outer(temp - 25.0, effects["temperature_drift"] * np.array([0.6, 0.0, 0.8]))
    if step_at_s is not None:
        field[t >= t[0] + step_at_s] += np.array([0.0, 80.0, 0.0])
    field += rng.normal(0.0, NOISE, size=field.shape)
    gyro = w + np.array([0.004, -0.003, 0.002]) + rng.normal(0, 0.002, size=w.shape)
    att = np.array([euler_from_dcm(ri) for ri in r])
    # the autopilot's yaw is disturbed by the bias (as a compass-fused yaw would be)
    att[:, 2] += 0.2 * speed**2
    accel = np.einsum("nji,j->ni", r, np.array([0.0, 0.0, -9.81]))
    log = LogData(
        source="synthetic",
        mag={0: Series(t, field)},
        imu_t_s=t,
        gyro_rad_s=gyro,
        accel_m_s2=accel,
        attitude_rad=Series(t[::2], att[::2]),
        throttle_01=Series(t[::2], thr[::2]),
        temperature_degc=Series(t[::5], temp[::5]),
    )
    return log, t, att[:, 2] - 0.2 * speed**2


def _dcm(q: np.ndarray) -> np.ndarray:
    from magcomp.core.rotations import dcm_from_quat

    return dcm_from_quat(q)


def test_paper_model_fits_clean_log_to_noise_eq11() -> None:
    log, _, _ = synth_log(1)
    data = compass_data(log, 0)
    fit = fit_model(data, (), start=initial_fit(data))
    assert fit.rms_mgauss < 1.1 * NOISE
    # theta (compass frame) recovered: field = K h + b + theta delta^2, theta enters unscaled
    np.testing.assert_allclose(fit.theta_mgauss, [-61.0, 26.4, -12.0], atol=3.0)


def test_clean_log_gives_no_finding() -> None:
    log, _, _ = synth_log(2)
    cd = diagnose_compass(compass_data(log, 0), "synthetic", log=log)
    assert cd.findings == []
    assert cd.extended.effects == ()


@pytest.mark.parametrize(
    ("effect", "value", "param", "tol"),
    [
        ("throttle_offset", 0.2, "offset", 0.03),
        ("throttle_exponent", 3.0, "exponent", 0.25),
        ("current_lag", 0.5, "tau_s", 0.15),
        ("time_skew", 0.25, "skew_s", 0.04),
    ],
)
def test_hidden_effect_is_strongest_finding(effect: str, value: float, param: str, tol: float) -> None:
    log, _, _ = synth_log(3, effects={effect: value})
    cd = diagnose_compass(compass_data(log, 0), "synthetic", log=log)
    assert cd.findings, "no finding"
    assert cd.findings[0].effect == effect
    assert abs(cd.findings[0].params[param] - value) <= tol
    assert cd.extended.rms_mgauss < 1.1 * NOISE


def test_temperature_drift_found_with_rate() -> None:
    log, _, _ = synth_log(4, effects={"temperature_drift": 2.0})
    cd = diagnose_compass(compass_data(log, 0), "synthetic", log=log)
    assert cd.findings and cd.findings[0].effect == "temperature_drift"
    assert abs(cd.findings[0].params["mgauss_per_degc"] - 2.0) < 0.3


def test_step_in_residual_is_located_and_sized() -> None:
    log, _, _ = synth_log(5, step_at_s=15.0)
    data = compass_data(log, 0)
    fit = fit_model(data, (), start=initial_fit(data))
    st = find_step(data.t_s, fit.residual_mgauss, {})
    assert st is not None
    assert abs(st.t_s - (data.t_s[0] + 15.0)) < 0.5
    assert st.size_sigma > 10.0


def test_relate_names_the_signal_and_lag_that_drive_the_residual() -> None:
    rng = np.random.default_rng(7)
    t = np.arange(0.0, 60.0, 0.05)
    s = np.cumsum(rng.normal(size=t.size))
    res = np.outer(np.interp(t - 0.5, t, s), [1.0, -2.0, 0.5]) + rng.normal(0, 1.0, (t.size, 3))
    rel = relate(t, res, {"driver": (t, s), "other": (t, rng.normal(size=t.size)), "time": (t, t)})
    assert rel[0].signal == "driver"
    assert abs(rel[0].lag_s - 0.5) < 0.11
    assert rel[0].r2 > 0.8


def test_linearisation_of_quadratic_bias_over_full_range() -> None:
    x = np.linspace(0.0, 1.0, 101)
    theta = np.array([-60.0, 30.0, 0.0])
    bias = np.outer(x**2, theta)
    terms = linearise(x, bias, None)
    # least squares slope through the origin of x^2 on [0, 1]: sum x^3 / sum x^2 -> 3/4
    np.testing.assert_allclose(terms.per_throttle_mgauss, 0.75 * theta, rtol=0.02)
    px4 = px4_params(terms, 0)
    assert px4["CAL_MAG_COMP_TYP"] == 1.0
    assert px4["CAL_MAG0_XCOMP"] == pytest.approx(0.045, abs=1e-3)  # gauss, negated


def test_heading_error_smaller_with_the_right_model() -> None:
    log, t, yaw = synth_log(6, effects={"throttle_offset": 0.25})
    d = diagnose(log, heading_reference=(t, yaw))
    h = d.compass(0).heading
    assert h is not None
    assert h.rms_deg["extended"] < h.rms_deg["paper"] < h.rms_deg["uncompensated"]


def test_the_fits_kept_design_parts_are_the_design_bit_for_bit() -> None:
    """The fit's residual keeps the field-direction and drive columns between evaluations
    (model._DesignParts): after any sequence of steps (the field direction only, one extension only,
    both) its matrix is design()'s, bit for bit."""
    from dataclasses import replace

    from magcomp.diagnosis.effects import ExtensionParams
    from magcomp.diagnosis.model import _DesignParts, design

    log, _, _ = synth_log(3, duration_s=20.0)
    data = compass_data(log, 0)
    parts = _DesignParts(data)
    base = ExtensionParams()
    steps = [
        (1.0, 0.2, 0.0, base),
        (1.0 + 1e-4, 0.2, 0.0, base),  # the field direction moves, the drive columns stay
        (1.0, 0.2, 0.0, replace(base, offset=0.1)),  # one extension moves, the field direction stays
        (1.0, 0.2, 1e-3, replace(base, offset=0.1)),
        (0.9, -0.3, 1e-3, replace(base, offset=0.1, exponent=1.8)),
        (0.9, -0.3, 1e-3, replace(base, offset=0.1, exponent=1.8)),  # nothing moves
        (1.0, 0.2, 0.0, base),  # back to the start
    ]
    for inc, dec, drift, ext in steps:
        got = parts.design(inc, dec, drift, ext)
        want, _ = design(data, inc, dec, drift, ext)
        assert got.shape == want.shape
        assert got.tobytes() == want.tobytes()
