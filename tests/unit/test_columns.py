"""Bounded memory on long logs (issue 12, item 12): ``load_log`` streams the file and keeps compact columns.

The columnar loader gives what a straightforward pymavlink read of the same seeded log gives (message counts
and values); the file read a chunk at a time gives the same messages and counts of bad input as the whole
file at once; a window cut while reading gives the same offline fit as the whole log cut afterwards.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

import magcomp.adapters.mavlink_source as ms
from magcomp.adapters import mavlink_frames
from magcomp.adapters.columns import PwmRows, Rows, Window
from magcomp.adapters.mavlink_emit import write_tlog
from magcomp.adapters.throttle import resolve_throttle, throttle_from_pwm
from magcomp.errors import MagcompError
from magcomp.sim import SimConfig, simulate

G = 9.80665


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("cols") / "mr.tlog"
    write_tlog(simulate(SimConfig(scenario="flight_multirotor", duration_s=30.0, seed=4)), path)
    return path


def _pymavlink_read(path: Path) -> tuple[dict[str, list[tuple[float, tuple[float, ...]]]], dict[str, float]]:
    """Rows per message type and the parameters, read the plain way: mavutil, recv_match, fields by name."""
    from magcomp.adapters.dialect import ensure_dialect

    ensure_dialect()
    from pymavlink import mavutil

    out: dict[str, list[tuple[float, tuple[float, ...]]]] = {}
    params: dict[str, float] = {}
    conn = mavutil.mavlink_connection(str(path), dialect="magcomp")
    try:
        while (m := conn.recv_match(type=["RAW_IMU", "SCALED_IMU2", "SCALED_IMU3", "ATTITUDE",
                                          "SERVO_OUTPUT_RAW", "PARAM_VALUE"])) is not None:  # fmt: skip
            kind = m.get_type()
            if kind in ("RAW_IMU", "SERVO_OUTPUT_RAW"):
                t = m.time_usec * 1e-6
            elif kind == "PARAM_VALUE":
                params[m.param_id] = m.param_value
                continue
            else:
                t = m.time_boot_ms * 1e-3
            if kind == "ATTITUDE":
                row: tuple[float, ...] = (m.roll, m.pitch, m.yaw)
            elif kind == "SERVO_OUTPUT_RAW":
                row = tuple(float(getattr(m, f"servo{i}_raw")) for i in range(1, 9))
            else:
                row = (m.xmag, m.ymag, m.zmag, m.xgyro * 1e-3, m.ygyro * 1e-3, m.zgyro * 1e-3,
                       m.xacc * G * 1e-3, m.yacc * G * 1e-3, m.zacc * G * 1e-3)  # fmt: skip
            out.setdefault(kind, []).append((t, row))
    finally:
        conn.close()
    return out, params


def test_columnar_load_log_matches_a_plain_pymavlink_read(flight: Path) -> None:
    ref, params = _pymavlink_read(flight)
    log = ms.load_log(flight)
    assert log.params == params and len(params) > 5
    assert log.counts.get("time_backwards", 0) == 0 and log.counts.get("clock_resets", 0) == 0
    for index, kind in enumerate(("RAW_IMU", "SCALED_IMU2", "SCALED_IMU3")):
        rows = ref.get(kind, [])
        if not rows:
            assert index not in log.mag
            continue
        t = np.array([r[0] for r in rows])
        v = np.array([r[1] for r in rows])
        has_mag = np.any(v[:, :3] != 0, axis=1)
        s = log.mag[index]
        assert len(s) == int(has_mag.sum()) > 100
        np.testing.assert_array_equal(s.t_s, t[has_mag])
        np.testing.assert_array_equal(s.values, v[has_mag, :3])
        if kind == "RAW_IMU":
            assert log.imu_t_s.shape[0] == len(rows)
            np.testing.assert_array_equal(log.imu_t_s, t)
            np.testing.assert_allclose(log.gyro_rad_s, v[:, 3:6], rtol=1e-15, atol=0)
            np.testing.assert_allclose(log.accel_m_s2, v[:, 6:9], rtol=1e-15, atol=0)
    att = np.array([r[1] for r in ref["ATTITUDE"]])
    assert len(log.attitude_rad) == att.shape[0] > 100
    np.testing.assert_array_equal(log.attitude_rad.values, att)
    # throttle: the motors' PWM of every SERVO_OUTPUT_RAW, mapped with the log's own parameters
    servo = ref["SERVO_OUTPUT_RAW"]
    resolved = resolve_throttle("motors", log.vehicle_type, log.params, {"servo"})
    assert resolved is not None
    expect = [(t, throttle_from_pwm(resolved, dict(enumerate(row, start=1)))) for t, row in servo]
    kept = [(t, e) for t, e in expect if e is not None]
    assert len(log.motors_01) == len(kept) > 100
    np.testing.assert_array_equal(log.motors_01.t_s, [t for t, _ in kept])
    np.testing.assert_array_equal(log.motors_01.values, [e[1] for _, e in kept])
    np.testing.assert_array_equal(log.throttle_01.values, [e[0] for _, e in kept])


def _damaged(flight: Path, tmp_path: Path) -> Path:
    data = bytearray(flight.read_bytes())
    rng = np.random.default_rng(9)
    for at in rng.choice(np.arange(1000, len(data) - 1000), size=40, replace=False):
        data[int(at)] ^= 0xA5  # flipped bytes: CRC failures and broken framing
    junk = bytes(rng.integers(0, 256, size=3000, dtype=np.uint8))
    mid = len(data) // 2
    out = tmp_path / "damaged.tlog"
    tail = bytes(8) + bytes([0xFD, 50]) + bytes(20)  # a MAVLink 2 header announcing more than is left
    out.write_bytes(bytes(data[:mid]) + junk + bytes(data[mid:]) + tail)
    return out


@pytest.mark.parametrize("chunk", [301, 4096, 65_537])
def test_reading_in_chunks_gives_the_same_messages_and_counts_as_the_whole_file(
    flight: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, chunk: int
) -> None:
    path = _damaged(flight, tmp_path)

    def read() -> tuple[list[tuple[str, float]], dict[str, int]]:
        with ms.open_source(path) as src:
            assert isinstance(src, ms.MavSource)
            got = [(type(s).__name__, float(s.t_s)) for s in src.samples()]
            return got, dict(src.counts)

    monkeypatch.setattr(mavlink_frames, "READ_CHUNK_BYTES", 1 << 30)  # the whole file at once
    whole, whole_counts = read()
    monkeypatch.setattr(mavlink_frames, "READ_CHUNK_BYTES", chunk)
    chunked, chunked_counts = read()
    assert chunked_counts == whole_counts
    assert chunked == whole
    assert whole_counts["bad_crc"] > 0 and whole_counts["garbage_bytes"] >= 3000
    assert whole_counts["truncated"] == 1


def test_window_cut_while_reading_gives_the_same_fit_as_the_whole_log(tmp_path: Path) -> None:
    from magcomp.commands.fit import MAX_THROTTLE_GAP_S, fit_log, report_json

    bench = tmp_path / "bench.tlog"  # a throttle sweep at rest from t = 5 s to 35 s
    write_tlog(simulate(SimConfig(scenario="bench", duration_s=30.0, seed=4)), bench)
    whole = ms.load_log(bench)
    t0, t1 = 12.0, 25.0
    cut = ms.load_log(bench, window=Window.around(t0, t1, MAX_THROTTLE_GAP_S))
    assert len(cut.mag[0]) < 0.6 * len(whole.mag[0])
    inside = (whole.mag[0].t_s >= t0 - MAX_THROTTLE_GAP_S) & (whole.mag[0].t_s <= t1 + MAX_THROTTLE_GAP_S)
    assert len(cut.mag[0]) == int(inside.sum()) + 2  # one neighbour each side
    assert cut.params == whole.params and cut.counts == whole.counts
    a = report_json(fit_log(whole, start_s=t0, end_s=t1, n_monte_carlo=50, rng=np.random.default_rng(1)))
    b = report_json(fit_log(cut, start_s=t0, end_s=t1, n_monte_carlo=50, rng=np.random.default_rng(1)))
    assert a == b and a["n"] > 100
    # a window past the log's end: the same message as on the whole log
    late = ms.load_log(bench, window=Window.around(100.0, 200.0, MAX_THROTTLE_GAP_S))
    for data in (whole, late):
        with pytest.raises(
            MagcompError, match=r"only 0 magnetometer samples with throttle in 100.00-200.00 s"
        ):
            fit_log(data, start_s=100.0, end_s=200.0, n_monte_carlo=0)


def test_rows_keep_one_neighbour_outside_the_window_and_pwm_pads_late_channels() -> None:
    r = Rows(2, Window(2.0, 4.0))
    for t in (0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0):
        r.append(t, (t, -t))
    t_s, v = r.arrays()
    assert t_s.tolist() == [1.0, 2.0, 3.0, 4.0, 5.0] and r.n_seen == 7
    assert v[:, 1].tolist() == [-1.0, -2.0, -3.0, -4.0, -5.0]
    late = Rows(0, Window(10.0, 20.0))  # nothing inside: the last row before the window is kept
    for t in (0.0, 1.0, 2.0):
        late.append(t, (t,))
    assert len(late) == 1 and late.series().t_s.tolist() == [2.0]
    s = Rows(0)
    for t in (0.0, 2.0, 1.0, 1.0):
        s.append(t, (t * 10,))
    ser = s.series()  # sorted, equal times in arrival order
    assert ser.t_s.tolist() == [0.0, 1.0, 1.0, 2.0] and ser.values.tolist() == [0.0, 10.0, 10.0, 20.0]
    p = PwmRows()
    p.append(0.0, {1: 1100.0})
    p.append(1.0, {1: 1200.0, 3: 1523.0})
    p.append(2.0, {3: 1600.0})
    rows = list(p.rows((1, 2, 3)))
    assert rows == [(0.0, {1: 1100.0}), (1.0, {1: 1200.0, 3: 1523.0}), (2.0, {3: 1600.0})]
    assert Window.around(None, None, 1.0) is None
    w = Window.around(5.0, None, 1.0)
    assert w is not None and w.lo == 4.0 and math.isinf(w.hi)
