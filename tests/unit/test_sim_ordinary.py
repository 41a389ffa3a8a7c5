"""The ``ordinary`` multirotor flight (issue 9): take-off / landing throttle, yaw turns, tilt, the Earth field
at the configured place and date, the autopilot's calibration and yaw sources, on seeded truth arrays."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from magcomp.core.rotations import dcms_from_quats
from magcomp.sim import SimConfig, SimResult, simulate
from magcomp.sim.autopilot import AutopilotParams
from magcomp.sim.config import apply_settings
from magcomp.sim.powertrain import first_order_lag
from magcomp.sim.trajectory import HOVER_THROTTLE, IDLE_THROTTLE


def ordinary(duration_s: float = 120.0, settings: list[str] | None = None, seed: int = 4) -> SimResult:
    cfg = apply_settings(SimConfig(scenario="ordinary", duration_s=duration_s, seed=seed), settings or [])
    return simulate(cfg)


@pytest.fixture(scope="module")
def flight() -> SimResult:
    return ordinary(300.0)


def segment_mask(r: SimResult, name: str) -> np.ndarray:
    return r.motion.segment == r.motion.segment_names.index(name)


def tilt_deg(r: SimResult) -> np.ndarray:
    down_z = dcms_from_quats(r.motion.q_nb)[:, 2, 2]  # body z . NED down
    return np.degrees(np.arccos(np.clip(down_z, -1.0, 1.0)))


def test_motors_off_only_briefly_on_the_ground_and_throttle_spans_climbs_and_descents(
    flight: SimResult,
) -> None:
    m = flight.motion
    thr = m.throttle_cmd_01
    dt = m.dt_s
    off = thr == 0.0
    assert off[0] and off[-1]  # starts and ends on the ground, motors off
    assert off.sum() * dt <= 10.0  # briefly: no motors-off hand rotation anywhere
    runs = np.flatnonzero(np.diff(off.astype(int)))  # motors off only at the very start and the very end
    assert len(runs) == 2
    airborne = m.alt_m > 1.0
    assert thr[airborne].min() >= 0.3 and thr[airborne].max() <= 0.8
    assert thr[airborne].min() <= 0.4 and thr[airborne].max() >= 0.7  # climbs and descents drive throttle
    # take-off: above hover throttle while climbing off the ground; idle on the ground with motors on
    takeoff = segment_mask(flight, "takeoff") & (m.vel_n_m_s[:, 2] < -1.0)
    assert np.median(thr[takeoff]) > HOVER_THROTTLE + 0.05
    idle = segment_mask(flight, "ground_idle")
    assert np.allclose(np.median(thr[idle]), IDLE_THROTTLE, atol=0.01)
    landing = segment_mask(flight, "landing") & airborne
    assert np.median(thr[landing]) < HOVER_THROTTLE  # descending: below hover
    assert m.alt_m.max() > 15.0 and abs(m.alt_m[-1]) < 0.05
    assert np.all(m.alt_m[off] < 0.05)


def test_full_yaw_turns_at_hover_and_in_forward_flight(flight: SimResult) -> None:
    yaw = np.unwrap(flight.euler_rad[:, 2])
    for name in ("hover_yaw", "circles"):
        mask = segment_mask(flight, name)
        # each contiguous run of the segment
        starts = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(int)])) == 1)
        ends = np.flatnonzero(np.diff(np.concatenate([mask.astype(int), [0]])) == -1)
        turns = [abs(yaw[e] - yaw[s]) / (2 * math.pi) for s, e in zip(starts, ends, strict=True)]
        assert len(turns) == 2
        assert min(turns) >= 1.9  # whole 360 deg turns, several of them
    speed = np.linalg.norm(flight.motion.vel_n_m_s[:, :2], axis=1)
    assert speed[segment_mask(flight, "circles")].min() > 5.0  # turns in forward flight
    assert speed[segment_mask(flight, "hover_yaw")].max() < 0.5  # turns at hover


def test_forward_flight_is_tilted_10_to_25_deg(flight: SimResult) -> None:
    tilt = tilt_deg(flight)
    for name in ("cruise", "cruise_fast", "circles"):
        mask = segment_mask(flight, name)
        core = np.percentile(tilt[mask], [10, 90])
        assert core[0] >= 8.0 and core[1] <= 26.0, (name, core)
    assert np.median(tilt[segment_mask(flight, "hover")]) < 4.0  # hover: wind wobble only


def test_earth_field_is_the_wmm_at_the_configured_place_and_date() -> None:
    from magcomp.geomag import earth_field_ned_mgauss

    r = ordinary(20.0, ["lat_deg=46.05", "lon_deg=14.51", "alt_m=300", "decimal_year=2026.4"])
    expected = earth_field_ned_mgauss(46.05, 14.51, 300.0, 2026.4)
    np.testing.assert_allclose(r.earth_field_ned_mgauss, expected, atol=1.0)
    # the field in body axes is that vector rotated by the true attitude
    r_nb = dcms_from_quats(r.motion.q_nb)
    np.testing.assert_allclose(
        np.einsum("nij,nj->ni", r_nb, r.field_earth_b_mgauss), np.tile(expected, (len(r_nb), 1)), atol=1.0
    )
    gps = r.samples.gps
    assert gps is not None and abs(gps.lat_deg[0] - 46.05) < 1e-9


def heading_error_from_bias_deg(r: SimResult, j: int) -> np.ndarray:
    """The heading error the bias B_j alone makes on a perfectly calibrated compass, at the samples."""
    idx = r.samples.truth_index
    r_nb = dcms_from_quats(r.motion.q_nb[idx])
    u = r.field_earth_b_mgauss[idx]
    clean = np.einsum("nij,nj->ni", r_nb, u)
    biased = np.einsum("nij,nj->ni", r_nb, u + r.bias_mgauss[j, idx])
    # the field seen rotated east by delta makes the compass read the heading delta too far west
    err = np.arctan2(clean[:, 1], clean[:, 0]) - np.arctan2(biased[:, 1], biased[:, 0])
    return np.degrees((err + math.pi) % (2 * math.pi) - math.pi)


def autopilot_yaw_error_deg(r: SimResult) -> np.ndarray:
    yaw_true = r.euler_rad[r.samples.truth_index, 2]
    err = r.samples.attitude_rad[:, 2] - yaw_true
    return np.degrees((err + math.pi) % (2 * math.pi) - math.pi)


def test_autopilot_yaw_follows_the_throttle_squared_bias_only_when_it_fuses_the_disturbed_compass() -> None:
    def pair(settings: list[str]) -> tuple[SimResult, np.ndarray]:
        """The run, and its autopilot yaw error minus that of the same run (same seed: same calibration
        errors and noise) without any current effect: what the bias alone does to the ATTITUDE yaw."""
        cfg = apply_settings(SimConfig(scenario="ordinary", duration_s=120.0, seed=4), settings)
        with_bias = simulate(cfg)
        without = simulate(dataclasses.replace(cfg, theta_mgauss=(0.0, 0.0, 0.0)))
        return with_bias, autopilot_yaw_error_deg(with_bias) - autopilot_yaw_error_deg(without)

    fused, d_fused = pair([])
    air = fused.samples.throttle_01 > 0.2
    # the complementary filter pulls its yaw toward the compass's at kp_yaw: a first-order lag
    predicted = first_order_lag(
        heading_error_from_bias_deg(fused, 0), 1.0 / fused.config.rates.imu_hz, 1.0 / AutopilotParams().kp_yaw
    )
    assert np.sqrt(np.mean(predicted[air] ** 2)) > 1.5  # the bias is large enough to matter
    # compass-fused: the bias's share of the yaw error is the bias-driven heading error, lagged by the filter
    assert np.corrcoef(d_fused[air], predicted[air])[0, 1] > 0.9
    assert np.sqrt(np.mean((d_fused - predicted)[air] ** 2)) < 0.35 * np.sqrt(np.mean(predicted[air] ** 2))
    # GPS yaw: no trace of the bias, and small
    truth, d_truth = pair(["yaw_source=truth"])
    assert np.sqrt(np.mean(d_truth[air] ** 2)) < 0.05
    assert np.sqrt(np.mean(autopilot_yaw_error_deg(truth)[air] ** 2)) < 0.5
    # external primary: its own theta is ~0; the internal compass 1 carries the configured theta, and the
    # autopilot's yaw does not see it
    external, d_external = pair(["external_compass0=on"])
    th_ext = np.linalg.norm(external.compasses[0].theta_mgauss)
    th_int = np.linalg.norm(external.compasses[1].theta_mgauss)
    assert th_ext < 0.05 * th_int
    np.testing.assert_allclose(external.compasses[1].theta_mgauss, external.config.theta_mgauss)
    pred_internal = heading_error_from_bias_deg(external, 1)
    assert np.sqrt(np.mean(d_external[air] ** 2)) < 0.1 * np.sqrt(np.mean(pred_internal[air] ** 2))


def test_true_calibration_maps_the_logged_field_to_the_body_field() -> None:
    r = ordinary(
        30.0,
        ["mag_noise_scale=0", "mag_lsb_mgauss=0.01", "ap_cal_hard_iron_mgauss=30", "ap_cal_soft_iron=0.04"],
    )
    assert r.ap_calibration is not None
    idx = r.samples.truth_index
    for j in range(len(r.compasses)):
        l_matrix, d = r.true_calibration(j)
        body = r.samples.mag_mgauss[j] @ l_matrix.T - d
        truth = r.field_earth_b_mgauss[idx] + r.bias_mgauss[j, idx] + r.drift_mgauss[j, idx]
        # logged values are whole mgauss: 0.5 per axis through L (~1)
        assert np.abs(body - truth).max() < 1.5
        cal = r.ap_calibration[j]
        assert np.linalg.norm(cal.residual_hard_iron_mgauss) == pytest.approx(30.0)
        np.testing.assert_allclose(cal.a_matrix, cal.a_matrix.T, atol=1e-12)  # DIA/ODI: symmetric
        np.testing.assert_allclose(
            r.theta_logged_mgauss(j), np.linalg.solve(l_matrix, r.compasses[j].theta_mgauss), atol=1e-9
        )
        # what the autopilot logs is its own calibration of the raw reading
        raw = r.samples.mag_sensor_mgauss
        assert raw is not None
        np.testing.assert_allclose(
            r.samples.mag_mgauss[j], (raw[j] + cal.offsets_mgauss) @ cal.a_matrix.T, atol=0.5 + 1e-9
        )


def test_calibration_error_sizes_change_the_residual_not_its_draw() -> None:
    small = ordinary(5.0, ["ap_cal_hard_iron_mgauss=5", "ap_cal_soft_iron=0.01"])
    large = ordinary(5.0, ["ap_cal_hard_iron_mgauss=40", "ap_cal_soft_iron=0.05"])
    assert small.ap_calibration is not None and large.ap_calibration is not None
    h_small = small.ap_calibration[0].residual_hard_iron_mgauss
    h_large = large.ap_calibration[0].residual_hard_iron_mgauss
    np.testing.assert_allclose(h_large, 8.0 * h_small, rtol=1e-12)
    np.testing.assert_allclose(
        large.ap_calibration[0].soft_iron_error, 5.0 * small.ap_calibration[0].soft_iron_error
    )
    np.testing.assert_array_equal(small.samples.gyro_rad_s, large.samples.gyro_rad_s)  # other draws unchanged


def test_ordinary_plane_flight_turns_climbs_and_lands_on_its_throttle() -> None:
    r = simulate(SimConfig(scenario="ordinary_plane", duration_s=150.0, seed=3))
    m = r.motion
    assert r.config.vehicle == "fixedwing" and m.motors_cmd_01.shape[1] == 1
    thr = m.throttle_cmd_01
    speed = np.linalg.norm(m.vel_n_m_s, axis=1)
    off = thr == 0.0
    assert off[0] and off[-1] and off.sum() * m.dt_s < 10.0  # motor off briefly, on the ground only
    assert np.all(m.alt_m[off] < 0.05) and np.all(speed[off] < 7.0)
    assert speed[0] == 0.0 and speed[-1] < 0.1  # standing at both ends
    airborne = m.alt_m > 2.0
    assert thr[airborne].min() < 0.25 and thr[airborne].max() > 0.85  # glide and climb
    yaw = np.unwrap(r.euler_rad[:, 2])
    circles = segment_mask(r, "circles")
    starts = np.flatnonzero(np.diff(np.concatenate([[0], circles.astype(int)])) == 1)
    ends = np.flatnonzero(np.diff(np.concatenate([circles.astype(int), [0]])) == -1)
    assert all(abs(yaw[e] - yaw[s]) >= 2 * math.pi * 0.95 for s, e in zip(starts, ends, strict=True))
    # coordinated turns: bank = atan(V psi_dot / g)
    roll = np.degrees(r.euler_rad[circles, 0])
    assert 10.0 < np.median(np.abs(roll)) < 35.0
    assert r.config.gps and r.config.ap_calibration
