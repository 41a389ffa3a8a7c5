"""Variation knobs (issue 10): coloured noise, quantisation, attitude errors, rates, settings parsing, and the
guarantee that a run with every knob at its default is the pre-knob run."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from magcomp.errors import InputError
from magcomp.sim import SimConfig, simulate
from magcomp.sim.config import Rates, Variation, apply_settings, setting_keys
from magcomp.sim.sensors import coloured_noise

FIELD = (240.0, -27.0, 386.0)  # explicit Earth field: these tests do not need the WMM


def test_ar1_noise_has_the_asked_sigma_and_correlation_time() -> None:
    dt, sigma, tau = 0.02, 4.0, 1.5
    x = coloured_noise(200_000, dt, sigma, tau, 0.0, np.random.default_rng(3))
    np.testing.assert_allclose(x.std(axis=0), sigma, rtol=0.06)  # ~ 2700 correlation times
    lag = round(tau / dt)
    r = np.mean([np.corrcoef(x[:-lag, i], x[lag:, i])[0, 1] for i in range(3)])
    assert r == pytest.approx(math.exp(-1.0), abs=0.05)


def test_random_walk_variance_grows_linearly_in_time() -> None:
    dt, q = 0.1, 0.5
    rng = np.random.default_rng(5)
    walks = np.stack([coloured_noise(1000, dt, 0.0, 1.0, q, rng)[:, 0] for _ in range(400)])
    t = np.arange(1, 1001) * dt
    for k in (99, 499, 999):
        assert walks[:, k].var() == pytest.approx(q**2 * t[k], rel=0.2)  # 400 walks: ~7 % sampling error


def test_quantisation_step_and_noise_scale_reach_the_raw_reading() -> None:
    cfg = apply_settings(
        SimConfig(scenario="bench", duration_s=10.0, earth_field_ned_mgauss=FIELD, n_compasses=2),
        ["mag_lsb_mgauss=5", "mag_noise_scale=0.5"],
    )
    r = simulate(cfg)
    mag = r.samples.mag_mgauss  # no autopilot calibration in bench: the raw reading
    np.testing.assert_array_equal(np.mod(mag, 5.0), 0.0)
    assert [c.noise_mgauss for c in r.compasses] == [4.0, 1.5]


def test_coloured_noise_is_seen_in_the_field_at_rest() -> None:
    base = SimConfig(scenario="step", duration_s=30.0, earth_field_ned_mgauss=FIELD, n_compasses=1, seed=2)
    cfg = apply_settings(base, ["mag_noise_scale=0", "mag_lsb_mgauss=0.01", "mag_ar1_sigma_mgauss=6"])
    r = simulate(cfg)
    at_rest = r.samples.throttle_01 == 0.0  # before the step: a fixed field plus the noise only
    v = r.samples.mag_mgauss[0][at_rest]
    d = np.diff(v, axis=0)
    assert v.std(axis=0).max() > 1.5  # the noise is there ...
    assert np.abs(d).mean() < 0.3 * v.std(axis=0).mean()  # ... and it is smooth: correlated, not white


def test_attitude_biases_and_noise_reach_attitude() -> None:
    base = SimConfig(
        scenario="flight_multirotor", duration_s=40.0, earth_field_ned_mgauss=FIELD, n_compasses=1
    )
    plain = simulate(base)
    biased = simulate(
        apply_settings(
            base,
            ["att_roll_bias_deg=1.5", "att_pitch_bias_deg=-2", "att_yaw_bias_deg=3", "att_noise_deg=0.5"],
        )
    )
    diff = np.degrees(biased.samples.attitude_rad - plain.samples.attitude_rad)
    diff[:, 2] = (diff[:, 2] + 180.0) % 360.0 - 180.0
    np.testing.assert_allclose(diff.mean(axis=0), [1.5, -2.0, 3.0], atol=0.05)
    np.testing.assert_allclose(diff.std(axis=0), 0.5, rtol=0.1)
    np.testing.assert_array_equal(biased.samples.mag_mgauss, plain.samples.mag_mgauss)  # nothing else moved


def test_defaults_are_the_pre_knob_run() -> None:
    cfg = SimConfig(scenario="paper", duration_s=20.0)
    assert cfg.legacy and not cfg.ap_calibration and not cfg.gps
    explicit = apply_settings(cfg, ["mag_noise_scale=1", "yaw_source=compass", "external_compass0=off"])
    assert explicit.legacy
    a, b = simulate(cfg), simulate(explicit)
    np.testing.assert_array_equal(a.samples.mag_mgauss, b.samples.mag_mgauss)
    np.testing.assert_array_equal(a.samples.attitude_rad, b.samples.attitude_rad)
    ordinary = SimConfig(scenario="ordinary", duration_s=20.0)
    assert not ordinary.legacy and ordinary.ap_calibration and ordinary.gps
    assert ordinary.vehicle == "multirotor"
    assert not apply_settings(ordinary, ["ap_calibration=off"]).ap_calibration


def test_rates_raise_the_loop_only_when_needed() -> None:
    cfg = SimConfig(scenario="ordinary")
    fast = apply_settings(cfg, ["mag_hz=100"])
    assert fast.rates.imu_hz == 100.0 and fast.rates.mag_rate == 100.0
    assert fast.rates.raw_imu_rate == 50.0  # the message rate stays where it was unless asked
    slow = apply_settings(cfg, ["telemetry_hz=2"])
    assert slow.rates.imu_hz == 50.0  # the autopilot's loop keeps running fast
    assert (slow.rates.raw_imu_rate, slow.rates.attitude_hz, slow.rates.rc_hz) == (2.0, 2.0, 2.0)
    odd = apply_settings(cfg, ["raw_imu_hz=60"])
    assert odd.rates.imu_hz == pytest.approx(200.0 / 3.0)  # the slowest divisor of 200 Hz above 60


@pytest.mark.parametrize(
    ("setting", "message"),
    [
        ("nonsense=1", "unknown setting"),
        ("mag_hz", "expected KEY=VALUE"),
        ("mag_hz=fast", "must be a number"),
        ("mag_hz=0", "rate must be in"),
        ("mag_hz=500", "rate must be in"),
        ("yaw_source=moon", "yaw_source"),
        ("external_compass0=maybe", "on/off"),
        ("ap_cal_soft_iron=0.5", "ap_cal_soft_iron"),
        ("primary_compass=2", "needs at least 3 compasses"),
        ("seed=-1", "seed"),
        ("seed=1.5", "whole number"),
        ("vehicle=fixedwing", "multirotor flight"),
        ("decimal_year=2031", "WMM-2025"),
        ("mag_ar1_sigma_mgauss=nan", "finite"),
    ],
)
def test_bad_settings_are_one_line_errors(setting: str, message: str) -> None:
    with pytest.raises(InputError, match=message) as info:
        apply_settings(SimConfig(scenario="ordinary"), [setting])
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: Variation(hover_throttle=0.9), r"hover_throttle=0.9: must be in \[0.2, 0.7\]$"),
        (lambda: Variation(mag_lsb_mgauss=0.0), r"mag_lsb_mgauss=0.0: must be in \(0, 50\]$"),
        (lambda: Variation(current_max_a=600.0), r"current_max_a=600.0: must be in \[1, 500\]$"),
        (lambda: Variation(ap_kp_yaw=math.nan), r"ap_kp_yaw=nan: must be in \[0.01, 10\]$"),
        (lambda: Rates(attitude_hz=60.0), r"attitude_hz=60.0 Hz must be in \(0, loop rate imu_hz=50.0\]$"),
        (lambda: Rates(mag_hz=0.0), r"mag_hz=0.0 Hz must be in \(0, loop rate imu_hz=50.0\]$"),
        (lambda: Rates(gps_hz=60.0), r"gps_hz=60.0 Hz must be in \(0, 50\]$"),
    ],
)
def test_out_of_range_knobs_and_rates_name_their_range(make: object, message: str) -> None:
    assert callable(make)
    with pytest.raises(InputError, match=message):
        make()
    Variation(hover_throttle=None, mag_lsb_mgauss=50.0, ap_kp_yaw=10.0)  # the edges and None pass
    Rates(attitude_hz=50.0, mag_hz=None, gps_hz=50.0)


def test_every_variation_field_is_a_setting() -> None:
    keys = set(setting_keys())
    assert {f for f in Variation.__dataclass_fields__} <= keys
    assert {"mag_hz", "raw_imu_hz", "attitude_hz", "loop_hz", "telemetry_hz", "seed", "vehicle"} <= keys


def test_cli_set_reaches_the_simulation(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from magcomp.cli import main

    out = tmp_path / "o.tlog"
    code = main(
        [
            "simulate",
            "--scenario",
            "ordinary",
            "--duration",
            "10",
            "--set",
            "telemetry_hz=2",
            "--out",
            str(out),
        ]
    )
    assert code == 0 and out.exists()
    code = main(["simulate", "--scenario", "ordinary", "--set", "bogus=1", "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert code != 0 and "unknown setting" in err and len(err.splitlines()) == 1


def test_vehicle_and_sensor_knobs_change_what_they_name() -> None:
    base = SimConfig(scenario="ordinary", duration_s=60.0, earth_field_ned_mgauss=FIELD, seed=6)
    plain = simulate(base)
    varied = simulate(
        apply_settings(
            base,
            [
                "hover_throttle=0.4",
                "current_max_a=60",
                "theta_scale=0.5",
                "gyro_bias_scale=0",
                "gyro_noise_scale=2",
                "ap_kp_yaw=0.2",
            ],
        )
    )
    hover = plain.motion.segment == plain.motion.segment_names.index("hover")
    assert np.median(plain.motion.throttle_cmd_01[hover]) == pytest.approx(0.5, abs=0.02)
    assert np.median(varied.motion.throttle_cmd_01[hover]) == pytest.approx(0.4, abs=0.02)
    thr = varied.motion.throttle_cmd_01
    np.testing.assert_allclose(varied.power.current_a, 60.0 * thr**2, atol=1e-9)  # eq. (11) chain, I_max
    for a, b in zip(plain.compasses, varied.compasses, strict=True):
        np.testing.assert_allclose(b.theta_mgauss, 0.5 * a.theta_mgauss, atol=1e-12)
        np.testing.assert_array_equal(b.gyro_bias_rad_s, 0.0)
        assert b.gyro_noise_rad_s == pytest.approx(2.0 * a.gyro_noise_rad_s)
    with_theta = apply_settings(base, ["theta_mgauss=-40,20,5"])
    assert with_theta.theta_mgauss == (-40.0, 20.0, 5.0)
    with pytest.raises(InputError, match="three numbers"):
        apply_settings(base, ["theta_mgauss=1,2"])


def test_link_loss_drops_that_fraction_of_messages_but_no_parameter() -> None:
    from magcomp.adapters.mavlink_emit import build_messages

    base = apply_settings(SimConfig(scenario="ordinary", duration_s=40.0, earth_field_ned_mgauss=FIELD), [])
    full = build_messages(simulate(base))
    lossy = build_messages(simulate(apply_settings(base, ["link_loss=0.1"])))

    def count(events: list[tuple[float, int, object]], prio: int) -> int:
        return sum(1 for e in events if e[1] == prio)

    assert count(lossy, -1) == count(full, -1)  # PARAM_VALUE all there
    n_full, n_lossy = count(full, 1), count(lossy, 1)  # RAW_IMU
    sigma = math.sqrt(0.1 * 0.9 / n_full)
    assert n_lossy / n_full == pytest.approx(0.9, abs=4 * sigma)


def test_sampled_variations_are_valid_and_simulate() -> None:
    from magcomp.adapters.mavlink_emit import build_messages
    from magcomp.sim.config import sample_variation

    rng = np.random.default_rng(10)
    draws = [sample_variation(rng) for _ in range(40)]
    configs = [apply_settings(SimConfig(scenario="ordinary", duration_s=8.0), d) for d in draws]
    assert not any(c.legacy for c in configs)
    assert {c.variation.yaw_source for c in configs} == {"compass", "truth"}
    assert any(c.variation.external_compass0 for c in configs)
    raw_rates = [c.rates.raw_imu_rate for c in configs]
    assert min(raw_rates) <= 2.0 and max(raw_rates) >= 50.0  # telemetry-like and onboard rates both drawn
    for cfg in configs[:3]:
        plane = dataclasses.replace(cfg, scenario="ordinary_plane")
        for c in (cfg, plane):
            assert build_messages(simulate(c))  # every draw runs end to end
    # numbers as values work as well as strings
    assert apply_settings(SimConfig(scenario="ordinary"), {"mag_hz": 10, "gps": False}).rates.mag_rate == 10.0
