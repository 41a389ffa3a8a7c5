"""Issue 9 on simulated ordinary flights (no motors-off hand rotation): in-flight calibration jointly with
theta through the whole product path (simulator -> tlog -> replay), GPS position for the Earth field,
low-rate telemetry, honest per-compass status, strictly valid JSON."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from magcomp.core.inflight.yawframe import yaw_turned
from magcomp.core.types import FLAG_CALIBRATED, FLAG_NO_THROTTLE
from magcomp.service.console import summary_lines, write_json
from magcomp.service.demo import oracle_replay, rms_after_learning
from magcomp.service.replay import replay_log
from tests.configs import ESTIMATOR_ONLY


def _flight(
    tmp_path: Path, settings: list[str], seed: int = 1, duration_s: float = 200.0
) -> tuple[Any, Path]:
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate
    from magcomp.sim.config import apply_settings

    cfg = apply_settings(SimConfig(scenario="ordinary", seed=seed, duration_s=duration_s), settings)
    result = simulate(cfg)
    path = tmp_path / "ordinary.tlog"
    write_tlog(result, path)
    return result, path


@pytest.mark.slow
def test_internal_primary_compass_is_corrected_without_a_hand_rotation(tmp_path: Path) -> None:
    """The autopilot's yaw follows the disturbed compass; the relative form uses only the rotations between
    samples (the autopilot's attitude, its slow compass-driven yaw drift estimated), not that yaw."""
    result, path = _flight(tmp_path, ["telemetry_hz=50"])
    rep = replay_log(path, ESTIMATOR_ONLY, keep_estimates=True)
    c0 = rep.summary["compasses"][0]
    assert c0["status"] == "corrected", c0["why"]
    assert c0["inflight"]["form"] == "relative" and c0["inflight"]["rotation"] == "attitude"
    theta, truth = np.asarray(c0["theta_mgauss"]), np.asarray(result.compasses[0].theta_mgauss)
    assert float(theta @ truth) / (np.linalg.norm(theta) * np.linalg.norm(truth)) > 0.9
    assert abs(np.linalg.norm(theta) / np.linalg.norm(truth) - 1.0) < 0.35
    corrected, raw = rms_after_learning(result, rep.estimates, 0)
    assert corrected < 0.75 * raw, (corrected, raw)
    assert rep.summary["earth_field"]["source"] == "gps"
    loc = result.config.location
    assert rep.summary["earth_field"]["lat_deg"] == pytest.approx(loc.lat_deg, abs=1e-3)


@pytest.mark.slow
def test_external_primary_gives_the_absolute_form_and_theta_within_ten_percent(tmp_path: Path) -> None:
    """Like log171: compass 0 external (the autopilot's yaw), compass 1 internal with the current's field."""
    result, path = _flight(tmp_path, ["telemetry_hz=50", "external_compass0=on"])
    rep = replay_log(path, ESTIMATOR_ONLY, keep_estimates=True)
    c1 = rep.summary["compasses"][1]
    assert c1["inflight"]["form"] == "absolute", c1["inflight"]["form_why"]
    assert c1["status"] == "corrected"
    theta, truth = np.asarray(c1["theta_mgauss"]), np.asarray(result.compasses[1].theta_mgauss)
    assert np.linalg.norm(theta - truth) < 0.10 * np.linalg.norm(truth)
    corrected, raw = rms_after_learning(result, rep.estimates, 1)
    assert corrected < 0.7 * raw, (corrected, raw)
    assert rep.estimates[-1].flags & FLAG_CALIBRATED


def test_one_hertz_telemetry_is_not_a_gap_on_every_sample(tmp_path: Path) -> None:
    """1 Hz RAW_IMU (a telemetry tlog): no gap, no observer reset per sample; every compass says what it is
    doing and why, and the JSON is strictly valid."""
    _, path = _flight(tmp_path, ["telemetry_hz=1"], duration_s=120.0)
    rep = replay_log(path, ESTIMATOR_ONLY)
    counts = rep.summary["counts"]
    assert counts["mag"] > 200
    assert counts["gaps"] == 0
    assert counts["observer_resets"] <= len(rep.summary["compasses"])
    for c in rep.summary["compasses"]:
        assert c["status"] in ("corrected", "uncorrected")
        assert c["why"]
        assert c["inflight"]["rotation"] == "attitude"  # a 1 Hz gyro cannot be integrated
    lines = summary_lines(rep.summary)
    assert all(("NOT corrected:" in ln) or ("corrected" in ln) for ln in lines)
    out = tmp_path / "summary.json"
    write_json(out, rep.to_json())

    def no_constant(name: str) -> float:
        raise AssertionError(f"non-JSON constant {name}")

    json.loads(out.read_text(), parse_constant=no_constant)


def test_no_throttle_source_is_said_per_compass(tmp_path: Path) -> None:
    _, path = _flight(tmp_path, ["telemetry_hz=10"], duration_s=60.0)
    cfg = ESTIMATOR_ONLY
    cfg = replace(cfg, input=replace(cfg.input, throttle_source="none"))
    rep = replay_log(path, cfg)
    for c in rep.summary["compasses"]:
        assert c["status"] == "uncorrected"
        assert "no throttle source" in c["why"]
    assert all("NOT corrected: no throttle source" in ln for ln in summary_lines(rep.summary))


def test_two_pass_replay_starts_corrected_and_says_so(tmp_path: Path) -> None:
    _, path = _flight(tmp_path, ["telemetry_hz=50", "external_compass0=on"], duration_s=150.0)
    rep = replay_log(path, ESTIMATOR_ONLY, keep_estimates=True, two_pass=True)
    assert rep.summary["passes"] == 2
    c1 = rep.summary["compasses"][1]
    assert c1["inflight"]["started_from_stored_state"]
    first = next(e for e in rep.estimates if e.mag_index == 1 and not e.flags & FLAG_NO_THROTTLE)
    assert first.flags & FLAG_CALIBRATED
    assert math.isfinite(first.heading_deg)


@pytest.mark.parametrize("gps", ["on", "off"])
def test_replay_says_where_the_earth_field_came_from(
    tmp_path: Path, gps: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """A log without a GPS fix (Ljubljana) is scaled to the configured location's WMM field (here the built-in
    default, Florida): the console must say so in one line, as it says the GPS position when there is one."""
    from magcomp.cli import main

    _, path = _flight(tmp_path, [f"gps={gps}", "lat_deg=46.05", "lon_deg=14.5"], duration_s=20.0)
    assert main(["replay", str(path), "--json", str(tmp_path / "s.json")]) == 0
    text = capsys.readouterr()
    out = text.out + text.err
    source = json.loads((tmp_path / "s.json").read_text())["earth_field"]["source"]
    if gps == "off":
        assert source == "config"
        assert "Earth field: no GPS fix in the log; WMM at the configured location (29.6500, -82.3500)" in out
    else:
        assert source == "gps"
        assert "Earth field from the GPS position (46.05" in out and "no GPS fix" not in out


def test_four_hertz_telemetry_matches_attitude_and_throttle_to_the_field_time(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """At 4 Hz every message of an instant (RAW_IMU, then ATTITUDE, SERVO_OUTPUT_RAW) shares its tick, and
    the ticks fall 0.24 / 0.26 s apart on the 50 Hz loop. The relative form must pair each field sample with
    the autopilot's attitude and throttle of that same tick, not the previous one (0.25 s stale: ~3 deg of
    rotation in turns). Fails when matching flips on and off with the interval's jitter (docs/inflight.md,
    "4 Hz telemetry")."""
    from magcomp.core.rotations import dcm_from_euler, so3_log
    from magcomp.service import inflight_stage

    result, path = _flight(tmp_path, ["telemetry_hz=4"], seed=2, duration_s=150.0)
    used: list[tuple[float, Any, float]] = []
    orig = inflight_stage.InflightStage._use

    def spy(self: Any, t_s: float, y: Any, x: Any, r_nb: Any, ref: Any, turn: Any = None) -> None:
        if self.mag_index == 0:  # the attitude the rows take: with the gyro's yaw turn, if it has one
            r = r_nb if turn is None else yaw_turned(np.array([r_nb]), *np.array([turn]).T)[0]
            used.append((t_s, np.array(r), float(x[0])))
        orig(self, t_s, y, x, r_nb, ref, turn)

    monkeypatch.setattr(inflight_stage.InflightStage, "_use", spy)
    replay_log(path, ESTIMATOR_ONLY)
    s = result.samples
    assert len(used) > 0.9 * 150.0 * 4.0
    ang, dthr = [], []
    for t, r, x in used:
        i = int(np.argmin(np.abs(s.t_s - t)))
        assert abs(s.t_s[i] - t) < 1e-3
        ang.append(np.linalg.norm(so3_log(dcm_from_euler(*s.attitude_rad[i]).T @ r)))
        dthr.append(x - float(s.throttle_01[i]) ** 2)
    rms_deg = math.degrees(float(np.sqrt(np.mean(np.square(ang)))))
    # PWM is 1 us of 1000 and the attitude float32: the match is exact to well under these
    assert rms_deg < 0.05, rms_deg
    assert float(np.sqrt(np.mean(np.square(dthr)))) < 0.002


@pytest.mark.slow
@pytest.mark.parametrize("seed", [2, 3])
def test_theta_from_the_tilt_model_within_ten_percent_at_ten_hertz(tmp_path: Path, seed: int) -> None:
    """Internal primary, 10 Hz: the autopilot's yaw follows the disturbed compass, so in accelerated flight
    its tilt is off by -psi a / g, and theta took that for current (13 % off on these seeds). The published
    theta comes from the tilt model's own estimator, the calibration from the ordinary one conditioned on
    that theta (``FeedSwitches.tilt_condition``; docs/inflight.md, seventh pass): theta within 10 % and
    within three of its own sigmas, the heading corrected."""
    result, path = _flight(tmp_path, ["telemetry_hz=10"], seed=seed, duration_s=300.0)
    rep = replay_log(path, ESTIMATOR_ONLY, keep_estimates=True)
    c0 = rep.summary["compasses"][0]
    assert c0["status"] == "corrected", c0["why"]
    theta, truth = np.asarray(c0["theta_mgauss"]), np.asarray(result.compasses[0].theta_mgauss)
    err = float(np.linalg.norm(theta - truth))
    assert err < 0.10 * np.linalg.norm(truth), (theta, truth)
    assert err < 3.0 * float(np.linalg.norm(c0["inflight"]["theta_sigma_mgauss"]))
    corrected, raw = rms_after_learning(result, rep.estimates, 0)
    assert corrected < 0.75 * raw, (corrected, raw)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2])
def test_heading_sigma_covers_the_error_beyond_the_oracle_with_the_two_models_apart(
    tmp_path: Path, seed: int
) -> None:
    """Internal primary, a realistic multirotor's theta (x6), 10 Hz: the heading error beyond the oracle's
    (true calibration and theta, everything else identical) is a bias the parameters' covariance does not
    see (0.4-0.6 deg reported for 1.3-1.6 deg). The heading the ordinary and the tilt model's calibrations
    give apart is counted in the published sigma (core.inflight.HEADING_MODEL_SPREAD; docs/inflight.md):
    the error beyond the oracle's within two reported sigmas (2.7-3.3 sigmas without it)."""
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate
    from magcomp.sim.config import apply_settings

    result = simulate(
        apply_settings(SimConfig(scenario="ordinary", seed=seed), ["telemetry_hz=10", "theta_scale=6"])
    )
    path = tmp_path / "ordinary.tlog"
    write_tlog(result, path)
    cfg = ESTIMATOR_ONLY
    rep = replay_log(path, cfg, keep_estimates=True)
    orc = oracle_replay(result, path, tmp_path / "oracle", cfg)
    c0 = rep.summary["compasses"][0]
    assert c0["status"] == "corrected", c0["why"]
    inf = c0["inflight"]
    corrected, _ = rms_after_learning(result, rep.estimates, 0)
    oracle, _ = rms_after_learning(result, orc.estimates, 0)
    beyond = math.sqrt(max(corrected**2 - oracle**2, 0.0))
    assert beyond > 1.0  # the bias is there: the test can fail
    assert inf["heading_model_deg"] > 0.0
    assert beyond < 2.0 * inf["heading_sigma_deg"], (
        beyond,
        inf["heading_sigma_deg"],
        inf["heading_model_deg"],
    )


@pytest.mark.slow
def test_a_stuck_compass_is_not_corrected_and_says_why(tmp_path: Path) -> None:
    """A dead compass repeating one reading: the learned hard iron equals the reading, the corrected field is
    ~0 mgauss and its heading noise, while the statistical sigma is small. It must not be published as
    corrected; the working compass beside it still is."""
    from magcomp.core.types import EARTH_MIN_MGAUSS
    from tests.conftest import split_tlog_records
    from tests.faultgen import rewrite

    _, path = _flight(tmp_path, ["telemetry_hz=10"])
    stuck = rewrite(split_tlog_records(path.read_bytes()), "SCALED_IMU2", xmag=120, ymag=-40, zmag=380)
    path.write_bytes(b"".join(stuck))
    rep = replay_log(path, ESTIMATOR_ONLY)
    c0, c1 = rep.summary["compasses"][:2]
    assert c0["status"] == "corrected", c0["why"]
    assert c1["status"] == "uncorrected", c1
    assert "corrected field" in c1["why"], c1["why"]
    strength = c1["inflight"].get("corrected_field_mgauss")
    assert strength is not None and strength < 0.65 * EARTH_MIN_MGAUSS, strength


@pytest.mark.slow
def test_the_relative_forms_excess_over_the_oracle_is_the_unobservable_mount_yaw(tmp_path: Path) -> None:
    """Internal primary, 10 Hz, seed 4 (its compass mounted 1.95 deg rotated about body z, the largest of
    seeds 0-5): the two-pass heading's rms is above the oracle's (1.4x; 2.2x before the heading filter
    propagated with the raw gyro), but what it lacks is a constant of about the mount's yaw, which a compass
    that is its own yaw reference cannot see (a declination error looks the same; the oracle is handed it).
    With the constant removed it is within 1.5x the oracle's; the summary says the mount's yaw is not counted
    (docs/inflight.md, tenth pass)."""
    from magcomp.core.rotations import so3_log
    from magcomp.service.demo import errors_after_learning, offset_split

    result, path = _flight(tmp_path, ["telemetry_hz=10"], seed=4, duration_s=600.0)
    cfg = ESTIMATOR_ONLY
    two = replay_log(path, cfg, keep_estimates=True, two_pass=True)
    orc = oracle_replay(result, path, tmp_path / "oracle", cfg)
    c0 = two.summary["compasses"][0]
    assert c0["status"] == "corrected" and c0["inflight"]["form"] == "relative"
    assert c0["inflight"]["mount_yaw_observable"] is False
    assert "not counting the mount's yaw" in "\n".join(summary_lines(two.summary))
    offset, rest = offset_split(errors_after_learning(result, two.estimates, 0)[0])
    o_offset, o_rest = offset_split(errors_after_learning(result, orc.estimates, 0)[0])
    u, _, vt = np.linalg.svd(result.true_calibration(0)[0])
    mount_z_deg = float(np.degrees(so3_log(u @ vt))[2])
    assert abs(mount_z_deg) > 1.5  # the case the test is about
    assert math.hypot(offset, rest) > 1.2 * math.hypot(o_offset, o_rest)  # the constant makes it worse
    assert abs(offset) > rest  # and is the larger part of its error
    assert rest < 1.5 * o_rest, (rest, o_rest)
    assert abs(offset - mount_z_deg) < 0.6 * abs(mount_z_deg), (offset, mount_z_deg)


@pytest.mark.slow
def test_an_autopilot_that_pulls_its_yaw_slowly_keeps_the_heading_and_theta(tmp_path: Path) -> None:
    """The simulated autopilot pulled its yaw to the compass at 0.5 /s; log171's EKF does it at ~0.02 /s
    (benchmarks/autopilot_yaw_follow.py). At 0.05 /s (10 Hz, seed 2, the worst offset-free causal ratio of
    seeds 0-5) the estimate learned in flight still holds: theta within 10 %, and beyond the constant (the
    mount's yaw and the autopilot's held tilt, not observable here) the causal and two-pass headings within
    1.5x the oracle's (docs/inflight.md, tenth pass)."""
    from magcomp.service.demo import errors_after_learning, offset_split

    result, path = _flight(tmp_path, ["telemetry_hz=10", "ap_kp_yaw=0.05"], seed=2, duration_s=600.0)
    cfg = ESTIMATOR_ONLY
    causal = replay_log(path, cfg, keep_estimates=True)
    two = replay_log(path, cfg, keep_estimates=True, two_pass=True)
    orc = oracle_replay(result, path, tmp_path / "oracle", cfg)
    c0 = causal.summary["compasses"][0]
    assert c0["status"] == "corrected", c0["why"]
    theta, truth = np.asarray(c0["theta_mgauss"]), np.asarray(result.compasses[0].theta_mgauss)
    assert np.linalg.norm(theta - truth) < 0.10 * np.linalg.norm(truth)
    _, o_rest = offset_split(errors_after_learning(result, orc.estimates, 0)[0])
    _, c_rest = offset_split(errors_after_learning(result, causal.estimates, 0)[0])
    _, t_rest = offset_split(errors_after_learning(result, two.estimates, 0)[0])
    assert c_rest < 1.5 * o_rest and t_rest < 1.5 * o_rest, (c_rest, t_rest, o_rest)
