"""``simulate(config, rng) -> SimResult``: truth and the autopilot's sensor samples for one scenario.

Reference: M. Silic and K. Mohseni, "Correcting Current-Induced Magnetometer Errors on UAVs: An Online
Model-Based Approach", IEEE Sensors J. 20(2), 2020; equation numbers as in that article.

Pipeline (pure: no I/O; the Earth field comes from :mod:`magcomp.geomag` unless the config gives one):
    motion (trajectory.py, exact SO(3) integration at truth_hz, eq. (18))
    -> powertrain (powertrain.py, eqs. (4)-(11) + hidden effects) -> bias per compass (eq. (11))
    -> sensors (sensors.py, eq. (1)) sampled at imu_hz -> autopilot attitude (autopilot.py)

Symbol table: theta -> CompassTruth.theta_mgauss (calibrated frame, mgauss); delta_t -> throttle_01;
B -> bias_mgauss (calibrated frame, mgauss, body); K, b -> k_matrix, b_mgauss (eq. (1)); u^e ->
earth_field_ned_mgauss (NED, mgauss).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from magcomp.core.heading import declination_rad
from magcomp.core.rotations import dcms_from_quats, euler_from_quats
from magcomp.core.types import STANDARD_GRAVITY_M_S2
from magcomp.sim.autopilot import AutopilotParams, run_autopilot
from magcomp.sim.config import SimConfig
from magcomp.sim.powertrain import PowertrainParams, PowertrainTruth, simulate_powertrain
from magcomp.sim.sensors import (
    CompassTruth,
    make_compasses,
    measure_accel,
    measure_gyro,
    measure_mag,
    quantize,
)
from magcomp.sim.trajectory import Motion, build_motion

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class SimSamples:
    """What the simulated autopilot reports, at imu_hz (n samples; J compasses / IMUs; m motors).

    Values are already quantised to the MAVLink units the emitter sends (gyro 1 mrad/s, accel 1 mG,
    mag 1 mgauss, motors 1 us of PWM, voltage 1 mV, current 10 mA), so a decoded log equals them.

    t_s (n,): boot clock; truth_index (n,): row of the truth arrays; gyro_rad_s, accel_m_s2, mag_mgauss
    (J, n, 3); imu_temp_degc (J, n); throttle_01 (n,) logged command; motors_01 (n, m); voltage_v,
    current_a (n,); attitude_rad (n, 3) autopilot roll, pitch, yaw; airspeed_m_s, groundspeed_m_s, alt_m,
    climb_m_s (n,).
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
    rates = config.rates
    dt = 1.0 / rates.truth_hz
    motion = build_motion(config.scenario, config.duration, config.vehicle, dt, rng_motion)
    n = motion.t_s.shape[0]
    t_s = config.t0_s + motion.t_s
    effects = dict(config.effects)
    per_motor = effects.get("per_motor", 0.0) > 0.0
    multirotor = config.vehicle == "multirotor"

    compasses = make_compasses(
        config.n_compasses,
        np.asarray(config.theta_mgauss, dtype=float),
        motion.motors_cmd_01.shape[1],
        effects.get("per_motor", 0.0),
        rng_params,
    )
    pt_params = PowertrainParams(current_max_a=40.0 if multirotor else 20.0)
    command = motion.motors_cmd_01 if per_motor else motion.throttle_cmd_01[:, None]
    power = simulate_powertrain(motion.t_s, command, dt, effects, pt_params)

    # eq. (11): B_j = theta_j * load (load = throttle^2 with no effect); per motor: sum_i theta_ij load_i / k
    k = power.load_01.shape[1]
    bias = np.stack([power.load_01 @ c.theta_motor_mgauss / k for c in compasses])  # eq. (11)
    drift_k = effects.get("temperature_drift", 0.0)
    dtemp = power.temp_powertrain_degc - pt_params.ambient_degc
    drift = np.stack([drift_k * dtemp[:, None] * c.drift_dir[None, :] for c in compasses])

    m_n = _earth_field(config)
    r_nb = dcms_from_quats(motion.q_nb)
    field_b = np.einsum("nji,j->ni", r_nb, m_n)  # u = R_nb^T m_n
    g_n = np.array([0.0, 0.0, STANDARD_GRAVITY_M_S2])
    f_b = np.einsum("nji,nj->ni", r_nb, motion.accel_n_m_s2 - g_n)

    step = round(rates.truth_hz / rates.imu_hz)
    idx = np.arange(0, n, step)
    gyro = np.stack([measure_gyro(c, motion.omega_b_rad_s[idx], rng_noise) for c in compasses])
    accel = np.stack([measure_accel(c, f_b[idx], rng_noise) for c in compasses])
    mag = np.stack(
        [
            measure_mag(c, field_b[idx] + bias[j, idx] + drift[j, idx], rng_noise)
            for j, c in enumerate(compasses)
        ]
    )
    imu_temp = np.stack([power.temp_imu_degc[idx] + 0.7 * j for j in range(len(compasses))])
    imu_temp = np.round(imu_temp + rng_noise.normal(0.0, 0.05, imu_temp.shape), 2)

    c0 = compasses[0]
    mag_cal0 = np.linalg.solve(c0.k_matrix, (mag[0] - c0.b_mgauss).T).T  # eq. (2), motor-off calibration
    decl = declination_rad(m_n)
    att_q = run_autopilot(
        motion.q_nb[0],
        gyro[0] - c0.gyro_bias_rad_s,
        accel[0],
        mag_cal0,
        motion.accel_n_m_s2[idx],
        step * dt,
        decl,
        AutopilotParams(),
    )
    attitude = euler_from_quats(att_q)

    voltage = np.round(power.voltage_v[idx] + rng_noise.normal(0.0, 0.01, idx.size), 3)
    noisy_current: F64 = power.current_a[idx] + rng_noise.normal(0.0, 0.05, idx.size)
    current = np.rint(np.maximum(noisy_current, 0.0) * 100.0) / 100.0  # 10 mA (cA in SYS_STATUS)
    vel = motion.vel_n_m_s[idx]
    samples = SimSamples(
        t_s=t_s[idx],
        truth_index=idx,
        gyro_rad_s=gyro,
        accel_m_s2=accel,
        mag_mgauss=mag,
        imu_temp_degc=imu_temp,
        throttle_01=quantize(motion.throttle_cmd_01[idx], 1e-3),
        motors_01=quantize(motion.motors_cmd_01[idx], 1e-3),
        voltage_v=voltage,
        current_a=current,
        attitude_rad=attitude,
        airspeed_m_s=motion.airspeed_m_s[idx],
        groundspeed_m_s=np.hypot(vel[:, 0], vel[:, 1]),
        alt_m=motion.alt_m[idx],
        climb_m_s=-vel[:, 2],
    )
    effect_params: dict[str, object] = {name: float(v) for name, v in effects.items()}
    if drift_k:
        effect_params["temperature_drift_dir"] = [c.drift_dir.tolist() for c in compasses]
        effect_params["temperature_ambient_degc"] = pt_params.ambient_degc
    if per_motor:
        effect_params["per_motor_theta_mgauss"] = [c.theta_motor_mgauss.tolist() for c in compasses]
    if "voltage_sag" in effects:
        effect_params["voltage_sag_reference_v"] = pt_params.v_full_v
    return SimResult(
        config=config,
        t_s=t_s,
        motion=motion,
        power=power,
        compasses=compasses,
        bias_mgauss=bias,
        drift_mgauss=drift,
        field_earth_b_mgauss=field_b,
        earth_field_ned_mgauss=m_n,
        declination_deg=math.degrees(decl),
        samples=samples,
        effect_params=effect_params,
    )
