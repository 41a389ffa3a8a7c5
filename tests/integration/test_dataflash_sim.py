"""ArduPilot 4.x DataFlash logs of simulated flights (``magcomp.adapters.dataflash_writer``): the source reads
the .bin into the samples of its tlog twin, a replay of both gives the same compass status, form, theta and
heading, ArduPilot's own motor compensation logged in MAG.MOX.. is removed end to end, and Plane's CTUN
throttle (percent) is read as 0..1."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from magcomp.adapters.config import Config
from magcomp.adapters.dataflash_writer import gps_week_ms, sim_parameters, write_sim_dataflash
from magcomp.adapters.mavlink_emit import default_start_unix_s, write_tlog
from magcomp.adapters.mavlink_source import load_log
from magcomp.core.heading import heading_from_trig_deg
from magcomp.core.types import FLAG_CALIBRATED
from magcomp.service.demo import rms_after_learning
from magcomp.service.replay import replay_log
from magcomp.sim import SimConfig, SimResult, simulate
from magcomp.sim.config import apply_settings
from tests.configs import ESTIMATOR_ONLY


@pytest.fixture(scope="module")
def ordinary(tmp_path_factory: pytest.TempPathFactory) -> tuple[SimResult, Path, Path]:
    """One ordinary multirotor flight (300 s, compass telemetry at 10 Hz) as a tlog and as a .bin."""
    d = tmp_path_factory.mktemp("dfsim")
    cfg = apply_settings(SimConfig(scenario="ordinary", duration_s=300.0, seed=11), ["telemetry_hz=10"])
    result = simulate(cfg)
    write_tlog(result, d / "twin.tlog")
    write_sim_dataflash(result, d / "twin.bin")
    return result, d / "twin.tlog", d / "twin.bin"


def _same_series(a: Any, b: Any, atol: float) -> None:
    assert a.values.shape == b.values.shape and len(a) > 0
    np.testing.assert_allclose(b.t_s, a.t_s, atol=1e-6)
    np.testing.assert_allclose(b.values, a.values, atol=atol)


def test_bin_reads_into_the_tlog_twins_samples(ordinary: tuple[SimResult, Path, Path]) -> None:
    result, tlog, binf = ordinary
    a, b = load_log(tlog), load_log(binf)
    assert sorted(b.mag) == sorted(a.mag) == [0, 1]
    for j in a.mag:  # both 1 mgauss integers of the same samples
        _same_series(a.mag[j], b.mag[j], 0.0)
    # ATT: centidegrees in the .bin, float radians in the tlog; yaw 0..360 against -180..180
    assert len(b.attitude_rad) == len(a.attitude_rad) > 0
    d = b.attitude_rad.values - a.attitude_rad.values
    d[:, 2] = np.remainder(d[:, 2] + np.pi, 2 * np.pi) - np.pi
    assert np.abs(d).max() < np.radians(0.006)
    assert b.throttle_source == a.throttle_source == "motors:1,2,3,4"
    _same_series(a.throttle_01, b.throttle_01, 1e-9)
    _same_series(a.voltage_v, b.voltage_v, 1e-5)  # float32 volts / amps against mV / cA
    _same_series(a.current_a, b.current_a, 1e-5)
    # GPS: Lat/Lng 1e-7 deg both, Alt cm (.bin) against mm (tlog)
    assert len(b.position) > 0 and len(a.position) > 0
    np.testing.assert_allclose(b.position.values[:, :2], result.samples.gps is not None
                               and a.position.values[: len(b.position), :2], atol=2e-7)  # fmt: skip
    np.testing.assert_allclose(b.position.values[:, 2], a.position.values[: len(b.position), 2], atol=0.006)
    # the date: GPS week + ms (GPS time, 18 s ahead of UTC: 6e-7 year) against SYSTEM_TIME's UTC
    assert abs(b.decimal_year - a.decimal_year) < 1e-6
    assert b.vehicle_type == a.vehicle_type == 2 and b.autopilot == a.autopilot == 3
    assert {k: b.params[k] for k in a.params} == a.params  # every PARAM_VALUE of the twin, same value
    extra = set(b.params) - set(a.params)
    assert extra == {"AHRS_EKF_TYPE", "EK3_SRC1_YAW", "COMPASS_USE2", "MOT_PWM_MIN", "MOT_PWM_MAX"}


def test_gps_week_and_time_of_week() -> None:
    # 2024-01-01 00:00:00 UTC: GPS week 2295, day 1 (Monday), + 18 leap seconds
    week, ms = gps_week_ms(1704067200.0)
    assert (week, ms) == (2295, 86_400_000 + 18_000)


def test_bin_replays_like_its_tlog_twin(ordinary: tuple[SimResult, Path, Path]) -> None:
    result, tlog, binf = ordinary
    # the readers' equivalence, through the 1 s heading filter: with the default 4 s one the tlog's gyro, one
    # RAW_IMU sample per 10 Hz compass interval, integrates its sampling error for longer than the .bin's
    # 50 Hz IMU (measured heading rms 1.12 / 1.12 against 0.77 / 0.67 deg; 0.95 / 0.78 and 0.97 / 0.78 at 1 s)
    cfg = replace(ESTIMATOR_ONLY, output=replace(ESTIMATOR_ONLY.output, heading_tau_s=1.0))
    a = replay_log(tlog, cfg, keep_estimates=True)
    b = replay_log(binf, cfg, keep_estimates=True)
    assert len(a.estimates) == len(b.estimates) > 0
    for j in (0, 1):
        ca, cb = a.summary["compasses"][j], b.summary["compasses"][j]
        assert cb["status"] == ca["status"] == "corrected"
        assert cb["inflight"]["form"] == ca["inflight"]["form"]
        # theta: the in-flight fit of the same samples up to the .bin's 0.01 deg attitude (measured 0.1 and
        # 1.1 mgauss apart), well inside the fit's own 1-sigma (3-6 mgauss per axis here)
        d = np.subtract(cb["theta_mgauss"], ca["theta_mgauss"])
        assert np.linalg.norm(d) < 2.0
        assert np.all(np.abs(d) < 0.5 * np.asarray(ca["inflight"]["theta_sigma_mgauss"]))
        rms_a, raw_a = rms_after_learning(result, a.estimates, j)
        rms_b, raw_b = rms_after_learning(result, b.estimates, j)
        assert abs(rms_b - rms_a) < 0.1 and abs(raw_b - raw_a) < 0.1  # deg (measured: up to 0.054)
        assert rms_b < 2.5


def test_onboard_motor_compensation_in_mag_is_removed(
    ordinary: tuple[SimResult, Path, Path], tmp_path: Path
) -> None:
    """COMPASS_MOTCT = 1: ArduPilot adds COMPASS_MOT * throttle to MagX.. and logs it in MOX..; the source
    subtracts it, so the replay equals the uncompensated .bin's."""
    result, _, binf = ordinary
    mot = np.array([[25.0, -40.0, 60.0], [-10.0, 15.0, 30.0]])
    comp = tmp_path / "motct.bin"
    write_sim_dataflash(result, comp, motor_comp=mot)
    raw = load_log(comp, undo_motor_comp=False)
    plain, undone = load_log(binf), load_log(comp)
    assert raw.params["COMPASS_MOTCT"] == 1.0 and raw.params["COMPASS_MOT2_Z"] == 30.0
    assert np.abs(raw.mag[0].values - plain.mag[0].values).max() > 30.0  # the compensation is really there
    for j in (0, 1):
        _same_series(plain.mag[j], undone.mag[j], 0.0)
    assert undone.counts["motor_comp_removed"] > 0
    cfg = ESTIMATOR_ONLY
    a = replay_log(binf, cfg, keep_estimates=True)
    b = replay_log(comp, cfg, keep_estimates=True)
    for j in (0, 1):
        ca, cb = a.summary["compasses"][j], b.summary["compasses"][j]
        assert cb["status"] == ca["status"] and cb["inflight"]["form"] == ca["inflight"]["form"]
        np.testing.assert_allclose(cb["theta_mgauss"], ca["theta_mgauss"], atol=1e-6)
        ea = [e for e in a.estimates if e.mag_index == j]
        eb = [e for e in b.estimates if e.mag_index == j]
        both = zip(ea, eb, strict=True)
        cal = np.array([bool(x.flags & FLAG_CALIBRATED and y.flags & FLAG_CALIBRATED) for x, y in both])
        assert cal.mean() > 0.5
        ha = np.array([e.heading_deg for e in ea])[cal]  # corrected: the same, compensation removed or not
        hb = np.array([e.heading_deg for e in eb])[cal]
        assert np.abs(np.remainder(hb - ha + 180.0, 360.0) - 180.0).max() < 1e-6


def _heading_at(series: Any, t: np.ndarray, trig: tuple[np.ndarray, ...]) -> np.ndarray:
    """Eq. (24) of a logged field series at times ``t`` (its sample at or after each) with ``trig``."""
    i = np.clip(np.searchsorted(series.t_s, t), 0, len(series) - 1)
    m = series.values[i]
    return np.asarray(heading_from_trig_deg(m[:, 0], m[:, 1], m[:, 2], *trig))


def test_uncorrected_heading_is_the_autopilots_with_its_motor_compensation(
    ordinary: tuple[SimResult, Path, Path], tmp_path: Path
) -> None:
    """Where magcomp corrects nothing, it publishes the autopilot's own heading: the field as logged, with
    ArduPilot's motor compensation (MAG.MOX..) in it, not the field the source took it out of."""
    result, _, _ = ordinary
    comp = tmp_path / "motct.bin"
    write_sim_dataflash(result, comp, motor_comp=np.array([[25.0, -40.0, 60.0], [-60.0, 45.0, 80.0]]))
    base = Config()
    cfg = replace(base, inflight=replace(base.inflight, enabled=False),
                  output=replace(base.output, heading_tau_s=0.0))  # fmt: skip
    rep = replay_log(comp, cfg, keep_estimates=True)
    logged, undone = load_log(comp, undo_motor_comp=False), load_log(comp)
    att = logged.attitude_rad
    for j in (0, 1):
        es = [e for e in rep.estimates if e.mag_index == j]
        t = np.array([e.t_s for e in es])
        k = np.clip(np.searchsorted(att.t_s, t, side="right") - 1, 0, len(att) - 1)  # the latest ATT
        roll, pitch = att.values[k, 0], att.values[k, 1]
        trig = (np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch))

        pub = np.array([e.heading_deg for e in es])
        own = np.abs(np.remainder(pub - _heading_at(logged.mag[j], t, trig) + 180.0, 360.0) - 180.0)
        bare = np.abs(np.remainder(pub - _heading_at(undone.mag[j], t, trig) + 180.0, 360.0) - 180.0)
        # measured 0.27 / 1.98 deg (median), 0.70 / 5.0 (90th percentile): the rest is the attitude's timing
        assert np.median(own) < 0.25 * np.median(bare), (np.median(own), np.median(bare))
        assert np.percentile(own, 90) < 0.25 * np.percentile(bare, 90)


def test_plane_ctun_throttle_is_percent(tmp_path: Path) -> None:
    """ArduPlane logs CTUN.ThO in percent (Copter 0..1): read as 0..1, the servo throttle's value."""
    result = simulate(SimConfig(scenario="flight_fixedwing", duration_s=20.0, seed=3))
    path = tmp_path / "plane.bin"
    write_sim_dataflash(result, path)
    servo = load_log(path)
    ctun = load_log(path, throttle_source="ctun")
    assert servo.vehicle_type == 1 and servo.throttle_source == "servo:3"
    assert ctun.throttle_source == "ctun" and len(ctun.throttle_01) == len(servo.throttle_01)
    assert 0.2 < float(np.mean(servo.throttle_01.values)) < 0.95
    np.testing.assert_allclose(ctun.throttle_01.values, servo.throttle_01.values, atol=1e-6)


def test_parameters_match_the_tlog_twins_and_the_autopilot() -> None:
    result = simulate(replace(SimConfig(scenario="ordinary", duration_s=5.0, seed=2)))
    p = dict(sim_parameters(result))
    assert p["SERVO1_FUNCTION"] == 33.0 and p["SERVO4_FUNCTION"] == 36.0
    assert p["AHRS_EKF_TYPE"] == 3.0 and p["EK3_SRC1_YAW"] == 1.0 and p["COMPASS_MOTCT"] == 0.0
    assert p["COMPASS_EXTERNAL"] == 0.0 and p["COMPASS_USE"] == 1.0
    assert default_start_unix_s(result) > 1.5e9


def test_plane_3x_ctun_throttrout_is_percent(tmp_path: Path) -> None:
    """ArduPlane 3.x: CTUN.ThrOut an int16 percent (Copter 3.3's ThrOut is 0..1000)."""
    from magcomp.adapters.dataflash_writer import DataflashWriter

    w = DataflashWriter()
    w.define("MSG", "QZ", "TimeUS,Message")
    w.define("CTUN", "Qcccchhhf", "TimeUS,NavRoll,Roll,NavPitch,Pitch,ThrOut,RdrOut,ThrDem,Aspd")
    w.define("ATT", "QccccCCCC", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw")
    w.add("MSG", [1000, b"ArduPlane V3.9.11"])
    for k in range(10):
        w.add("ATT", [1500 + 100_000 * k, 0, 0, 0, 0, 9000, 9000, 0, 0])
        w.add("CTUN", [2000 + 100_000 * k, 0, 0, 0, 0, 10 * k, 0, 10 * k, 15.0])
    path = tmp_path / "plane39.bin"
    w.write(path)
    got = load_log(path, throttle_source="ctun").throttle_01.values
    np.testing.assert_allclose(got, 0.1 * np.arange(10), atol=1e-12)


def test_bat_instance_field_spelled_instance(tmp_path: Path) -> None:
    """Early ArduPilot 4.x logs BAT with the instance field ``Instance`` (later ``Inst``): battery 1's samples
    must not be read as battery 0's."""
    from magcomp.adapters.dataflash_writer import DataflashWriter

    w = DataflashWriter()
    w.define("MSG", "QZ", "TimeUS,Message")
    w.define("ATT", "QccccCCCC", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw")
    w.define("BAT", "QBfffffcf", "TimeUS,Instance,Volt,VoltR,Curr,CurrTot,EnrgTot,Temp,Res")
    w.add("MSG", [1000, b"ArduCopter V4.0.7"])
    for k in range(10):
        t = 2000 + 100_000 * k
        w.add("ATT", [t, 0, 0, 0, 0, 9000, 9000, 0, 0])
        w.add("BAT", [t + 10, 0, 16.0, 16.1, 12.0, 100.0, 1.0, 2500, 0.01])
        w.add("BAT", [t + 20, 1, 5.0, 5.0, 0.5, 3.0, 0.0, 2500, 0.01])
    path = tmp_path / "two_batteries.bin"
    w.write(path)
    data = load_log(path)
    assert len(data.voltage_v) == len(data.current_a) == 10
    np.testing.assert_allclose(data.voltage_v.values, 16.0)
    np.testing.assert_allclose(data.current_a.values, 12.0)


def test_simulate_cli_writes_a_dataflash_bin(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from magcomp.cli import main

    out = tmp_path / "run.bin"
    args = ["simulate", "--scenario", "flight_multirotor", "--duration", "8", "--seed", "4"]
    args += ["--compasses", "3"]
    assert main([*args, "--out", str(out)]) == 0
    assert out.read_bytes()[:3] == b"\xa3\x95\x80"  # a DataFlash FMT first
    assert (tmp_path / "run.truth.json").exists() and "wrote" in capsys.readouterr().out
    data = load_log(out)
    assert sorted(data.mag) == [0, 1, 2] and data.vehicle_type == 2


def test_units_and_lazy_formats_read_like_a_plain_log(
    ordinary: tuple[SimResult, Path, Path], tmp_path: Path
) -> None:
    """ArduPilot 4.x writes each FMT just before its first message and UNIT / MULT / FMTU tables (FMTU's
    ``#`` makes DFReader index the instance field, its multipliers only rename units): the same samples as a
    log with every FMT first and no units."""
    from pymavlink import DFReader

    result, _, binf = ordinary  # written with units and lazy formats (the default)
    plain = tmp_path / "plain.bin"
    write_sim_dataflash(result, plain, units=False, lazy_formats=False)
    reader = DFReader.DFReader_binary(str(binf))
    try:
        mag = reader.recv_match(type="MAG")
    finally:
        reader.close()
    assert mag is not None and mag.fmt.instance_field == "I" and mag.fmt.units[2] == "mGauss"
    assert isinstance(mag.MagX, int)  # still mgauss: the FMTU multiplier C is not applied
    a, b = load_log(plain), load_log(binf)
    assert "garbage_bytes" not in b.counts and b.counts["messages"] == a.counts["messages"]
    for j in (0, 1):
        _same_series(a.mag[j], b.mag[j], 0.0)
    _same_series(a.attitude_rad, b.attitude_rad, 0.0)
    _same_series(a.throttle_01, b.throttle_01, 0.0)
    _same_series(a.position, b.position, 0.0)
    assert a.params == b.params and a.decimal_year == b.decimal_year


def _mag_log(path: Path, params: dict[str, float], mox: list[int]) -> None:
    """A small 4.x log: PARMs, ATT and MAG (compass 0, field (200, -100, 400) mgauss as logged) whose MOX is
    ``mox[k]`` in message k."""
    from magcomp.adapters.dataflash_writer import FORMATS, DataflashWriter

    w = DataflashWriter(units=True, lazy_formats=True)
    for name in ("PARM", "MSG", "ATT", "MAG"):
        w.define(name, *FORMATS[name])
    w.add("MSG", [1000, b"ArduCopter V4.5.7"])
    for name, value in params.items():
        w.add("PARM", [1000, name.encode(), value, value])
    for k, mo in enumerate(mox):
        t = 2000 + 20_000 * k
        w.add("ATT", [t, 0, 0, 0, 0, 9000, 9000, 0, 0, 3])
        w.add("MAG", [t + 10, 0, 200, -100, 400, 0, 0, 0, mo, 0, 0, 1, t])
    w.write(path)


def test_mag_motor_offset_with_compensation_off_is_not_subtracted(tmp_path: Path) -> None:
    """With COMPASS_MOTCT = 0 the autopilot adds no motor offset: a non-zero MOX is a corrupt record (a byte
    hit; DataFlash has no checksum). Subtracting it made a jump in the field and a warning that the
    autopilot's compensation (off) 'was wrong'."""
    mox = [0] * 50
    mox[10], mox[30] = 8000, -5000  # two hit records
    off = tmp_path / "off.bin"
    _mag_log(off, {"COMPASS_MOTCT": 0.0, "COMPASS_MOT_X": 0.0}, mox)
    data = load_log(off)
    np.testing.assert_array_equal(data.mag[0].values, np.tile([200.0, -100.0, 400.0], (50, 1)))
    assert data.counts["motor_comp_ignored"] == 2 and "motor_comp_removed" not in data.counts
    # COMPASS_MOTCT = 1 (or the parameters unknown): the logged offset is the autopilot's, undone
    for params in ({"COMPASS_MOTCT": 1.0, "COMPASS_MOT_X": 50.0}, {}):
        on = tmp_path / "on.bin"
        _mag_log(on, params, [25] * 50)
        got = load_log(on)
        np.testing.assert_array_equal(got.mag[0].values, np.tile([175.0, -100.0, 400.0], (50, 1)))
        assert got.counts["motor_comp_removed"] == 50
    # per-motor compensation (compass 0) adds an offset whatever COMPASS_MOTCT says
    pm = tmp_path / "pmot.bin"
    _mag_log(pm, {"COMPASS_MOTCT": 0.0, "COMPASS_PMOT_EN": 1.0}, [25] * 50)
    assert load_log(pm).counts["motor_comp_removed"] == 50


@pytest.fixture(scope="module")
def plain_bin(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    """A 60 s ordinary flight, every FMT first (FMT, PARM, MSG, IMU, MAG, ATT, RCOU, BAT, GPS, CTUN)."""
    path = tmp_path_factory.mktemp("plain") / "plain.bin"
    write_sim_dataflash(simulate(SimConfig(scenario="ordinary", duration_s=60.0, seed=2)), path, units=False,
                        lazy_formats=False)  # fmt: skip
    return path.read_bytes()


def _fmt_offset(data: bytes, name: str) -> int:
    for p in range(0, 4096, 89):
        if data[p : p + 3] == b"\xa3\x95\x80" and data[p + 5 : p + 9].rstrip(b"\0") == name.encode():
            return p
    raise AssertionError(name)


@pytest.mark.parametrize("hit", ["format_char", "length"])
def test_a_byte_hit_in_one_fmt_loses_that_message_type_only(
    plain_bin: bytes, tmp_path: Path, hit: str
) -> None:
    """A byte hit inside an FMT (DataFlash has no checksum): a bad format character made pymavlink's reader
    raise (a traceback, not a one-line error), a bad length made every CTUN look like damage (the samples
    around each dropped). Now that FMT is not believed and only its type's messages are skipped."""
    p = _fmt_offset(plain_bin, "CTUN")
    data = bytearray(plain_bin)
    if hit == "format_char":
        data[p + 3 + 6 + 3] = ord("\\")
    else:
        data[p + 4] = 200
    path = tmp_path / "hit.bin"
    path.write_bytes(bytes(data))
    got = load_log(path)
    assert {k: len(v) for k, v in got.mag.items()} == {0: 3000, 1: 3000}
    assert len(got.attitude_rad) == 1500 and len(got.params) == 55 and got.throttle_source == "motors:1,2,3,4"
    assert got.counts["dataflash_resyncs"] == 0 and got.counts["garbage_bytes"] > 0  # the CTUNs skipped


def test_fmts_just_before_damage_are_kept(plain_bin: bytes, tmp_path: Path) -> None:
    """Damage a little after the FMT block (and more later in the log): the FMTs within the damage margin
    before it were dropped with the other messages there, so no later message had a format ("no DataFlash
    messages found")."""
    p = plain_bin.find(b"\xa3\x95", _fmt_offset(plain_bin, "CTUN") + 89 + 1000)
    q = plain_bin.find(b"\xa3\x95", len(plain_bin) // 2)
    data = bytearray(plain_bin)
    data[p] ^= 0xFF  # two message headers hit
    data[q] ^= 0xFF
    path = tmp_path / "hit.bin"
    path.write_bytes(bytes(data))
    got = load_log(path)
    assert got.counts["dataflash_resyncs"] == 2
    assert len(got.mag[0]) > 0.9 * 3000 and len(got.attitude_rad) > 0.9 * 1500
