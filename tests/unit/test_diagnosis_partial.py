"""Partial observability (issue 26): a hover at near-constant attitude with varying throttle. The calibration
is refused (heading span and tilt span too small) but theta is given, with the autopilot's calibration as
prior, and its interval brackets the simulated theta; a throttle that does not vary still refuses theta."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from magcomp.core.rotations import dcm_from_euler
from magcomp.core.types import LogData, Series
from magcomp.diagnosis.engine import diagnose
from magcomp.diagnosis.gate import EarthReference
from magcomp.diagnosis.report import markdown

THETA = np.array([-61.0, 26.4, -12.0])
M_NED = np.array([230.0, -20.0, 410.0])


def hover_log(
    seed: int,
    throttle_varies: bool = True,
    duration_s: float = 120.0,
    noise_mgauss: float = 2.0,
    wander_mgauss: float = 0.0,
    ar1_mgauss: float = 0.0,
    ar1_tau_s: float = 10.0,
) -> LogData:
    """50 Hz hover: yaw wanders over ~40 deg, roll/pitch within +-3 deg, throttle 0.35-0.75 (or constant);
    the compass is calibrated to within a few % (as the autopilot flies it) and carries theta throttle^2.
    ``noise_mgauss``: white noise per axis; ``wander_mgauss``: a slow field error no model term describes
    (a 23 s sine on every axis, partly in step with the 9 s throttle cycle's beats); ``ar1_mgauss``: coloured
    compass noise, AR(1) with that standard deviation per axis and correlation time ``ar1_tau_s``."""
    rng = np.random.default_rng(seed)
    dt = 0.02
    n = int(duration_s / dt)
    t = 5.0 + dt * np.arange(n, dtype=np.float64)
    u = t - t[0]
    yaw = np.radians(30.0 + 20.0 * np.sin(2 * np.pi * u / 70.0))
    roll = np.radians(3.0 * np.sin(2 * np.pi * u / 11.0))
    pitch = np.radians(3.0 * np.sin(2 * np.pi * u / 7.0 + 1.0))
    r = np.stack([dcm_from_euler(a, b, c) for a, b, c in zip(roll, pitch, yaw, strict=True)])
    rates = np.gradient(np.column_stack([roll, pitch, yaw]), dt, axis=0)  # small angles: body ~ Euler rates
    thr = 0.55 + (0.2 * np.sin(2 * np.pi * u / 9.0) if throttle_varies else 0.0 * u)
    kmat = np.array([[1.03, 0.02, -0.01], [0.01, 0.98, 0.02], [-0.02, 0.01, 1.01]])
    b = np.array([40.0, -25.0, 60.0])
    h_b = np.einsum("nji,j->ni", r, M_NED)
    field = h_b @ kmat.T + b + np.outer(thr**2, THETA) + rng.normal(0.0, noise_mgauss, (n, 3))
    field += wander_mgauss * np.sqrt(2.0) * np.sin(2 * np.pi * u / 23.0)[:, None] * np.ones(3)
    if ar1_mgauss > 0.0:
        rho = float(np.exp(-dt / ar1_tau_s))
        e = rng.normal(0.0, ar1_mgauss * np.sqrt(1.0 - rho * rho), (n, 3))
        e[0] *= 1.0 / np.sqrt(1.0 - rho * rho)  # the stationary spread from the first sample on
        for k in range(1, n):
            e[k] += rho * e[k - 1]
        field += e
    att = np.column_stack([roll, pitch, yaw])
    accel = np.einsum("nji,j->ni", r, np.array([0.0, 0.0, -9.81]))
    return LogData(
        source="synthetic hover",
        mag={0: Series(t, field)},
        imu_t_s=t,
        gyro_rad_s=rates + rng.normal(0.0, 0.002, rates.shape),
        accel_m_s2=accel,
        attitude_rad=Series(t[::2], att[::2]),
        throttle_01=Series(t[::2], thr[::2]),
    )


EARTH = EarthReference(M_NED, "simulated place")


@pytest.mark.parametrize("seed", [1, 2])
def test_hover_gives_theta_with_the_calibration_refused(seed: int) -> None:
    d = diagnose(hover_log(seed), earth=EARTH)
    c = d.to_json()["compasses"][0]
    assert not c["observable"]
    assert "heading covers only" in c["unobservable_why"]
    pt = c["theta_given_prior"]
    assert pt is not None, c["unobservable_why"]
    assert pt["identifiable"]
    theta, hw = np.array(pt["theta"]), np.array(pt["theta_ci95_halfwidth"])
    assert np.all(np.abs(theta - THETA) <= hw), (theta, hw)
    assert float(np.linalg.norm(hw)) < 0.25 * float(np.linalg.norm(THETA))
    text = markdown(d)
    assert "theta is" in text and "None" not in text


def test_constant_throttle_still_refuses_theta() -> None:
    c = diagnose(hover_log(3, throttle_varies=False), earth=EARTH).to_json()["compasses"][0]
    assert not c["observable"]
    assert "throttle spans only" in c["unobservable_why"]
    assert c["theta_given_prior"] is None


def test_hover_without_a_position_takes_the_field_from_the_compass() -> None:
    """No WMM: the prior's field strength is the compass's own magnitude (not its spread about the median, 28
    mgauss on a real hover before), within the prior's own +-35 % (this compass keeps 76 mgauss of hard iron
    and theta throttle^2 in its magnitude)."""
    c = diagnose(hover_log(4)).to_json()["compasses"][0]
    pt = c["theta_given_prior"]
    assert pt is not None, c["unobservable_why"]
    strength = float(pt["prior"].split("A = ")[1].split(" mgauss")[0])
    assert abs(strength - float(np.linalg.norm(M_NED))) < 0.35 * float(np.linalg.norm(M_NED))
    theta, hw = np.array(pt["theta"]), np.array(pt["theta_ci95_halfwidth"])
    assert np.all(np.abs(theta - THETA) <= hw), (theta, hw)


def test_a_noisy_compass_refused_for_its_residual_still_gets_theta() -> None:
    """The telemetry case of issue 26: the forward model leaves more than 5 % of the field (here white noise
    of 30 mgauss per axis), so the calibration is refused, but that residual does not follow the throttle:
    theta is given, identifiable, its interval bracketing the truth (before: refused with no theta)."""
    d = diagnose(hover_log(4, noise_mgauss=30.0), earth=EARTH)
    c = d.to_json()["compasses"][0]
    assert not c["observable"]
    assert "forward model leaves" in c["unobservable_why"]
    pt = c["theta_given_prior"]
    assert pt is not None
    assert pt["identifiable"], pt["note"]
    theta, hw = np.array(pt["theta"]), np.array(pt["theta_ci95_halfwidth"])
    assert np.all(np.abs(theta - THETA) <= hw), (theta, hw)
    assert pt["model_error_bound_mgauss"] < float(np.linalg.norm(theta))


def test_a_structured_residual_beyond_the_gate_leaves_theta_given_but_not_identifiable() -> None:
    """A slow 40 mgauss error no term models: theta is still printed with its interval, flagged not
    identifiable with the model-error bound as the reason, and no autopilot parameter is suggested."""
    d = diagnose(hover_log(5, wander_mgauss=40.0), earth=EARTH)
    c = d.to_json()["compasses"][0]
    assert "forward model leaves" in c["unobservable_why"]
    pt = c["theta_given_prior"]
    assert pt is not None
    assert not pt["identifiable"]
    assert "structured residual" in pt["note"]
    assert pt["model_error_bound_mgauss"] >= float(np.linalg.norm(pt["theta"]))
    assert not c["autopilot"]
    text = markdown(d)
    assert "does not determine theta" in text and "None" not in text


def test_two_hovers_of_one_vehicle_with_coloured_noise_repeat() -> None:
    """Two hovers of one vehicle (the same compass and theta, other noise) whose compass noise is coloured:
    AR(1), 5 mgauss, 10 s correlation, so the 6000 samples carry far fewer independent pieces than a
    white-noise interval counts. Each flight's interval holds the simulated theta and the two overlap,
    without growing past a quarter of |theta|. Before the block jackknife floor both flights missed the
    truth (largest |error| / half-width 1.22 and 1.50); over seeds 200-229 the truth was inside on every
    axis in 22/30 flights, with the floor 28/30 (median half-width 3.5 -> 5.7 mgauss against |theta| 68)."""
    got = []
    for seed in (200, 221):
        c = diagnose(hover_log(seed, ar1_mgauss=5.0, ar1_tau_s=10.0), earth=EARTH).to_json()["compasses"][0]
        pt = c["theta_given_prior"]
        assert pt is not None, c["unobservable_why"]
        theta, hw = np.array(pt["theta"]), np.array(pt["theta_ci95_halfwidth"])
        assert np.all(np.abs(theta - THETA) <= hw), (seed, theta, hw)
        assert float(np.linalg.norm(hw)) < 0.25 * float(np.linalg.norm(THETA)), (seed, hw)
        got.append((theta, hw))
    (ta, ha), (tb, hb) = got
    assert np.all(np.abs(ta - tb) <= ha + hb), got


def test_diagnose_json_names_each_compass_sensor() -> None:
    """The compass's sensor (device id, external flag) from the log's parameters, in the JSON and the report:
    what a comparison between flights pairs on (tests/unit/test_diagnosis_identity.py)."""
    params = {"COMPASS_DEV_ID": 131594.0, "COMPASS_DEV_ID2": 0.0, "COMPASS_EXTERNAL": 0.0}
    d = diagnose(replace(hover_log(7), params=params), earth=EARTH)
    c = d.to_json()["compasses"][0]
    assert c["sensor"]["device_id"] == 131594 and c["sensor"]["external"] is False
    assert c["sensor"]["from"] == "COMPASS_DEV_ID" and "SPI bus 1" in c["sensor"]["text"]
    assert "Sensor: device id 131594 (SPI bus 1, address 0x02), internal (COMPASS_DEV_ID)." in markdown(d)
    assert diagnose(hover_log(7), earth=EARTH).to_json()["compasses"][0]["sensor"]["device_id"] is None
