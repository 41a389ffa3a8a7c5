"""``simulate(config, rng) -> SimResult``: truth and the autopilot's sensor samples for one scenario.

Reference: M. Silic and K. Mohseni, "Correcting Current-Induced Magnetometer Errors on UAVs: An Online
Model-Based Approach", IEEE Sensors J. 20(2), 2020; equation numbers as in that article.

Pipeline (pure: no I/O; the Earth field comes from :mod:`magcomp.geomag` unless the config gives one):
    motion (trajectory.py, exact SO(3) integration at truth_hz, eq. (18))
    -> powertrain (powertrain.py, eqs. (4)-(11) + hidden effects) -> bias per compass (eq. (11))
    -> sensors (sensors.py, eq. (1)) sampled at imu_hz -> autopilot attitude (autopilot.py)
    [-> the autopilot's own compass calibration, logged = A (v - b_ap) (sensors.AutopilotCalibration),
       when config.ap_calibration; the autopilot then steers by that calibrated field, or by GPS yaw]

The variation knobs (config.Variation) draw from their own random streams, so with every knob at its
default a pre-knob scenario reproduces its earlier output exactly (config.SimConfig.legacy).

Symbol table: theta -> CompassTruth.theta_mgauss (calibrated frame, mgauss); delta_t -> throttle_01;
B -> bias_mgauss (calibrated frame, mgauss, body); K, b -> k_matrix, b_mgauss (eq. (1)); u^e ->
earth_field_ned_mgauss (NED, mgauss).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from magcomp.core.heading import declination_rad
from magcomp.core.rotations import dcms_from_quats, euler_from_quats
from magcomp.core.types import STANDARD_GRAVITY_M_S2
from magcomp.sim.autopilot import AutopilotParams, run_autopilot
from magcomp.sim.config import SimConfig
from magcomp.sim.powertrain import PowertrainParams, PowertrainTruth, simulate_powertrain
from magcomp.sim.sensors import (
    AutopilotCalibration,
    CompassTruth,
    autopilot_calibration,
    coloured_noise,
    make_compasses,
    measure_accel,
    measure_gyro,
    measure_mag,
    quantize,
)
from magcomp.sim.trajectory import Motion, build_motion

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class GpsTrack:
    """The simulated GNSS track at the loop rows (n samples): truth, no GNSS noise. lat_deg, lon_deg (n,);
    alt_msl_m (n,) m, above the ellipsoid = MSL here (the geoid separation is taken as 0); vel_n_m_s (n, 3)
    NED velocity."""

    lat_deg: F64
    lon_deg: F64
    alt_msl_m: F64
    vel_n_m_s: F64

    def lat_lon_e7(self, i: int) -> tuple[int, int]:
        """Latitude and longitude of row ``i`` in 1e-7 deg, as GPS_RAW_INT and DataFlash GPS carry them."""
        return round(float(self.lat_deg[i]) * 1e7), round(float(self.lon_deg[i]) * 1e7)


@dataclass(frozen=True)
class SimSamples:
    """What the simulated autopilot reports, at imu_hz (n samples; J compasses / IMUs; m motors).

    Values are already quantised to the MAVLink units the emitter sends (gyro 1 mrad/s, accel 1 mG,
    mag 1 mgauss, motors 1 us of PWM, voltage 1 mV, current 10 mA), so a decoded log equals them.

    t_s (n,): boot clock; truth_index (n,): row of the truth arrays; gyro_rad_s, accel_m_s2, mag_mgauss
    (J, n, 3); imu_temp_degc (J, n); throttle_01 (n,) logged command; motors_01 (n, m); voltage_v,
    current_a (n,); attitude_rad (n, 3) autopilot roll, pitch, yaw; airspeed_m_s, groundspeed_m_s, alt_m,
    climb_m_s (n,).

    mag_mgauss is what the messages carry: the raw reading, or, with the autopilot's calibration on, the
    calibrated field ``A (v - b_ap)`` rounded to 1 mgauss; mag_sensor_mgauss is then the raw reading v.
    gps: the :class:`GpsTrack` with GPS on, else None.
    """

    t_s: F64
    truth_index: NDArray[np.int64]
    gyro_rad_s: F64
    accel_m_s2: F64
    mag_mgauss: F64
    imu_temp_degc: F64
    throttle_01: F64
    motors_01: F64
    voltage_v: F64
    current_a: F64
    attitude_rad: F64
    airspeed_m_s: F64
    groundspeed_m_s: F64
    alt_m: F64
    climb_m_s: F64
    mag_sensor_mgauss: F64 | None = None
    gps: GpsTrack | None = None


@dataclass(frozen=True)
class SimResult:
    """Truth (truth_hz) and samples (imu_hz) of one run. Truth arrays (n_truth rows):

    t_s: boot clock (s); motion: attitude q_nb, body rates, NED kinematics, commands (scenario time in
    motion.t_s = t_s - t0_s); power: the powertrain chain; bias_mgauss (J, n, 3): current-induced field at
    each compass (calibrated frame; = theta_j throttle^2 with no effect on); drift_mgauss (J, n, 3):
    temperature-driven hard iron; field_earth_b_mgauss (n, 3): Earth field in body axes.
    """

    config: SimConfig
    t_s: F64
    motion: Motion
    power: PowertrainTruth
    compasses: tuple[CompassTruth, ...]
    bias_mgauss: F64
    drift_mgauss: F64
    field_earth_b_mgauss: F64
    earth_field_ned_mgauss: F64
    declination_deg: float
    samples: SimSamples
    effect_params: dict[str, object] = field(default_factory=dict)
    ap_calibration: tuple[AutopilotCalibration, ...] | None = None

    def true_calibration(self, j: int) -> tuple[F64, F64]:
        """(L, d) of eq. (2) for the LOGGED field of compass j: ``L logged - d = u + B + D`` (body frame,
        noise aside). Without the autopilot's calibration the logged field is the raw reading: L = K^-1,
        d = K^-1 b."""
        c = self.compasses[j]
        if self.ap_calibration is not None:  # logged = A (v - b_ap): L = (A K)^-1, d = K^-1 (b - b_ap)
            cal = self.ap_calibration[j]
            l_ap = np.asarray(np.linalg.inv(cal.a_matrix @ c.k_matrix), dtype=np.float64)
            return l_ap, np.asarray(
                np.linalg.solve(c.k_matrix, c.b_mgauss - cal.b_ap_mgauss), dtype=np.float64
            )
        l_matrix = np.asarray(np.linalg.inv(c.k_matrix), dtype=np.float64)
        return l_matrix, l_matrix @ c.b_mgauss

    def theta_logged_mgauss(self, j: int) -> F64:
        """theta of compass j in the frame of the logged field (= L^-1 theta)."""
        l_matrix, _ = self.true_calibration(j)
        return np.asarray(np.linalg.solve(l_matrix, self.compasses[j].theta_mgauss), dtype=np.float64)

    @property
    def t0_s(self) -> float:
        return float(self.config.t0_s)

    @property
    def euler_rad(self) -> F64:
        """True roll, pitch, yaw (n_truth, 3)."""
        return euler_from_quats(self.motion.q_nb)

    def truth_at_samples(self, values: F64) -> F64:
        """Pick truth rows at the sample instants (values indexed on axis 0, or axis 1 for (J, n, 3))."""
        idx = self.samples.truth_index
        return values[:, idx] if values.ndim == 3 else values[idx]


def _earth_field(config: SimConfig) -> F64:
    if config.earth_field_ned_mgauss is not None:
        return np.asarray(config.earth_field_ned_mgauss, dtype=float)
    from magcomp.geomag import earth_field_ned_mgauss

    loc = config.location
    return earth_field_ned_mgauss(loc.lat_deg, loc.lon_deg, loc.alt_m, loc.decimal_year)


def simulate(config: SimConfig, rng: np.random.Generator | None = None) -> SimResult:
    """Simulate one run. ``rng`` defaults to ``np.random.default_rng(config.seed)``.

    The rng is split into independent streams for the motion, the sensor errors and the noise, so the
    same seed gives the same compass errors (K, b, theta) in every scenario: calibrate on ``tumble`` and
    apply the result to ``bench`` of the same seed.
    """
    rng = np.random.default_rng(config.seed) if rng is None else rng
    rng_motion, rng_params, rng_noise = rng.spawn(3)
    # the knobs draw from their own streams, so a pre-knob run's draws are unchanged
    rng_cal, rng_cnoise, rng_att = rng.spawn(1)[0].spawn(3)
    var = config.variation
    rates = config.rates
    dt = 1.0 / rates.truth_hz
    motion = build_motion(
        config.scenario, config.duration, config.vehicle, dt, rng_motion, config.variation.hover_throttle
    )
    effects = dict(config.effects)
    compasses = make_compasses(
        config.n_compasses,
        np.asarray(config.theta_mgauss, dtype=float) * var.theta_scale,
        motion.motors_cmd_01.shape[1],
        effects.get("per_motor", 0.0),
        rng_params,
    )
    compasses = _vary_compasses(config, compasses)
    current_max = config.variation.current_max_a
    if current_max is None:
        current_max = 40.0 if config.vehicle == "multirotor" else 20.0
    pt_params = PowertrainParams(current_max_a=current_max)
    per_motor = effects.get("per_motor", 0.0) > 0.0
    command = motion.motors_cmd_01 if per_motor else motion.throttle_cmd_01[:, None]
    power = simulate_powertrain(motion.t_s, command, dt, effects, pt_params)
    bias, drift = _bias_and_drift(compasses, power, effects, pt_params)

    m_n = _earth_field(config)
    r_nb = dcms_from_quats(motion.q_nb)
    field_b = np.einsum("nji,j->ni", r_nb, m_n)  # u = R_nb^T m_n
    step = round(rates.truth_hz / rates.imu_hz)
    idx = np.arange(0, motion.t_s.shape[0], step)
    field_total_b = field_b + bias + drift
    run = _Run(config, compasses, motion, power, idx)
    sensed = _measure(run, field_total_b, r_nb, rng_noise, rng_cnoise)
    ap_cal = None
    if config.ap_calibration:
        ap_cal = tuple(autopilot_calibration(c, *config.ap_cal_errors, rng_cal) for c in compasses)
    decl = declination_rad(m_n)
    attitude = _autopilot_attitude(run, sensed, ap_cal, decl, rng_att)
    samples = _samples(run, sensed, ap_cal, attitude, rng_noise)
    return SimResult(
        config=config,
        t_s=config.t0_s + motion.t_s,
        motion=motion,
        power=power,
        compasses=compasses,
        bias_mgauss=bias,
        drift_mgauss=drift,
        field_earth_b_mgauss=field_b,
        earth_field_ned_mgauss=m_n,
        declination_deg=math.degrees(decl),
        samples=samples,
        effect_params=_effect_params(effects, compasses, pt_params),
        ap_calibration=ap_cal,
    )


def _bias_and_drift(
    compasses: Sequence[CompassTruth],
    power: PowertrainTruth,
    effects: dict[str, float],
    pt_params: PowertrainParams,
) -> tuple[F64, F64]:
    """Per compass and truth row: the motor bias of eq. (11) and the temperature drift (mgauss)."""
    # eq. (11): B_j = theta_j * load (load = throttle^2 with no effect); per motor: sum_i theta_ij load_i / k
    k = power.load_01.shape[1]
    bias = np.stack([power.load_01 @ c.theta_motor_mgauss / k for c in compasses])  # eq. (11)
    drift_k = effects.get("temperature_drift", 0.0)
    dtemp = power.temp_powertrain_degc - pt_params.ambient_degc
    drift = np.stack([drift_k * dtemp[:, None] * c.drift_dir[None, :] for c in compasses])
    return bias, drift


class _Run(NamedTuple):
    """What the steps of :func:`simulate` share: the run, its truth and the loop rows ``idx``."""

    config: SimConfig
    compasses: Sequence[CompassTruth]
    motion: Motion
    power: PowertrainTruth
    idx: NDArray[np.int64]


class _Sensed(NamedTuple):
    """What the compasses and IMUs measure at the loop rows (compass j with IMU j)."""

    gyro: F64  # (J, n, 3) rad/s
    accel: F64  # (J, n, 3) m/s^2
    mag: F64  # (J, n, 3) mgauss, held between mag_hz updates
    imu_temp: F64  # (J, n) degC


def _measure(
    run: _Run, field_total_b: F64, r_nb: F64, rng_noise: np.random.Generator, rng_cnoise: np.random.Generator
) -> _Sensed:
    """The sensors at the loop rows ``idx``: gyro, accelerometer and compass of each compass's IMU (the
    field: the Earth's plus each compass's motor bias and drift, ``field_total_b`` (J, n, 3)), and the IMU
    temperatures."""
    config, compasses, motion, power, idx = run
    var = config.variation
    rates = config.rates
    step = round(rates.truth_hz / rates.imu_hz)
    dt = 1.0 / rates.truth_hz
    g_n = np.array([0.0, 0.0, STANDARD_GRAVITY_M_S2])
    f_b = np.einsum("nji,nj->ni", r_nb, motion.accel_n_m_s2 - g_n)
    gyro = np.stack([measure_gyro(c, motion.omega_b_rad_s[idx], rng_noise) for c in compasses])
    accel = np.stack([measure_accel(c, f_b[idx], rng_noise) for c in compasses])
    coloured = var.mag_ar1_sigma_mgauss > 0.0 or var.mag_rw_mgauss_per_sqrt_s > 0.0

    def extra(j: int) -> F64 | None:
        if not coloured:
            return None
        return coloured_noise(idx.size, step * dt, var.mag_ar1_sigma_mgauss, var.mag_ar1_tau_s,
                              var.mag_rw_mgauss_per_sqrt_s, rng_cnoise)  # fmt: skip

    mag = np.stack(
        [measure_mag(c, field_total_b[j, idx], rng_noise, extra(j)) for j, c in enumerate(compasses)]
    )
    if rates.mag_hz is not None:  # the compass updates at mag_hz; the autopilot holds its last value
        mag = mag[:, _hold_index(idx.size, rates.imu_hz, rates.mag_rate)]
    imu_temp = np.stack([power.temp_imu_degc[idx] + 0.7 * j for j in range(len(compasses))])
    imu_temp = np.round(imu_temp + rng_noise.normal(0.0, 0.05, imu_temp.shape), 2)
    return _Sensed(gyro, accel, mag, imu_temp)


def _autopilot_attitude(
    run: _Run,
    sensed: _Sensed,
    ap_cal: tuple[AutopilotCalibration, ...] | None,
    decl: float,
    rng_att: np.random.Generator,
) -> F64:
    """The simulated autopilot's attitude (roll, pitch, yaw rad) at the loop rows: its filter steered by
    the primary compass as it sees it (its own calibration, or the motor-off calibration), with the
    attitude knobs' biases and noise."""
    config, compasses, motion, _, idx = run
    var = config.variation
    step_dt = round(config.rates.truth_hz / config.rates.imu_hz) / config.rates.truth_hz
    mag = sensed.mag
    primary = var.primary_compass
    cp = compasses[primary]
    if ap_cal is not None:  # the autopilot steers by the field it logs: its own calibration, in float
        mag_ap = (mag[primary] - ap_cal[primary].b_ap_mgauss) @ ap_cal[primary].a_matrix.T
    else:
        mag_ap = np.linalg.solve(cp.k_matrix, (mag[primary] - cp.b_mgauss).T).T  # eq. (2), motor-off cal.
    yaw_ref = euler_from_quats(motion.q_nb[idx])[:, 2] if var.yaw_source == "truth" else None
    att_q = run_autopilot(
        motion.q_nb[0],
        sensed.gyro[0] - compasses[0].gyro_bias_rad_s,
        sensed.accel[0],
        mag_ap,
        motion.accel_n_m_s2[idx],
        step_dt,
        decl,
        AutopilotParams(kp_tilt=var.ap_kp_tilt, kp_yaw=var.ap_kp_yaw),
        yaw_ref_rad=yaw_ref,
    )
    attitude = euler_from_quats(att_q)
    att_bias = np.radians([var.att_roll_bias_deg, var.att_pitch_bias_deg, var.att_yaw_bias_deg])
    if att_bias.any() or var.att_noise_deg > 0.0:
        attitude = attitude + att_bias + rng_att.normal(0.0, math.radians(var.att_noise_deg), attitude.shape)
        attitude[:, 2] = (attitude[:, 2] + math.pi) % (2.0 * math.pi) - math.pi
        attitude[:, 1] = np.clip(attitude[:, 1], -math.pi / 2.0, math.pi / 2.0)
    return attitude  # type: ignore[no-any-return]


def _samples(
    run: _Run,
    sensed: _Sensed,
    ap_cal: tuple[AutopilotCalibration, ...] | None,
    attitude: F64,
    rng_noise: np.random.Generator,
) -> SimSamples:
    """What the autopilot reports at the loop rows, quantised as it sends it."""
    config, _, motion, power, idx = run
    mag = sensed.mag
    mag_sensor = None
    if ap_cal is not None:
        mag_sensor = mag
        logged = [(mag[j] - cal.b_ap_mgauss) @ cal.a_matrix.T for j, cal in enumerate(ap_cal)]
        mag = np.round(np.stack(logged))  # RAW_IMU carries whole mgauss
    gps: GpsTrack | None = None
    if config.gps:
        gps = _gps_track(config, motion.vel_n_m_s, motion.alt_m, 1.0 / config.rates.truth_hz, idx)
    voltage = np.round(power.voltage_v[idx] + rng_noise.normal(0.0, 0.01, idx.size), 3)
    noisy_current: F64 = power.current_a[idx] + rng_noise.normal(0.0, 0.05, idx.size)
    current = np.rint(np.maximum(noisy_current, 0.0) * 100.0) / 100.0  # 10 mA (cA in SYS_STATUS)
    vel = motion.vel_n_m_s[idx]
    return SimSamples(
        t_s=(config.t0_s + motion.t_s)[idx],
        truth_index=idx,
        gyro_rad_s=sensed.gyro,
        accel_m_s2=sensed.accel,
        mag_mgauss=mag,
        imu_temp_degc=sensed.imu_temp,
        throttle_01=quantize(motion.throttle_cmd_01[idx], 1e-3),
        motors_01=quantize(motion.motors_cmd_01[idx], 1e-3),
        voltage_v=voltage,
        current_a=current,
        attitude_rad=attitude,
        airspeed_m_s=motion.airspeed_m_s[idx],
        groundspeed_m_s=np.hypot(vel[:, 0], vel[:, 1]),
        alt_m=motion.alt_m[idx],
        climb_m_s=-vel[:, 2],
        mag_sensor_mgauss=mag_sensor,
        gps=gps,
    )


def _effect_params(
    effects: dict[str, float], compasses: Sequence[CompassTruth], pt_params: PowertrainParams
) -> dict[str, object]:
    """The effects' parameters as the truth files record them."""
    effect_params: dict[str, object] = {name: float(v) for name, v in effects.items()}
    if effects.get("temperature_drift", 0.0):
        effect_params["temperature_drift_dir"] = [c.drift_dir.tolist() for c in compasses]
        effect_params["temperature_ambient_degc"] = pt_params.ambient_degc
    if effects.get("per_motor", 0.0) > 0.0:
        effect_params["per_motor_theta_mgauss"] = [c.theta_motor_mgauss.tolist() for c in compasses]
    if "voltage_sag" in effects:
        effect_params["voltage_sag_reference_v"] = pt_params.v_full_v
    return effect_params


#: compass 0 as an external (GPS-mast) compass: this far from the power wires, theta falls as (r0 / r)^2
EXTERNAL_COMPASS_DISTANCE_M = 0.40


def _vary_compasses(config: SimConfig, compasses: tuple[CompassTruth, ...]) -> tuple[CompassTruth, ...]:
    """Apply the knobs that change the compasses themselves (layout, noise level, quantisation)."""
    var = config.variation
    out = list(compasses)
    if var.external_compass0:
        theta_cfg = np.asarray(config.theta_mgauss, dtype=float) * var.theta_scale
        r0, r_ext = compasses[0].distance_m, EXTERNAL_COMPASS_DISTANCE_M
        for j, (theta, dist) in enumerate([(theta_cfg * (r0 / r_ext) ** 2, r_ext), (theta_cfg, r0)]):
            c = out[j]
            size = max(float(np.linalg.norm(c.theta_mgauss)), 1e-12)
            spread = (c.theta_motor_mgauss - c.theta_mgauss) / size
            out[j] = dataclasses.replace(
                c,
                theta_mgauss=theta,
                theta_raw_mgauss=c.k_matrix @ theta,
                theta_motor_mgauss=theta + spread * float(np.linalg.norm(theta)),
                distance_m=dist,
            )
    if var.gyro_noise_scale != 1.0 or var.gyro_bias_scale != 1.0:
        out = [
            dataclasses.replace(
                c,
                gyro_noise_rad_s=c.gyro_noise_rad_s * var.gyro_noise_scale,
                gyro_bias_rad_s=c.gyro_bias_rad_s * var.gyro_bias_scale,
            )
            for c in out
        ]
    if var.mag_noise_scale != 1.0 or var.mag_lsb_mgauss is not None:
        out = [
            dataclasses.replace(
                c,
                noise_mgauss=c.noise_mgauss * var.mag_noise_scale,
                lsb_mgauss=c.lsb_mgauss if var.mag_lsb_mgauss is None else float(var.mag_lsb_mgauss),
            )
            for c in out
        ]
    return tuple(out)


def _hold_index(n: int, loop_hz: float, update_hz: float) -> NDArray[np.int64]:
    """Row of the last update (at k / update_hz) at or before each loop sample i / loop_hz."""
    t = np.arange(n) / loop_hz
    k = np.floor(t * update_hz + 1e-9)
    return np.minimum(np.floor(k / update_hz * loop_hz + 1e-9).astype(np.int64), n - 1)


EARTH_RADIUS_M = 6_378_137.0


def _gps_track(config: SimConfig, vel_n: F64, alt_m: F64, dt_s: float, idx: NDArray[np.int64]) -> GpsTrack:
    """Latitude/longitude from the integrated NED velocity around the configured location (flat-Earth
    local tangent plane: metres to degrees with the WGS-84 equatorial radius), altitude = location + climb."""
    pos = np.concatenate([np.zeros((1, 3)), np.cumsum(vel_n[:-1], axis=0) * dt_s])[idx]
    loc = config.location
    lat = loc.lat_deg + np.degrees(pos[:, 0] / EARTH_RADIUS_M)
    lon = loc.lon_deg + np.degrees(pos[:, 1] / (EARTH_RADIUS_M * math.cos(math.radians(loc.lat_deg))))
    return GpsTrack(lat_deg=lat, lon_deg=lon, alt_msl_m=loc.alt_m + alt_m[idx], vel_n_m_s=vel_n[idx])
