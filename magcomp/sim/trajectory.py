"""Truth motion and throttle command of each scenario, integrated exactly on SO(3).

Every scenario yields body rates ``omega_b_rad_s`` held constant over each truth step; the attitude is
``q_nb[k+1] = q_nb[k] * exp(omega_b[k] dt)`` (strap-down eq. (18) in closed form,
:func:`magcomp.core.rotations.quat_integrate_body_rate`). Flight profiles are first written as Euler angles
and turned into the body rates that reproduce them, then integrated the same way.

Scenarios (the paper's experiments, sec. III):
    tumble  hand rotation covering the sphere, motor off (calibration data, sec. III-A / Fig. 5)
    spin    hand rotation at full throttle (online estimation, Fig. 8)
    pan     level, full throttle, panned through 360 deg (Fig. 9a)
    ramp    fixed orientation, throttle 0 -> 100 % (Fig. 9b)
    step    fixed orientation, throttle step 0 -> 100 % at t = 4 s (Fig. 9c)
    bench   stationary throttle staircase up and down, twice (Fig. 7 / Table II)
    flight  fixed-wing or multirotor flight with turns, climbs and throttle changes
    paper   tumble, spin, pan, ramp and step in one run (the paper's whole experiment)
    ordinary  an ordinary multirotor flight (issue 9): motors off on the ground briefly, take-off, hover,
            full 360 deg yaw turns at hover and circles in forward flight, climbs and descents, forward
            flight tilted 10-25 deg by drag and turns, landing; no hand rotation
    ordinary_plane  the same for a fixed wing: take-off roll, climb, cruise, loiter circles (full 360 deg
            turns both ways), climbing turn, glide, landing and roll-out
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from magcomp.core.rotations import quat_from_euler, quat_integrate_body_rate, quats_from_euler, quats_multiply
from magcomp.core.types import STANDARD_GRAVITY_M_S2

F64 = NDArray[np.float64]
# heading of the fixed-orientation scenarios (ramp, step, bench, pan start): with the default theta and
# location the bias is then nearly square to the horizontal field, the worst case of Fig. 9b/c
FIXED_HEADING_RAD = math.radians(110.0)
STEP_TIME_S = 4.0  # Fig. 9c
TRANSITION_S = 2.0

# ArduPilot quad-X motor order (SERVO1..4 = motor 1..4: front right, back left, front left, back right):
# roll / pitch / yaw mixing factors.
QUAD_MIX = np.array(
    [  # roll, pitch, yaw
        [-0.5, 0.5, 1.0],
        [0.5, -0.5, 1.0],
        [0.5, 0.5, -1.0],
        [-0.5, -0.5, -1.0],
    ]
)


@dataclass(frozen=True)
class Motion:
    """Truth on the truth grid, n samples at ``dt_s``; ``t_s`` is scenario time (0 at the start).

    omega_b_rad_s (n, 3): body rate held over [t_k, t_k + dt); q_nb (n, 4): attitude (w, x, y, z)
    accel_n_m_s2 / vel_n_m_s (n, 3): kinematic acceleration / velocity, NED; alt_m (n,): altitude
    throttle_cmd_01 (n,): the throttle command the autopilot logs (collective for a multirotor)
    motors_cmd_01 (n, m): each motor's output (m = 1 fixed-wing, 4 multirotor)
    airspeed_m_s (n,); segment (n,) int index into ``segment_names``
    """

    dt_s: float
    t_s: F64
    omega_b_rad_s: F64
    q_nb: F64
    accel_n_m_s2: F64
    vel_n_m_s: F64
    alt_m: F64
    throttle_cmd_01: F64
    motors_cmd_01: F64
    airspeed_m_s: F64
    segment: NDArray[np.int64]
    segment_names: tuple[str, ...]


def _smoothstep(x: F64) -> F64:
    """0 -> 1 with zero slope at both ends: s(x) = x - sin(2 pi x) / (2 pi), x in [0, 1]."""
    x = np.clip(x, 0.0, 1.0)
    return x - np.sin(2.0 * np.pi * x) / (2.0 * np.pi)


def rates_from_quat_path(q_nb: F64, dt_s: float) -> F64:
    """Body rates that carry q[k] to q[k+1] in one step (last row repeats the previous one)."""
    dq = quats_multiply(q_nb[:-1] * np.array([1.0, -1.0, -1.0, -1.0]), q_nb[1:])
    dq = dq * np.where(dq[:, :1] < 0.0, -1.0, 1.0)
    vn = np.linalg.norm(dq[:, 1:], axis=1)
    angle = 2.0 * np.arctan2(vn, dq[:, 0])
    scale = np.where(vn > 1e-15, angle / np.maximum(vn, 1e-300), 2.0)
    omega = dq[:, 1:] * scale[:, None] / dt_s
    return np.vstack([omega, omega[-1:]]) if omega.shape[0] else np.zeros((1, 3))


def integrate_attitude(q0_nb: F64, omega_b_rad_s: F64, dt_s: float) -> F64:
    """Exact SO(3) integration, eq. (18): q[k+1] = q[k] * exp(omega[k] dt). Returns (n, 4)."""
    n = omega_b_rad_s.shape[0]
    q = np.empty((n, 4))
    q[0] = q0_nb
    for k in range(n - 1):
        q[k + 1] = quat_integrate_body_rate(q[k], omega_b_rad_s[k], dt_s)  # eq. (18)
    return q


def _hand_rotation(n: int, dt_s: float, rng: np.random.Generator, rms_rad_s: float) -> F64:
    """Smooth random body rates of a vehicle turned by hand (a few incommensurate sinusoids per axis),
    faded in and out over 1 s so that the motion starts and ends at rest."""
    t = np.arange(n) * dt_s
    omega = np.zeros((n, 3))
    for axis in range(3):
        freqs = rng.uniform(0.04, 0.35, size=4)
        phases = rng.uniform(0.0, 2.0 * np.pi, size=4)
        amps = rng.uniform(0.5, 1.0, size=4)
        amps *= rms_rad_s * math.sqrt(2.0) / float(np.linalg.norm(amps))
        omega[:, axis] = (amps[None, :] * np.sin(2 * np.pi * freqs[None, :] * t[:, None] + phases)).sum(
            axis=1
        )
    duration = n * dt_s
    fade = np.clip(np.minimum(t, duration - t) / 1.0, 0.0, 1.0)
    return omega * _smoothstep(fade)[:, None]


def _rotate_to(q_from: F64, q_to: F64, n: int) -> F64:
    """Per-step rotation vectors (body) turning q_from into q_to about one fixed body axis, smoothly."""
    dq = quats_multiply((q_from * np.array([1.0, -1.0, -1.0, -1.0]))[None, :], q_to[None, :])[0]
    if dq[0] < 0:
        dq = -dq
    vn = float(np.linalg.norm(dq[1:]))
    phi = np.zeros(3) if vn < 1e-15 else dq[1:] / vn * 2.0 * math.atan2(vn, dq[0])
    s = _smoothstep(np.arange(n + 1) / n)
    return np.diff(s)[:, None] * phi[None, :]


class _Builder:
    """Appends segments (body-rate increments + throttle) and integrates the attitude as it goes."""

    def __init__(self, dt_s: float, q0_nb: F64) -> None:
        self.dt = dt_s
        self.q = q0_nb
        self.omega: list[F64] = []
        self.quats: list[F64] = []
        self.thr: list[F64] = []
        self.seg: list[NDArray[np.int64]] = []
        self.names: list[str] = []

    def add(self, name: str, omega_b: F64, throttle: F64) -> None:
        n = omega_b.shape[0]
        q = np.empty((n, 4))
        qk = self.q
        for k in range(n):
            q[k] = qk
            qk = quat_integrate_body_rate(qk, omega_b[k], self.dt)  # eq. (18)
        self.q = qk
        self.omega.append(omega_b)
        self.quats.append(q)
        self.thr.append(throttle)
        self.seg.append(np.full(n, len(self.names), dtype=np.int64))
        self.names.append(name)

    def n_of(self, duration_s: float) -> int:
        return max(2, round(duration_s / self.dt))

    def rotate_to(self, name: str, q_target: F64, duration_s: float, throttle: float = 0.0) -> None:
        n = self.n_of(duration_s)
        self.add(name, _rotate_to(self.q, q_target, n) / self.dt, np.full(n, throttle))

    def hold(self, name: str, throttle: F64) -> None:
        self.add(name, np.zeros((throttle.shape[0], 3)), throttle)

    def pan(self, duration_s: float, throttle: float) -> None:
        """Level, yawed once through 360 deg with a smooth start and stop (Fig. 9a)."""
        n = self.n_of(duration_s)
        dpsi = 2.0 * np.pi * np.diff(_smoothstep(np.arange(n + 1) / n))
        omega = np.zeros((n, 3))
        omega[:, 2] = dpsi / self.dt  # level: body z is down, so a yaw rate is a body-z rate
        self.add("pan", omega, np.full(n, throttle))

    def motion(self, vehicle: str) -> Motion:
        omega = np.vstack(self.omega)
        q = np.vstack(self.quats)
        thr = np.concatenate(self.thr)
        n = thr.shape[0]
        zeros = np.zeros((n, 3))
        return Motion(
            dt_s=self.dt,
            t_s=np.arange(n, dtype=np.float64) * self.dt,
            omega_b_rad_s=omega,
            q_nb=q,
            accel_n_m_s2=zeros,
            vel_n_m_s=zeros.copy(),
            alt_m=np.zeros(n),
            throttle_cmd_01=thr,
            motors_cmd_01=_motors(thr, omega, self.dt, vehicle),
            airspeed_m_s=np.zeros(n),
            segment=np.concatenate(self.seg),
            segment_names=tuple(self.names),
        )


def _motors(throttle: F64, omega_b: F64, dt_s: float, vehicle: str) -> F64:
    """Motor outputs: the throttle itself (fixed wing), or quad-X mixing of the collective throttle with
    the attitude controller's roll/pitch/yaw demands (proportional to angular acceleration and yaw rate)."""
    if vehicle != "multirotor":
        return throttle[:, None].copy()
    alpha = np.gradient(omega_b, dt_s, axis=0)
    demand = np.stack(
        [0.04 * alpha[:, 0], 0.04 * alpha[:, 1], 0.15 * omega_b[:, 2] + 0.05 * alpha[:, 2]], axis=1
    )
    diff = np.clip(demand @ QUAD_MIX.T, -0.15, 0.15)
    on = (throttle > 0.0)[:, None]  # motors stopped: no mixing
    return np.clip(throttle[:, None] + diff * on, 0.0, 1.0)


def _level(yaw_rad: float) -> F64:
    return quat_from_euler(0.0, 0.0, yaw_rad)


def _staircase(n: int, dt_s: float) -> F64:
    """Throttle 0, 0.1, ..., 1.0, ..., 0.1, 0 held in equal steps, twice (bench sweep, Fig. 7)."""
    levels = np.round(np.concatenate([np.arange(0, 11), np.arange(9, -1, -1)]) * 0.1, 10)
    levels = np.concatenate([levels, levels[1:]])
    idx = np.minimum((np.arange(n) * levels.size) // n, levels.size - 1)
    return levels[idx]


def build_motion(
    scenario: str,
    duration_s: float,
    vehicle: str,
    dt_s: float,
    rng: np.random.Generator,
    hover_throttle: float | None = None,
) -> Motion:
    """Truth motion and throttle for one scenario (see the module docstring). ``hover_throttle``: the
    multirotor's hover collective in the ``ordinary`` scenario (None: HOVER_THROTTLE)."""
    if scenario == "ordinary":
        return _ordinary_multirotor(
            duration_s, dt_s, rng, HOVER_THROTTLE if hover_throttle is None else hover_throttle
        )
    if scenario == "ordinary_plane":
        return _ordinary_fixedwing(duration_s, dt_s, rng)
    if scenario == "flight":
        return (
            _flight_multirotor(duration_s, dt_s)
            if vehicle == "multirotor"
            else _flight_fixedwing(duration_s, dt_s)
        )
    q_fixed = _level(FIXED_HEADING_RAD)
    if scenario in ("tumble", "spin"):
        b = _Builder(dt_s, _level(0.0))
        n = b.n_of(duration_s)
        b.add(scenario, _hand_rotation(n, dt_s, rng, 1.0), np.full(n, 0.0 if scenario == "tumble" else 1.0))
    elif scenario == "pan":
        b = _Builder(dt_s, q_fixed)
        b.pan(duration_s, 1.0)
    elif scenario == "ramp":
        b = _Builder(dt_s, q_fixed)
        n = b.n_of(duration_s)
        t = np.arange(n) * dt_s
        b.hold("ramp", np.clip((t - 1.0) / max(duration_s - 2.0, dt_s), 0.0, 1.0))
    elif scenario == "step":
        b = _Builder(dt_s, q_fixed)
        n = b.n_of(duration_s)
        b.hold("step", np.where(np.arange(n) * dt_s >= STEP_TIME_S, 1.0, 0.0))
    elif scenario == "bench":
        b = _Builder(dt_s, q_fixed)
        n = b.n_of(duration_s)
        b.hold("bench", _staircase(n, dt_s))
    elif scenario == "paper":
        b = _paper(duration_s, dt_s, rng)
    else:  # pragma: no cover - SimConfig validates the name
        raise ValueError(scenario)
    return b.motion(vehicle)


def _paper(duration_s: float, dt_s: float, rng: np.random.Generator) -> _Builder:
    """tumble 40, spin 40, pan 20, ramp 15, step 10 s (scaled to the duration) with 2 s transitions."""
    fixed = 4 * TRANSITION_S
    scale = max(duration_s - fixed, 10.0) / (133.0 - fixed)
    b = _Builder(dt_s, _level(0.0))
    n = b.n_of(40.0 * scale)
    b.add("tumble", _hand_rotation(n, dt_s, rng, 1.0), np.zeros(n))
    b.rotate_to("transition", _level(1.2), TRANSITION_S)
    n = b.n_of(40.0 * scale)
    b.add("spin", _hand_rotation(n, dt_s, rng, 1.0), np.ones(n))
    b.rotate_to("transition", _level(FIXED_HEADING_RAD), TRANSITION_S)
    b.pan(20.0 * scale, 1.0)
    b.hold("rest", np.zeros(b.n_of(TRANSITION_S)))
    n = b.n_of(15.0 * scale)
    t = np.arange(n) * dt_s
    b.hold("ramp", np.clip((t - 1.0) / max(15.0 * scale - 2.0, dt_s), 0.0, 1.0))
    b.hold("rest", np.zeros(b.n_of(TRANSITION_S)))
    n = b.n_of(max(10.0 * scale, STEP_TIME_S + 2.0))
    b.hold("step", np.where(np.arange(n) * dt_s >= STEP_TIME_S, 1.0, 0.0))
    return b


def _smooth(x: F64, dt_s: float, window_s: float) -> F64:
    """Zero-phase moving average (Hann window) with edge padding: smooth phase changes of a profile."""
    m = max(3, round(window_s / dt_s) | 1)
    w = np.hanning(m + 2)[1:-1]
    w = w / w.sum()
    pad = m // 2
    xp = np.concatenate([np.full(pad, x[0]), x, np.full(pad, x[-1])])
    return np.convolve(xp, w, mode="valid")


def _phases(duration_s: float, dt_s: float, table: Sequence[tuple[float, ...]]) -> tuple[F64, ...]:
    """Piecewise-constant columns of ``table`` (rows: fraction of duration, values...) on the grid."""
    n = max(2, round(duration_s / dt_s))
    frac = np.array([row[0] for row in table])
    edges = np.concatenate([[0.0], np.cumsum(frac / frac.sum())]) * n
    idx = np.searchsorted(edges[1:], np.arange(n), side="right")
    idx = np.minimum(idx, len(table) - 1)
    values = np.array([row[1:] for row in table])
    return tuple(values[idx, j] for j in range(values.shape[1]))


def _finish_path(
    dt_s: float, roll: F64, pitch: F64, yaw: F64, vel_n: F64, alt: F64, thr: F64, airspeed: F64, vehicle: str
) -> Motion:
    q_path = quats_from_euler(roll, pitch, yaw)
    omega = rates_from_quat_path(q_path, dt_s)
    q = integrate_attitude(q_path[0], omega, dt_s)  # eq. (18): the truth is the integrated attitude
    n = thr.shape[0]
    return Motion(
        dt_s=dt_s,
        t_s=np.arange(n, dtype=np.float64) * dt_s,
        omega_b_rad_s=omega,
        q_nb=q,
        accel_n_m_s2=np.gradient(vel_n, dt_s, axis=0),
        vel_n_m_s=vel_n,
        alt_m=alt,
        throttle_cmd_01=thr,
        motors_cmd_01=_motors(thr, omega, dt_s, vehicle),
        airspeed_m_s=airspeed,
        segment=np.zeros(n, dtype=np.int64),
        segment_names=(f"flight_{vehicle}",),
    )


def _flight_fixedwing(duration_s: float, dt_s: float) -> Motion:
    """Hand-launched delta wing: climb, cruise, turns both ways, climbing turn, descent, 360 turn, glide.
    Coordinated turns (roll = atan(V psi_dot / g)), pitch = flight-path angle + 3.4 deg of incidence."""
    table = [  # fraction, throttle, turn rate deg/s, climb m/s
        (0.12, 1.0, 0.0, 3.0),
        (0.10, 0.6, 0.0, 0.0),
        (0.12, 0.65, -15.0, 0.0),
        (0.08, 0.55, 0.0, 0.0),
        (0.12, 0.9, 18.0, 2.0),
        (0.08, 0.5, 0.0, 0.0),
        (0.12, 0.15, 0.0, -2.5),
        (0.14, 0.6, 25.0, 0.0),
        (0.12, 0.0, 0.0, -1.5),
    ]
    thr_raw, turn_deg_s, climb = _phases(duration_s, dt_s, table)
    thr = np.clip(_smooth(thr_raw, dt_s, 0.4), 0.0, 1.0)
    psi_dot = np.radians(_smooth(turn_deg_s, dt_s, 2.0))
    climb = _smooth(climb, dt_s, 2.0)
    # airspeed follows throttle with a 3 s lag: 10 m/s gliding .. 18 m/s at full power
    a = dt_s / 3.0
    v = np.empty_like(thr)
    v[0] = 14.0
    target = 10.0 + 8.0 * thr
    for k in range(1, v.size):
        v[k] = v[k - 1] + a * (target[k - 1] - v[k - 1])
    yaw = np.cumsum(psi_dot) * dt_s
    gamma = np.arcsin(np.clip(climb / v, -0.5, 0.5))
    roll = np.arctan(v * psi_dot / STANDARD_GRAVITY_M_S2)
    pitch = gamma + 0.06
    vel = v[:, None] * np.stack([np.cos(gamma) * np.cos(yaw), np.cos(gamma) * np.sin(yaw), -np.sin(gamma)], 1)
    alt = 30.0 - np.cumsum(vel[:, 2]) * dt_s
    return _finish_path(dt_s, roll, pitch, yaw, vel, alt, thr, v, "fixedwing")


def _flight_multirotor(duration_s: float, dt_s: float) -> Motion:
    """Quad: take-off, hover, forward flight with yaw turns, climb, descent and landing. Tilt follows the
    thrust needed for the acceleration; collective throttle = hover throttle * sqrt(|thrust| / g)."""
    table = [  # fraction, forward speed m/s, yaw rate deg/s, climb m/s
        (0.08, 0.0, 0.0, 2.0),
        (0.08, 0.0, 0.0, 0.0),
        (0.10, 0.0, 45.0, 0.0),
        (0.14, 7.0, 0.0, 0.0),
        (0.12, 6.0, 25.0, 1.0),
        (0.12, 8.0, -30.0, 0.0),
        (0.10, 0.0, 0.0, 0.0),
        (0.12, 3.0, 0.0, -1.5),
        (0.14, 0.0, 0.0, -1.0),
    ]
    u, yaw_rate_deg_s, climb = _phases(duration_s, dt_s, table)
    u = _smooth(u, dt_s, 3.0)
    yaw = np.cumsum(np.radians(_smooth(yaw_rate_deg_s, dt_s, 1.5))) * dt_s
    climb = _smooth(climb, dt_s, 1.5)
    vel = np.stack([u * np.cos(yaw), u * np.sin(yaw), -climb], axis=1)
    acc = np.gradient(vel, dt_s, axis=0)
    f_n = acc - np.array([0.0, 0.0, STANDARD_GRAVITY_M_S2])  # specific force the thrust must provide, NED
    d = -f_n / np.linalg.norm(f_n, axis=1, keepdims=True)  # body z axis in NED
    cy, sy = np.cos(yaw), np.sin(yaw)
    d_h = np.stack([cy * d[:, 0] + sy * d[:, 1], -sy * d[:, 0] + cy * d[:, 1], d[:, 2]], axis=1)
    roll = -np.arcsin(np.clip(d_h[:, 1], -1.0, 1.0))
    pitch = np.arctan2(d_h[:, 0], d_h[:, 2])
    hover = 0.5
    g_load = np.linalg.norm(f_n, axis=1) / STANDARD_GRAVITY_M_S2
    thr = np.clip(hover * np.sqrt(g_load) + 0.03 * climb, 0.0, 0.95)
    alt = np.cumsum(climb) * dt_s
    return _finish_path(dt_s, roll, pitch, yaw, vel, alt, thr, np.abs(u), "multirotor")


# ordinary flight: (name, duration s, forward speed m/s, full yaw turns (signed), climb m/s)
ORDINARY_PLAN: tuple[tuple[str, float, float, float, float], ...] = (
    ("ground_off", 4.0, 0.0, 0.0, 0.0),
    ("ground_idle", 2.0, 0.0, 0.0, 0.0),
    ("takeoff", 8.0, 0.0, 0.0, 2.5),
    ("hover", 10.0, 0.0, 0.0, 0.0),
    ("hover_yaw", 36.0, 0.0, 3.0, 0.0),
    ("hover", 5.0, 0.0, 0.0, 0.0),
    ("cruise", 25.0, 9.0, 0.0, 0.0),
    ("circles", 40.0, 8.0, 2.0, 0.0),
    ("climb_forward", 15.0, 6.0, 0.0, 3.0),
    ("cruise_fast", 20.0, 10.0, 0.0, 0.0),
    ("circles", 36.0, 8.0, -2.0, 0.0),
    ("descent_forward", 20.0, 5.0, 0.0, -2.0),
    ("hover", 8.0, 0.0, 0.0, 0.0),
    ("climb", 10.0, 0.0, 0.0, 4.0),
    ("hover_yaw", 18.0, 0.0, -2.0, 0.0),
    ("descent", 18.0, 0.0, 0.0, -2.5),
    ("landing", 20.0, 0.0, 0.0, -1.0),
    ("ground_idle", 3.0, 0.0, 0.0, 0.0),
    ("ground_off", 3.0, 0.0, 0.0, 0.0),
)
ORDINARY_NOMINAL_S = sum(row[1] for row in ORDINARY_PLAN)
HOVER_THROTTLE = 0.5
IDLE_THROTTLE = 0.15  # ArduCopter's MOT_SPIN_ARM-like idle on the ground before take-off / after landing
CLIMB_THROTTLE_PER_M_S = 0.055  # extra collective per m/s of climb (induced + vertical drag), empirical
DRAG_PER_M = 0.036  # horizontal drag acceleration = DRAG_PER_M * v^2: tilt 16 deg at 9 m/s, 20 at 10 m/s


class _Plan(NamedTuple):
    """A flight plan laid out on the rows of a run: each row's segment, speed, climb rate and yaw rate."""

    names: tuple[str, ...]  # the plan's segment names, first appearance first
    seg: NDArray[np.int64]  # index into ``names``
    speed: F64  # m/s
    climb: F64  # m/s
    yaw_rate: F64  # rad/s
    spans: list[tuple[tuple[Any, ...], int, int]]  # (plan row, first row, end row) of each non-empty segment


def _lay_out(plan: Sequence[tuple[Any, ...]], duration_s: float, dt_s: float) -> _Plan:
    """Rows of (name, nominal duration s, speed, full turns, climb, ...): durations scaled to ``duration_s``,
    the number of full yaw turns kept (at least one per turning segment), speeds and climb rates kept."""
    scale = duration_s / sum(row[1] for row in plan)
    n = max(2, round(duration_s / dt_s))
    names = tuple(dict.fromkeys(row[0] for row in plan))
    durs = np.array([row[1] for row in plan]) * scale
    edges = np.round(np.concatenate([[0.0], np.cumsum(durs)]) / dt_s).astype(np.int64)
    edges[-1] = n
    out = _Plan(names, np.zeros(n, dtype=np.int64), np.zeros(n), np.zeros(n), np.zeros(n), [])
    for row, a, b in zip(plan, edges[:-1], edges[1:], strict=True):
        if b <= a:
            continue
        name, _, speed, turns, vz = row[:5]
        out.seg[a:b] = names.index(name)
        out.speed[a:b] = speed
        out.climb[a:b] = vz
        if turns:
            k = math.copysign(max(1.0, round(abs(turns) * scale)), turns)
            out.yaw_rate[a:b] = 2.0 * math.pi * k / ((b - a) * dt_s)
        out.spans.append((row, int(a), int(b)))
    return out


def _ordinary_multirotor(duration_s: float, dt_s: float, rng: np.random.Generator, hover: float) -> Motion:
    """Ordinary multirotor flight (see ORDINARY_PLAN): segment durations scale with ``duration_s`` (nominal
    301 s); the number of full yaw turns is kept (at least one per turning segment), speeds and climb rates
    are kept, so altitudes scale. Tilt comes from the thrust needed against gravity, drag (v^2) and the
    turn's centripetal acceleration; collective = hover * sqrt(|thrust| / g) + climb term + a small gusty
    component (+-0.02, seeded). Velocity is along the heading (circles turn the vehicle through 360 deg).
    Ends on the ground at the altitude it started from."""
    plan = _lay_out(ORDINARY_PLAN, duration_s, dt_s)
    names, seg, u, climb, yaw_rate = plan.names, plan.seg, plan.speed, plan.climb, plan.yaw_rate
    n = seg.size
    ground = np.zeros(n, dtype=bool)
    off = np.zeros(n, dtype=bool)
    for row, a, b in plan.spans:
        ground[a:b] = row[0].startswith("ground")
        off[a:b] = row[0] == "ground_off"
    u = _smooth(u, dt_s, 6.0)
    # no climb within 1 s of the ground phases, so that the smoothed climb is zero where it meets them
    near_ground = np.convolve(ground.astype(float), np.ones(2 * round(1.0 / dt_s) + 1), mode="same") > 0
    climb[near_ground] = 0.0
    climb = _smooth(climb, dt_s, 2.0)
    climb[ground] = 0.0
    yaw_rate = _smooth(yaw_rate, dt_s, 1.5)
    yaw = math.radians(40.0) + np.cumsum(yaw_rate) * dt_s
    alt = np.cumsum(climb) * dt_s
    # land exactly where it took off: spread the (smoothing) altitude residual over the descents
    desc = climb < 0.0
    if desc.any() and alt[-1] != 0.0:
        climb[desc] -= alt[-1] / (desc.sum() * dt_s)
        alt = np.maximum(np.cumsum(climb) * dt_s, 0.0)
    vel = np.stack([u * np.cos(yaw), u * np.sin(yaw), -climb], axis=1)
    acc = np.gradient(vel, dt_s, axis=0)
    drag = DRAG_PER_M * np.abs(u)[:, None] * vel * np.array([1.0, 1.0, 0.0])
    f_n = acc + drag - np.array([0.0, 0.0, STANDARD_GRAVITY_M_S2])  # specific force the thrust provides
    f_n[ground] = np.array([0.0, 0.0, -STANDARD_GRAVITY_M_S2])  # on the ground: level, at rest
    d = -f_n / np.linalg.norm(f_n, axis=1, keepdims=True)  # body z axis in NED
    cy, sy = np.cos(yaw), np.sin(yaw)
    d_h = np.stack([cy * d[:, 0] + sy * d[:, 1], -sy * d[:, 0] + cy * d[:, 1], d[:, 2]], axis=1)
    # wind: a slow, seeded wobble of about 1.5 deg rms in roll and pitch while airborne
    wobble = np.stack([_smooth(rng.normal(0.0, 1.0, n), dt_s, 2.0) for _ in range(2)], axis=1)
    wobble *= math.radians(1.5) / np.maximum(wobble.std(axis=0), 1e-12)
    wobble[ground] = 0.0
    wobble = np.stack([_smooth(wobble[:, i], dt_s, 1.0) for i in range(2)], axis=1)
    roll = _smooth(-np.arcsin(np.clip(d_h[:, 1], -1.0, 1.0)), dt_s, 0.5) + wobble[:, 0]
    pitch = _smooth(np.arctan2(d_h[:, 0], d_h[:, 2]), dt_s, 0.5) + wobble[:, 1]
    g_load = np.linalg.norm(f_n, axis=1) / STANDARD_GRAVITY_M_S2
    gust = _smooth(rng.normal(0.0, 1.0, n), dt_s, 1.0)
    gust *= 0.02 / max(float(np.std(gust)), 1e-12)
    thr = hover * np.sqrt(g_load) + CLIMB_THROTTLE_PER_M_S * climb + np.clip(gust, -0.04, 0.04)
    thr = np.where(ground, IDLE_THROTTLE, thr)
    thr = np.where(off, 0.0, _smooth(thr, dt_s, 0.5))
    thr = np.clip(thr, 0.0, 0.95)
    motion = _finish_path(dt_s, roll, pitch, yaw, vel, alt, thr, np.abs(u), "multirotor")
    return dataclasses.replace(motion, segment=seg, segment_names=names)


# ordinary plane flight: (name, duration s, airspeed m/s, full turns (signed), climb m/s, throttle)
ORDINARY_PLANE_PLAN: tuple[tuple[str, float, float, float, float, float], ...] = (
    ("ground_off", 4.0, 0.0, 0.0, 0.0, 0.0),
    ("takeoff_roll", 6.0, 14.0, 0.0, 0.0, 1.0),
    ("climb", 25.0, 15.0, 0.0, 3.0, 0.9),
    ("cruise", 25.0, 16.0, 0.0, 0.0, 0.6),
    ("circles", 40.0, 15.0, 2.0, 0.0, 0.65),
    ("cruise", 15.0, 17.0, 0.0, 0.0, 0.7),
    ("climbing_turn", 25.0, 15.0, 1.0, 2.0, 0.85),
    ("glide", 25.0, 13.0, 0.0, -2.5, 0.15),
    ("circles", 40.0, 15.0, -2.0, 0.0, 0.6),
    ("cruise", 20.0, 16.0, 0.0, 0.0, 0.55),
    ("approach", 40.0, 13.0, 0.0, -2.0, 0.3),
    ("rollout", 8.0, 0.0, 0.0, 0.0, 0.0),
    ("ground_off", 4.0, 0.0, 0.0, 0.0, 0.0),
)
PLANE_INCIDENCE_RAD = 0.06  # pitch = flight-path angle + incidence in flight


def _ordinary_fixedwing(duration_s: float, dt_s: float, rng: np.random.Generator) -> Motion:
    """Ordinary plane flight (ORDINARY_PLANE_PLAN), scaled to ``duration_s`` like the multirotor one (full
    turns kept, speeds and climb rates kept). Coordinated turns, roll = atan(V psi_dot / g); pitch =
    flight-path angle + incidence; throttle per phase plus a small seeded gust component; level on the
    ground. Ends on the ground, stopped, at the take-off altitude."""
    plan = _lay_out(ORDINARY_PLANE_PLAN, duration_s, dt_s)
    names, seg, v, climb, yaw_rate = plan.names, plan.seg, plan.speed, plan.climb, plan.yaw_rate
    n = seg.size
    thr = np.zeros(n)
    ground = np.zeros(n, dtype=bool)
    for row, a, b in plan.spans:
        thr[a:b] = row[5]
        ground[a:b] = row[0] in ("ground_off", "takeoff_roll", "rollout")
    off = seg == names.index("ground_off")
    v = _smooth(v, dt_s, 4.0)
    v[off] = 0.0  # standing, motor off
    v = _smooth(v, dt_s, 0.5)
    near_ground = np.convolve(ground.astype(float), np.ones(2 * round(1.0 / dt_s) + 1), mode="same") > 0
    climb[near_ground] = 0.0
    climb = _smooth(climb, dt_s, 2.0)
    climb[ground] = 0.0
    desc = climb < 0.0
    alt = np.cumsum(climb) * dt_s
    if desc.any() and alt[-1] != 0.0:
        climb[desc] -= alt[-1] / (desc.sum() * dt_s)
        alt = np.maximum(np.cumsum(climb) * dt_s, 0.0)
    psi_dot = _smooth(yaw_rate, dt_s, 2.0)
    psi_dot[ground] = 0.0
    yaw = math.radians(-30.0) + np.cumsum(psi_dot) * dt_s
    gust = _smooth(rng.normal(0.0, 1.0, n), dt_s, 1.0)
    gust *= 0.02 / max(float(np.std(gust)), 1e-12)
    thr = np.clip(_smooth(thr, dt_s, 0.6) + np.where(ground, 0.0, np.clip(gust, -0.04, 0.04)), 0.0, 1.0)
    thr[off] = 0.0
    gamma = np.arcsin(np.clip(climb / np.maximum(v, 1.0), -0.5, 0.5))
    roll = np.where(ground, 0.0, np.arctan(v * psi_dot / STANDARD_GRAVITY_M_S2))
    airborne_weight = _smooth((~ground).astype(float), dt_s, 1.0)
    pitch = (gamma + PLANE_INCIDENCE_RAD) * airborne_weight
    vel = v[:, None] * np.stack([np.cos(gamma) * np.cos(yaw), np.cos(gamma) * np.sin(yaw), -np.sin(gamma)], 1)
    motion = _finish_path(dt_s, roll, pitch, yaw, vel, alt, thr, v, "fixedwing")
    return dataclasses.replace(motion, segment=seg, segment_names=names)
