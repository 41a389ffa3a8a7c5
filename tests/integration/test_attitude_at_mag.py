"""The roll and pitch of a magnetometer sample between two slow ATTITUDE messages: interpolated at its time
(the two-pass replay; service/attitude_at_mag.py).

On a telemetry log (ATTITUDE at 2 Hz, the field at 1.25 Hz) eq. (24) with the latest ATTITUDE's roll and
pitch lags them by up to an interval; at 60-70 deg of inclination each degree of roll is 2-3 deg of heading.
magcomp's "autopilot's own heading" (what it publishes where no correction applies, and what its self-check
compares a correction with) was then further from the autopilot's yaw than that same field tilt-compensated
at the attitude interpolated at each sample's time (a real ArduCopter 3.5.7 tlog: 10.4 against 7.0 deg rms,
published worse than the autopilot's own heading; docs/real-flights.md, eighth stop)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters.config import Config
from magcomp.adapters.mavlink_source import load_log, open_source
from magcomp.core import selfcheck as sc
from magcomp.core.heading import heading_from_trig_deg
from magcomp.core.types import AttitudeSample, ClockResetSample, ImuSample, MagSample, Sample
from magcomp.service.attitude_at_mag import AttitudeAtMag
from magcomp.service.evaluate import FLYING_THROTTLE_01
from magcomp.service.replay import replay_log


@pytest.fixture(scope="module")
def telemetry_tlog(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate
    from magcomp.sim.config import apply_settings

    cfg = apply_settings(
        SimConfig(scenario="ordinary", duration_s=180.0, seed=1), ["telemetry_hz=2", "raw_imu_hz=1.25"]
    )
    path = tmp_path_factory.mktemp("attmag") / "telemetry.tlog"
    write_tlog(simulate(cfg), path)
    return path


def _own_att_rms_deg(path: Path, idx: int) -> float:
    """The autopilot's own heading of compass ``idx`` against its yaw (offset removed, motors running): the
    field as logged, tilt-compensated at the roll and pitch interpolated at each sample's time (eq. (24))."""
    d = load_log(path, undo_motor_comp=False)
    att, s = d.attitude_rad, d.mag[idx]
    roll = np.interp(s.t_s, att.t_s, att.values[:, 0])
    pitch = np.interp(s.t_s, att.t_s, att.values[:, 1])
    m = s.values
    h = np.radians(heading_from_trig_deg(m[:, 0], m[:, 1], m[:, 2], np.cos(roll), np.sin(roll),
                                         np.cos(pitch), np.sin(pitch)))  # fmt: skip
    yaw = np.interp(s.t_s, att.t_s, np.unwrap(att.values[:, 2]))
    fly = np.interp(s.t_s, d.throttle_01.t_s, d.throttle_01.values) > FLYING_THROTTLE_01
    return float(sc.offset_removed_rms_deg(h[fly] - yaw[fly]))


def test_the_autopilots_own_heading_takes_the_attitude_at_the_samples_time(telemetry_tlog: Path) -> None:
    rep = replay_log(telemetry_tlog, Config(), two_pass=True)
    with open_source(telemetry_tlog) as src:  # the summary counts the log's samples, not the interpolated
        assert rep.summary["counts"]["samples"] == sum(1 for _ in src.samples())
    checks = {int(c["index"]): c["self_check"] for c in rep.summary["compasses"] if c.get("self_check")}
    assert checks
    for idx, chk in checks.items():
        own = _own_att_rms_deg(telemetry_tlog, idx)
        # the same heading on the same samples (held: 6.3 deg on compass 0 against 2.7)
        assert chk["baseline_att_deg"] == pytest.approx(own, rel=0.1), (idx, chk["baseline_att_deg"], own)


def _att(t: float, roll: float) -> AttitudeSample:
    return AttitudeSample(t, roll, 0.0, 0.1 * t)


def _mag(t: float, idx: int = 0) -> MagSample:
    return MagSample(t, np.array([200.0, 0.0, 400.0]), idx)


def test_a_magnetometer_sample_waits_for_the_next_attitude_when_the_stream_is_slow() -> None:
    at = AttitudeAtMag()
    assert at.push(_att(0.0, 0.0)) and at.push(_att(0.5, 0.2))  # 2 Hz: slow
    m = _mag(0.8)
    imu = ImuSample(0.85, np.zeros(3), np.array([0.0, 0.0, -9.8]))
    assert at.push(m) == [] and at.push(imu) == []  # both wait, in order
    out = at.push(_att(1.0, 0.4))
    assert [type(s) for s in out] == [AttitudeSample, MagSample, ImuSample, AttitudeSample]
    mid = out[0]
    assert isinstance(mid, AttitudeSample) and mid.t_s == pytest.approx(0.8)
    assert mid.roll_rad == pytest.approx(0.2 + 0.6 * 0.2) and mid.yaw_rad == pytest.approx(0.08)


def test_a_fast_stream_and_a_long_gap_pass_through() -> None:
    at = AttitudeAtMag()
    at.push(_att(0.0, 0.0))
    at.push(_att(0.02, 0.0))  # 50 Hz: nothing waits
    m = _mag(0.03)
    assert at.push(m) == [m]
    slow = AttitudeAtMag()
    slow.push(_att(0.0, 0.0))
    slow.push(_att(0.5, 0.0))
    assert slow.push(_mag(0.6)) == []
    late = ImuSample(0.6 + 2.5, np.zeros(3), np.zeros(3))  # no ATTITUDE for longer than MAX_BRACKET_S
    out = slow.push(late)
    assert [type(s) for s in out] == [MagSample, ImuSample]
    # a reboot releases what waits, before it
    rb = AttitudeAtMag()
    rb.push(_att(0.0, 0.0))
    rb.push(_att(0.5, 0.0))
    rb.push(_mag(0.7))
    out = rb.push(ClockResetSample(0.9, 10.0))
    assert [type(s) for s in out] == [MagSample, ClockResetSample]


def test_what_waits_is_released_at_the_end_of_the_stream() -> None:
    stream: list[Sample] = [_att(0.0, 0.0), _att(0.5, 0.0), _mag(0.7), _mag(0.7, 1)]
    assert list(AttitudeAtMag().stream(stream)) == stream
