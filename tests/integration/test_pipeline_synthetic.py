"""The pipeline on a small synthetic stream built here (hand rotation at zero throttle, spin at full
throttle, then a level pan): calibration, theta and heading against the known truth."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from magcomp.adapters.config import Config
from magcomp.core.rotations import dcm_from_quat, quat_from_euler, quat_integrate_body_rate
from magcomp.core.types import (
    FLAG_CALIBRATED,
    FLAG_NO_THROTTLE,
    HeadingEstimate,
    ImuSample,
    MagSample,
    Sample,
    ThrottleSample,
)
from magcomp.geomag import earth_field_ned_mgauss
from magcomp.service.pipeline import Pipeline
from tests.configs import ESTIMATOR_ONLY

G = 9.80665
THETA = np.array([-61.0, 26.4, -12.0])
K_TRUE = np.array([[1.05, 0.03, -0.02], [0.01, 0.97, 0.04], [-0.03, 0.02, 1.02]])
B_TRUE = np.array([40.0, -25.0, 60.0])


def synth_stream(
    rng: np.random.Generator,
    tumble_s: float = 40.0,
    spin_s: float = 40.0,
    pan_s: float = 20.0,
    mag_noise: float = 1.0,
    t0: float = 10.0,
) -> tuple[list[Sample], dict[str, np.ndarray]]:
    """Samples in arrival order (throttle, IMU, magnetometer at 50 Hz) and the truth per mag sample."""
    cfg = Config()
    loc = cfg.location
    b_ned = earth_field_ned_mgauss(loc.lat_deg, loc.lon_deg, loc.alt_m, loc.decimal_year)
    fs, sub = 50.0, 4
    dt = 1.0 / (fs * sub)
    n = int((tumble_s + spin_s + pan_s) * fs)
    q = quat_from_euler(0.0, 0.0, 0.3)
    freqs = rng.uniform(0.15, 0.6, size=(3, 3))
    phases = rng.uniform(0, 2 * np.pi, size=(3, 3))
    out: list[Sample] = []
    truth = {"t": np.zeros(n), "heading": np.zeros(n), "throttle": np.zeros(n)}
    t = 0.0
    for k in range(n):
        tk = k / fs
        seg_pan = tk >= tumble_s + spin_s
        for _ in range(sub):
            # hand rotation (sum of sinusoids), faded out over the last 5 s before the pan while a
            # levelling rate brings the down vector to body z; then a level pan at 0.6 rad/s
            fade = min(max((tumble_s + spin_s - t) / 5.0, 0.0), 1.0)
            w = fade * np.sum(1.2 * np.sin(2 * math.pi * freqs * t + phases), axis=1)
            if fade < 1.0:
                down = dcm_from_quat(q)[2]
                w = w - 2.0 * np.cross(down, [0.0, 0.0, 1.0])
            if seg_pan:
                w = w + np.array([0.0, 0.0, 0.6])
            q = quat_integrate_body_rate(q, w, dt)
            t += dt
        r_nb = dcm_from_quat(q)
        thr = 0.0 if tk < tumble_s else 1.0
        u_b = r_nb.T @ b_ned
        v_raw = K_TRUE @ (u_b + thr * thr * THETA) + B_TRUE + mag_noise * rng.standard_normal(3)
        accel = r_nb.T @ np.array([0.0, 0.0, -G]) + 0.02 * rng.standard_normal(3)
        gyro = w + 0.002 * rng.standard_normal(3)
        ts = t0 + tk
        if k % 2 == 0:
            out.append(ThrottleSample(ts, thr, "servo:3"))
        out.append(ImuSample(ts, gyro, accel))
        out.append(MagSample(ts, v_raw))
        yaw_true = math.degrees(math.atan2(r_nb[1, 0], r_nb[0, 0]))
        b_h = math.degrees(math.atan2(b_ned[1], b_ned[0]))
        truth["t"][k] = ts
        truth["heading"][k] = (yaw_true - b_h) % 360.0  # magnetic heading
        truth["throttle"][k] = thr
    return out, truth


def run(cfg: Config, samples: list[Sample]) -> tuple[Pipeline, list[HeadingEstimate]]:
    p = Pipeline(cfg)
    ests = [e for e in (p.process(s) for s in samples) if e is not None]
    p.close()
    return p, ests


def wrap(a: np.ndarray) -> np.ndarray:
    return (a + 180.0) % 360.0 - 180.0


@pytest.fixture(scope="module")
def stream() -> tuple[list[Sample], dict[str, np.ndarray]]:
    return synth_stream(np.random.default_rng(7))


def test_pipeline_learns_calibration_then_theta_and_corrects_heading_in_the_pan(
    stream: tuple[list[Sample], dict[str, np.ndarray]],
) -> None:
    samples, truth = stream
    _, ests = run(ESTIMATOR_ONLY, samples)
    assert len(ests) == len(truth["t"])
    t = np.array([e.t_s for e in ests])
    np.testing.assert_array_equal(t, truth["t"])
    flags = np.array([e.flags for e in ests])
    assert flags[-1] & FLAG_CALIBRATED
    theta = ests[-1].theta_mgauss
    # theta of eq. (11) learned online in the spin, to a few % of |theta|
    assert np.linalg.norm(theta - THETA) < 0.05 * np.linalg.norm(THETA), theta
    pan = t >= t[0] + 80.0
    err = wrap(np.array([e.heading_deg for e in ests])[pan] - truth["heading"][pan])
    err_raw = wrap(np.array([e.heading_raw_deg for e in ests])[pan] - truth["heading"][pan])
    assert np.max(np.abs(err)) < 2.0, np.max(np.abs(err))
    assert np.max(np.abs(err_raw)) > 5.0 * np.max(np.abs(err))


def test_no_throttle_source_headings_still_flow_flagged_uncorrected(
    stream: tuple[list[Sample], dict[str, np.ndarray]],
) -> None:
    samples, truth = stream
    cfg = replace(Config(), input=replace(Config().input, throttle_source="none"))
    p, ests = run(cfg, samples)
    assert len(ests) == len(truth["t"])
    assert all(e.flags & FLAG_NO_THROTTLE for e in ests)
    assert all(e.heading_deg == e.heading_raw_deg for e in ests)
    assert any("no throttle source" in w for w in p.warnings)
