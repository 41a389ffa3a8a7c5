"""Powertrain: throttle -> ESC -> motor speed -> propeller torque -> current, battery, heat (eqs. (4)-(11)).

With every hidden effect off this reproduces the paper's chain exactly:
    speed_01 = delta_t                                   eq. (9)   (speed_01 = Omega / Omega_max)
    Q = C_Q rho Omega^2 D^5  and  Q_m = K_t I  at equilibrium  eqs. (8), (5a) -> I = I_max speed_01^2
    B = theta I / I_max = theta delta_t^2                eqs. (4), (10), (11)
so ``load_01`` (= I / I_max, what multiplies theta) is exactly ``throttle^2``.

The hidden effects (see :mod:`magcomp.sim.config`) enter here: ``time_skew`` shifts the throttle that acts,
``throttle_offset`` replaces eq. (9) by a dead band, ``voltage_sag`` scales speed by the battery voltage,
``current_lag`` low-passes the speed, ``throttle_exponent`` replaces the 2 of eq. (8), and ``per_motor``
splits the load per motor. The battery (open-circuit voltage falling with discharge, internal resistance)
and the powertrain temperature are always simulated, so the log carries them whether or not an effect uses
them.

Departure for multirotors without ``per_motor``: the load follows the collective throttle, i.e. the
attitude-control differentials are treated as current-neutral (the second-order sum of d_i^2 is dropped),
which keeps eq. (11) exact with the logged throttle.

Symbols: delta_t -> throttle (0..1); Omega/Omega_max -> speed_01; I -> current_a (A); V -> voltage_v (V).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.signal import lfilter

F64 = NDArray[np.float64]

# LiPo cell open-circuit voltage versus state of charge (typical discharge curve)
_SOC_POINTS = np.array([0.0, 0.05, 0.1, 0.2, 0.4, 0.6, 0.8, 0.9, 1.0])
_CELL_OCV_V = np.array([3.30, 3.55, 3.65, 3.72, 3.79, 3.87, 3.98, 4.07, 4.20])


@dataclass(frozen=True)
class PowertrainParams:
    """current_max_a: battery current at full throttle (all motors); capacity_ah, cells, soc0: battery;
    r_internal_ohm: pack resistance (sag = R I); ambient_degc; rise_full_degc: steady powertrain temperature
    rise at full current (heating ~ I^2); tau_thermal_s; imu_self_heat_degc and imu_coupling: the IMU
    temperature = ambient + self-heating + coupling * (powertrain rise)."""

    current_max_a: float = 20.0
    cells: int = 3
    capacity_ah: float = 2.2
    soc0: float = 0.95
    r_internal_ohm: float = 0.05
    ambient_degc: float = 22.0
    rise_full_degc: float = 40.0
    tau_thermal_s: float = 90.0
    imu_self_heat_degc: float = 8.0
    imu_coupling: float = 0.3

    @property
    def v_full_v(self) -> float:
        """Open-circuit voltage of the full pack: the reference of the ``voltage_sag`` effect."""
        return float(self.cells * _CELL_OCV_V[-1])


@dataclass(frozen=True)
class PowertrainTruth:
    """Arrays on the truth grid (n samples; k = 1, or 4 motors with ``per_motor``).

    throttle_acting_01 (n, k): command after the time skew; speed_01 (n, k): Omega / Omega_max;
    load_01 (n, k): per-branch current / branch share of I_max (multiplies theta);
    current_a, voltage_v, ocv_v, soc (n,): battery; temp_powertrain_degc, temp_imu_degc (n,).
    """

    throttle_acting_01: F64
    speed_01: F64
    load_01: F64
    current_a: F64
    voltage_v: F64
    ocv_v: F64
    soc: F64
    temp_powertrain_degc: F64
    temp_imu_degc: F64


def ocv_v(soc: F64, cells: int) -> F64:
    """Open-circuit pack voltage for a state of charge 0..1."""
    return cells * np.interp(np.clip(soc, 0.0, 1.0), _SOC_POINTS, _CELL_OCV_V)


def first_order_lag(x: F64, dt_s: float, tau_s: float) -> F64:
    """y' = (x - y) / tau, exact for x held over each step, y(0) = x(0); along axis 0."""
    if tau_s <= 0.0:
        return x.copy()
    a = math.exp(-dt_s / tau_s)
    zi = (a * x[0])[None, ...] if x.ndim > 1 else np.array([a * x[0]])
    y, _ = lfilter([1.0 - a], [1.0, -a], x, axis=0, zi=zi)
    return np.asarray(y)


def simulate_powertrain(
    t_s: F64, command_01: F64, dt_s: float, effects: dict[str, float], p: PowertrainParams
) -> PowertrainTruth:
    """Run the chain on ``command_01`` (n, k): the logged throttle (k = 1) or each motor output (k = 4).

    effects: name -> VALUE of the active hidden effects (missing -> off).
    """
    n, k = command_01.shape
    skew = effects.get("time_skew", 0.0)
    acting = command_01
    if skew != 0.0:  # field responds to the throttle logged skew_s earlier
        acting = np.stack([np.interp(t_s - skew, t_s, command_01[:, j]) for j in range(k)], axis=1)
    offset = effects.get("throttle_offset", 0.0)
    speed_cmd = np.clip((acting - offset) / (1.0 - offset), 0.0, 1.0)  # eq. (9); dead band if offset > 0
    sag = effects.get("voltage_sag", 0.0)
    tau = effects.get("current_lag", 0.0)
    exponent = effects.get("throttle_exponent", 2.0)
    share_a = p.current_max_a / k
    soc = np.full(n, p.soc0)
    voltage = ocv_v(soc, p.cells)
    speed = load = current = np.zeros((n, k))
    # the sag couples voltage and current: whole-trajectory fixed-point sweeps, under-relaxed (the map
    # V -> I -> V has slope -R dI/dV, negative and near -1 at high current), until the voltage that sets the
    # speed is the voltage the battery then shows (to 1 uV). Four plain sweeps, as before, left up to
    # ~0.5 V between the two at 80 A and biased a fitted sag strength by ~0.15.
    for sweep in range(200 if sag > 0.0 else 1):
        target = speed_cmd * (1.0 - sag + sag * voltage / p.v_full_v)[:, None]
        speed = first_order_lag(target, dt_s, tau)
        load = np.clip(speed, 0.0, None) ** exponent  # eqs. (8), (5a): I / I_max = speed^2
        current = share_a * load
        total = current.sum(axis=1)
        soc = p.soc0 - np.concatenate([[0.0], np.cumsum(total[:-1])]) * dt_s / (3600.0 * p.capacity_ah)
        new_v = ocv_v(soc, p.cells) - p.r_internal_ohm * total
        if sag == 0.0 or float(np.max(np.abs(new_v - voltage))) < 1e-6:
            voltage = new_v
            break
        voltage = new_v if sweep == 0 else 0.5 * (voltage + new_v)
    total = current.sum(axis=1)
    # powertrain temperature: T' = (rise_full (I / I_max)^2 - (T - T_amb)) / tau, exact per step
    a = math.exp(-dt_s / p.tau_thermal_s)
    heat = p.rise_full_degc * (total / p.current_max_a) ** 2
    rise, _ = lfilter([0.0, 1.0 - a], [1.0, -a], heat, zi=np.array([0.0]))
    temp_pt = p.ambient_degc + np.asarray(rise)
    temp_imu = p.ambient_degc + p.imu_self_heat_degc + p.imu_coupling * (temp_pt - p.ambient_degc)
    return PowertrainTruth(
        throttle_acting_01=acting,
        speed_01=speed,
        load_01=load,
        current_a=total,
        voltage_v=voltage,
        ocv_v=ocv_v(soc, p.cells),
        soc=soc,
        temp_powertrain_degc=temp_pt,
        temp_imu_degc=temp_imu,
    )
