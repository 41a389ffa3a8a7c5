"""Cramer-Rao bound on theta for the simulated ordinary flight (issue 9): how well can *any* unbiased
estimator know theta from the samples a telemetry rate delivers, given what it may trust of the attitude?

The model is the absolute form's, eqs. (1), (11), (13): ``y_k = A R_nb,k^T h_n + d + theta x_k + n_k``,
``x_k = delta_k^2``, white noise ``n_k`` of the simulator's compass (sigma per axis: its white noise and its
quantisation), at the samples the link carries (every ``imu_hz / rate``-th one) with the motors running.
Unknowns: A (9: soft iron, scale, misalignment), d (3), theta (3), with the estimator's own prior on A and
d (the autopilot calibrated the compass: 0.05 and 50 mgauss; ``InflightConfig``), plus what the attitude
reference leaves unknown:

``trusted``  nothing: the true attitude (an external primary compass, GPS yaw; the absolute form).
``window``   a yaw offset and a yaw rate per 2 s window (``ROTATION_WINDOW_S``), free: the autopilot's yaw
             follows the disturbed compass and is trusted only for rotations within a window. This is the
             information the relative form's assumptions leave (rotation-source yaw-rate error constant
             per window); its 0.3 s pairs see only part of it.
``window_field``  the window's horizontal Earth field free (its size too) and a yaw rate per 2 s window,
             the vertical field one unknown for the flight: the relative form's window-field rows.
``gyro_window``  the same over GYRO_WINDOW_S (10 s) windows: the yaw from the raw gyro, which drifts only
             by its bias (``GYRO_YAW``), as the relative form uses for an internal compass.
``tilt``     a yaw offset per sample, free: only the yaw-free part of every sample (the field along the
             vertical and the horizontal field's size), i.e. no trust in any yaw.

The Fisher information of a linear Gaussian model does not depend on the measurements, so it is computed
from the simulator's true attitude and throttle; the nuisances are eliminated per window (Schur
complement). Rows come from ``magcomp.core.inflight`` (one implementation of each equation).
Reported: ``sqrt(trace C_theta) / |theta|`` (the rms of |theta error| / |theta|), in %.

    .venv/bin/python benchmarks/theta_crb.py [--rates 1 10 50] [--seeds 0] [--set KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from magcomp.core.inflight import absolute_rows, reference_yaw_error_rows
from magcomp.core.inflight.feed import ROTATION_WINDOW_S
from magcomp.core.inflight.yawframe import GYRO_WINDOW_S
from magcomp.core.rotations import dcms_from_quats

F64 = NDArray[np.float64]
MODELS = ("trusted", "window", "window_field", "gyro_window", "tilt")
#: the estimator's prior for a compass the autopilot calibrated (InflightConfig defaults)
PRIOR_SD_A = 0.05
PRIOR_SD_D_MGAUSS = 50.0


@dataclass(frozen=True)
class ThetaBound:
    """theta's bound for one flight, one rate, one attitude model: ``pct_60`` after the first 60 s of
    flight, ``pct_end`` at the end (rms |theta error| / |theta|, %), ``sd_end_mgauss`` per axis, the
    samples used and the noise sigma assumed."""

    model: str
    pct_60: float
    pct_end: float
    sd_end_mgauss: tuple[float, float, float]
    n_60: int
    n_end: int
    sigma_mgauss: float


def noise_sigma_mgauss(result: Any, j: int) -> float:
    """Per-axis noise of compass j's logged field: white noise (scaled) and two roundings (sensor LSB,
    then the message's 1 mgauss), uniform quantisation error variance lsb^2 / 12."""
    c = result.compasses[j]
    return math.sqrt(c.noise_mgauss**2 + c.lsb_mgauss**2 / 12.0 + 1.0 / 12.0)


def _sample_index(result: Any, rate_hz: float) -> NDArray[np.int64]:
    s = result.samples
    step = max(1, round(result.config.rates.imu_hz / rate_hz))
    k = np.arange(0, s.t_s.size, step)
    return k[np.asarray(s.throttle_01)[k] > 0.0]  # motors running (the estimator's rows)


def theta_bounds(result: Any, rate_hz: float, j: int = 0) -> list[ThetaBound]:
    """theta's Cramer-Rao bound for compass j at ``rate_hz``, per attitude model (MODELS)."""
    s = result.samples
    k = _sample_index(result, rate_hz)
    t = np.asarray(s.t_s)[k]
    thr = np.asarray(s.throttle_01)[k]
    r_nb = dcms_from_quats(result.motion.q_nb[np.asarray(s.truth_index)[k]])
    h_n = np.asarray(result.earth_field_ned_mgauss, dtype=float)
    flying = thr > 0.2
    t_fly = float(t[flying][0]) if flying.any() else math.inf
    sigma = noise_sigma_mgauss(result, j)
    theta = np.asarray(result.compasses[j].theta_mgauss, dtype=float)
    rows = np.empty((k.size, 3, 15))
    yaw_col = np.empty((k.size, 3))
    for i in range(k.size):
        rows[i], _ = absolute_rows(r_nb[i].T @ h_n, np.zeros(3), np.array([thr[i] * thr[i]]))
        yaw_col[i] = reference_yaw_error_rows(r_nb[i], h_n)[:, 0]
    prior = np.diag(
        1.0 / np.concatenate([np.full(9, PRIOR_SD_A), np.full(3, PRIOR_SD_D_MGAUSS), np.full(3, 600.0)]) ** 2
    )
    out = []
    for model in MODELS:
        res = {}
        for label, t_end in (("60", t_fly + 60.0), ("end", math.inf)):
            m = t <= t_end
            info = _information(rows[m], yaw_col[m], r_nb[m], t[m], model) / sigma**2 + prior
            cov = np.linalg.inv(info)[12:15, 12:15]
            res[label] = (cov, int(m.sum()))
        c60, n60 = res["60"]
        cend, nend = res["end"]
        norm = float(np.linalg.norm(theta))
        sd = np.sqrt(np.diag(cend))
        out.append(
            ThetaBound(
                model=model,
                pct_60=100.0 * math.sqrt(float(np.trace(c60))) / norm,
                pct_end=100.0 * math.sqrt(float(np.trace(cend))) / norm,
                sd_end_mgauss=(float(sd[0]), float(sd[1]), float(sd[2])),
                n_60=n60,
                n_end=nend,
                sigma_mgauss=sigma,
            )
        )
    return out


def _information(rows: F64, yaw_col: F64, r_nb: F64, t: F64, model: str) -> F64:
    """Unit-weight Fisher information of the parameters with the model's nuisances eliminated."""
    n_p = rows.shape[2]
    if model == "trusted":
        flat = rows.reshape(-1, n_p)
        return np.asarray(flat.T @ flat, dtype=np.float64)
    if model == "tilt":
        # a free yaw per sample: project each sample's rows off its yaw column
        e = yaw_col / np.maximum(np.linalg.norm(yaw_col, axis=1, keepdims=True), 1e-12)
        proj = rows - e[:, :, None] * np.einsum("ni,nip->np", e, rows)[:, None, :]
        flat = proj.reshape(-1, n_p)
        return np.asarray(flat.T @ flat, dtype=np.float64)
    if model in ("window_field", "gyro_window"):  # the vertical Earth field: one unknown for the flight
        rows = np.concatenate([rows, r_nb[:, 2, :, None]], axis=2)
    n_a = rows.shape[2]
    win = np.floor(t / (GYRO_WINDOW_S if model == "gyro_window" else ROTATION_WINDOW_S))
    info = np.zeros((n_a, n_a))
    for w in np.unique(win):
        m = win == w
        jp = rows[m].reshape(-1, n_a)
        dt = (t[m] - t[m].mean())[:, None]
        if model == "window":
            je = np.stack([yaw_col[m], yaw_col[m] * dt], axis=2).reshape(-1, 2)
        else:  # the horizontal Earth field of the window free (its size too), and a yaw rate
            je = np.stack([r_nb[m][:, 0, :], r_nb[m][:, 1, :], yaw_col[m] * dt], axis=2).reshape(-1, 3)
        hee = je.T @ je + 1e-9 * np.eye(je.shape[1])
        hpe = jp.T @ je
        info += jp.T @ jp - hpe @ np.linalg.solve(hee, hpe.T)
    if n_a > n_p:
        c = info[:n_p, n_p:]
        info = info[:n_p, :n_p] - c @ np.linalg.solve(info[n_p:, n_p:], c.T)
    return np.asarray(info, dtype=np.float64)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rates", type=float, nargs="+", default=[1.0, 10.0, 50.0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="simulator knob")
    ap.add_argument("--compass", type=int, default=0)
    args = ap.parse_args()
    from magcomp.sim import SimConfig, simulate
    from magcomp.sim.config import apply_settings

    print("rate Hz  seed  model    N(60s)  N(end)  CRB 60 s %  CRB end %  sd end (x, y, z) mgauss")
    for rate in args.rates:
        for seed in args.seeds:
            cfg = apply_settings(
                SimConfig(scenario="ordinary", seed=seed), [f"telemetry_hz={rate:g}", *args.set]
            )
            result = simulate(cfg)
            for b in theta_bounds(result, rate, args.compass):
                sd = ", ".join(f"{v:.1f}" for v in b.sd_end_mgauss)
                print(f"{rate:7g}  {seed:4d}  {b.model:7s}  {b.n_60:6d}  {b.n_end:6d}  {b.pct_60:10.1f}  "
                      f"{b.pct_end:9.1f}  ({sd})")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
