"""`magcomp diagnose` end to end: a simulated tlog (+ truth beside it) -> JSON, Markdown report, plots."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters.mavlink_emit import write_tlog, write_truth
from magcomp.cli import main
from magcomp.sim import SimConfig, simulate

REQUIRED_KEYS = {"findings", "residual_rms_baseline", "residual_rms_extended", "gain", "compasses"}
COMPASS_KEYS = {"index", "source", "theta", "residual_rms_baseline", "residual_rms_extended", "findings"}
FINDING_KEYS = {"effect", "cause", "params", "evidence", "residual_rms_after"}


@pytest.fixture(scope="module")
def skewed_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("diag")
    res = simulate(SimConfig(scenario="paper", duration_s=45.0, seed=21, effects={"time_skew": 0.3}))
    path = d / "skew.tlog"
    write_tlog(res, path)
    write_truth(res, path)
    return path


def test_cli_writes_json_with_the_issue_keys_and_finds_the_skew(
    skewed_log: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = skewed_log.with_suffix(".json")
    assert main(["diagnose", str(skewed_log), "--json", str(out)]) == 0
    j = json.loads(out.read_text())
    assert set(j) >= REQUIRED_KEYS
    assert len(j["compasses"]) == 2
    for c in j["compasses"]:
        assert set(c) >= COMPASS_KEYS
        assert len(c["theta"]) == 3
    assert j["findings"][0]["effect"] == "time_skew"
    assert set(j["findings"][0]) >= FINDING_KEYS
    assert abs(j["findings"][0]["params"]["skew_s"] - 0.3) < 0.04
    # the truth beside the log is found and used as the heading reference
    assert j["gain"]["heading_reference"] == "truth"
    assert j["gain"]["heading_error_rms_deg"]["extended"] < j["gain"]["heading_error_rms_deg"]["paper"]
    # both autopilots' parameters are given, with the linearisation caveat
    ap = j["compasses"][0]["autopilot"]
    assert {"COMPASS_MOT_X", "COMPASS_MOT_Y", "COMPASS_MOT_Z"} <= set(ap["ardupilot"])
    assert {"CAL_MAG0_XCOMP", "CAL_MAG0_YCOMP", "CAL_MAG0_ZCOMP"} <= set(ap["px4_throttle"])
    assert "linearly" in j["compasses"][0]["linearisation"]
    # the console line gives the parameter with its 95 % interval, as the JSON has it (issue 26)
    lo, hi = j["findings"][0]["params"]["skew_s_ci95"]
    console = capsys.readouterr().out
    assert "time_skew" in console
    assert f"skew_s={j['findings'][0]['params']['skew_s']:.3g} [{lo:.3g}, {hi:.3g}]" in console, console


def test_cli_report_has_plots_and_names_the_cause(skewed_log: Path) -> None:
    md = skewed_log.parent / "report.md"
    assert main(["diagnose", str(skewed_log), "--report", str(md)]) == 0
    text = md.read_text()
    assert "time_skew" in text and "COMPASS_MOT" in text
    assert "**Against the gyro** (10 s windows" in text  # theta's check, as the console prints it
    # an ArduPilot log: its own parameters only (the JSON keeps both); no "None" in the prose
    assert "CAL_MAG" not in text and "None" not in text
    pngs = sorted((md.parent / "report_img").glob("*.png"))
    assert len(pngs) >= 4
    assert all(p.stat().st_size > 5000 for p in pngs)
    for p in pngs:
        assert f"report_img/{p.name}" in text


def test_cli_missing_file_is_a_one_line_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["diagnose", str(tmp_path / "nope.tlog")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no such file" in err[0]


def test_cli_rerun_save_writes_a_recording(skewed_log: Path) -> None:
    pytest.importorskip("magcomp.adapters.rerun_viz")
    rrd = skewed_log.parent / "diag.rrd"
    # in a process of its own: the Rerun SDK's native threads outlive the recording
    cmd = [sys.executable, "-m", "magcomp", "diagnose", str(skewed_log), "--rerun", f"save={rrd}"]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    assert rrd.is_file() and rrd.stat().st_size > 10_000


def test_cli_does_not_claim_to_leave_out_an_impact_it_kept(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A 5 s flight whose every sample lies within the impact window of its > 2.5 g take-off: the diagnosis
    keeps them all (fewer than 50 would remain), so the note must not say they were left out."""
    res = simulate(SimConfig(scenario="ordinary", duration_s=5.0, seed=22))
    path = tmp_path / "short.tlog"
    write_tlog(res, path)
    assert main(["diagnose", str(path), "--json", str(tmp_path / "d.json")]) == 0
    out = capsys.readouterr().out
    assert "with an impact above 2.5 g (a crash" not in out, out
    assert "impact above 2.5 g around t =" in out and "kept" in out, out
    doc = json.loads((tmp_path / "d.json").read_text())
    assert doc["compasses"], doc


def test_cli_notes_the_impacts_left_out_once_per_log(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The stretches left out for an impact (the > 2.5 g take-off of a simulated flight) are the same for
    every compass of the log: one note names them all with the compasses (issue 25: repeated warnings
    summarised), not one line per compass and stretch."""
    res = simulate(SimConfig(scenario="ordinary", duration_s=40.0, seed=23))
    acc = res.samples.accel_m_s2.copy()
    t = res.samples.t_s
    for t_hit in (15.0, 28.0):  # two knocks of 4 g, 50 ms each, on every IMU
        acc[:, (t >= t[0] + t_hit) & (t < t[0] + t_hit + 0.05)] = (0.0, 0.0, -4.0 * 9.80665)
    res = replace(res, samples=replace(res.samples, accel_m_s2=acc))
    path = tmp_path / "flight.tlog"
    write_tlog(res, path)
    assert main(["diagnose", str(path)]) == 0
    out = capsys.readouterr().out
    lines = [ln for ln in out.splitlines() if "with an impact above 2.5 g" in ln]
    assert len(lines) == 1, out
    assert lines[0].startswith("note: compasses 0, 1: left out 2 stretches"), lines[0]


@pytest.mark.parametrize("theta_on", [True, False])
def test_cli_judges_its_model_against_the_gyro(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], theta_on: bool
) -> None:
    """diagnose says per compass whether the heading its model gives is better than the field as logged
    against the gyro (diagnosis/gyro_check.py, the replay's self-check): on a simulated flight whose compass
    0 carries theta and no calibration, the model helps (its rms below 0.8 of the field's); with no theta and
    the autopilot's calibration exact, there is nothing to correct and it does not."""
    from magcomp.sim.config import Variation

    exact = Variation(theta_scale=0.0, ap_calibration=True, ap_cal_hard_iron_mgauss=0.0, ap_cal_soft_iron=0.0)
    var = Variation() if theta_on else exact
    path = tmp_path / "flight.tlog"
    write_tlog(simulate(SimConfig(scenario="ordinary", duration_s=120.0, seed=5, variation=var)), path)
    assert main(["diagnose", str(path), "--json", str(tmp_path / "d.json")]) == 0
    out = capsys.readouterr().out
    h = json.loads((tmp_path / "d.json").read_text())["compasses"][0]["heading_vs_gyro"]
    assert h is not None and h["windows"] >= 10, h
    assert "compass 0: heading vs gyro, the field as logged -> with this theta removed:" in out, out
    if theta_on:
        assert h["helps"] and h["model_gyro_deg"] < 0.8 * h["baseline_gyro_deg"], h
    else:
        assert not h["helps"] and ("no clear gain" in out or "makes it worse" in out), h


def test_check_against_the_gyro_survives_a_nan_attitude(tmp_path: Path) -> None:
    """A damaged ATTITUDE record (NaN) early in the log must not end the check's unwrapped yaw
    (diagnosis/gyro_check.py), the reference where the gyro comes slow: the check is made over the same
    windows, with the same figures within 5 %."""
    from magcomp.commands.diagnose import diagnose_file
    from magcomp.core.types import Series
    from magcomp.diagnosis.gyro_check import heading_check, references

    path = tmp_path / "flight.tlog"
    write_tlog(simulate(SimConfig(scenario="ordinary", duration_s=120.0, seed=5)), path)
    d, log = diagnose_file(str(path))
    # the IMU as 2.5 Hz telemetry: the autopilot's yaw is then the check's windowed reference
    log = replace(log, imu_t_s=log.imu_t_s[::20], gyro_rad_s=log.gyro_rad_s[::20])
    refs = references(log, d.yaw_follow)
    assert refs is not None
    clean = heading_check(d.compasses[0], refs)
    v = log.attitude_rad.values.copy()
    v[50:53] = np.nan
    damaged_log = replace(log, attitude_rad=Series(log.attitude_rad.t_s, v))
    damaged_refs = references(damaged_log, d.yaw_follow)
    assert damaged_refs is not None
    damaged = heading_check(d.compasses[0], damaged_refs)
    assert clean is not None and damaged is not None
    assert damaged.n_windows == clean.n_windows, (damaged, clean)
    assert abs(damaged.candidate_gyro_deg - clean.candidate_gyro_deg) < 0.05 * clean.candidate_gyro_deg


def test_cli_says_when_the_calibration_not_theta_is_what_helps(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A simulated flight with no current-driven bias and the raw (uncalibrated) field logged: theta alone
    gives no clear gain against the gyro, the diagnosis's whole model (its calibration) helps, and diagnose
    says the compass wants calibrating again."""
    from magcomp.sim.config import Variation

    path = tmp_path / "flight.tlog"
    var = Variation(theta_scale=0.0)
    write_tlog(simulate(SimConfig(scenario="ordinary", duration_s=120.0, seed=5, variation=var)), path)
    assert main(["diagnose", str(path), "--json", str(tmp_path / "d.json")]) == 0
    out = capsys.readouterr().out
    c = json.loads((tmp_path / "d.json").read_text())["compasses"][0]
    assert not c["heading_vs_gyro"]["helps"], c["heading_vs_gyro"]
    m = c["heading_vs_gyro_model"]
    assert m["helps"] and m["model_gyro_deg"] < 0.9 * m["baseline_gyro_deg"], m
    assert "the autopilot's calibration of this compass is off" in out, out
