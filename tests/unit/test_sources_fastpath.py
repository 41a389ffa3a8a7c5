"""The tlog fast path (own frame walk, X.25 CRC with crc_extra, a precompiled Struct per needed id) gives
exactly what pymavlink's own decode gives: the same samples, bit for bit, and the same counts of bad input."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from magcomp.adapters import dialect
from magcomp.adapters.mavlink_emit import write_tlog
from magcomp.adapters.mavlink_source import WANTED_MAVLINK, MavSource, open_source
from magcomp.core.types import ImuSample, MagSample, ParamSample, TemperatureSample, ThrottleSample
from magcomp.sim import SimConfig, simulate


def _kind(sample: Any) -> str:
    """The public sample type (magcomp.core.types) of a sample, also for the source's compact subclasses."""
    return next(c.__name__ for c in type(sample).__mro__ if c.__module__ == "magcomp.core.types")


def _key(sample: Any) -> tuple[Any, ...]:
    """A sample as a comparable tuple: arrays by dtype and values, floats by repr (NaN == NaN)."""
    out: list[Any] = [_kind(sample)]
    for name in sample.__dataclass_fields__:
        v = getattr(sample, name)
        if isinstance(v, np.ndarray):
            out.append((v.dtype.str, v.shape, tuple(repr(x) for x in v.tolist())))
        elif isinstance(v, float):
            out.append(repr(v))
        elif isinstance(v, tuple):
            out.append(tuple(repr(x) for x in v))
        else:
            out.append(v)
    return tuple(out)


class Frames:
    """Packs magcomp-dialect messages into tlog records (8-byte big-endian usec + packet)."""

    def __init__(self) -> None:
        self.mod = dialect.ensure_dialect()
        self.mav = self.mod.MAVLink(None, srcSystem=1, srcComponent=1)
        self.wall_us = 1_600_000_000_000_000

    def packet(self, name: str, **fields: Any) -> bytes:
        return bytes(getattr(self.mod, f"MAVLink_{name.lower()}_message")(**fields).pack(self.mav))

    def record(self, pkt: bytes) -> bytes:
        self.wall_us += 1000
        return self.wall_us.to_bytes(8, "big") + pkt

    def crc(self, buf: bytes) -> bytes:
        return int(self.mod.x25crc(buf).crc).to_bytes(2, "little")

    def as_v1(self, pkt: bytes) -> bytes:
        """The same message as a MAVLink 1 frame (full, untruncated payload)."""
        msgid = pkt[7] | (pkt[8] << 8) | (pkt[9] << 16)
        cls = self.mod.mavlink_map[msgid]
        payload = pkt[10:-2] + bytes(cls.unpacker.size - (len(pkt) - 12))
        head = bytes([0xFE, len(payload), pkt[4], pkt[5], pkt[6], msgid])
        return head + payload + self.crc(head[1:] + payload + bytes([cls.crc_extra]))

    def as_signed(self, pkt: bytes) -> bytes:
        """The same MAVLink 2 frame flagged as signed, with a 13-byte signature block (not checked)."""
        msgid = pkt[7] | (pkt[8] << 8) | (pkt[9] << 16)
        body = bytearray(pkt[:-2])
        body[2] |= 1
        crc = self.crc(bytes(body[1:]) + bytes([self.mod.mavlink_map[msgid].crc_extra]))
        return bytes(body) + crc + bytes(range(1, 14))


def imu_fields(t: int, key: str, scale: int = 1) -> dict[str, Any]:
    return {
        key: t,
        "xacc": 3 * scale,
        "yacc": -5,
        "zacc": -1000,
        "xgyro": 11,
        "ygyro": -7,
        "zgyro": 2,
        "xmag": 210 + scale,
        "ymag": -33,
        "zmag": 405,
        "temperature": 3150,
    }


def extra_head(f: Frames) -> list[bytes]:
    """Frames placed before the simulated stream: SCALED_IMU before any RAW_IMU (used), SCALED_PRESSURE, a
    PARAM_VALUE with a full 16-character name, and an id the source does not need (PING)."""
    pkts = [f.packet("SCALED_IMU", **imu_fields(10 * k, "time_boot_ms", k)) for k in range(5)]
    pkts.append(f.packet("SCALED_PRESSURE", time_boot_ms=40, press_abs=1013.2, press_diff=0.0,
                         temperature=2512, temperature_press_diff=0))  # fmt: skip
    pkts.append(f.packet("PARAM_VALUE", param_id=b"COMPASS_MOT_XYZA", param_value=1.5, param_type=9,
                         param_count=2, param_index=0))  # fmt: skip
    pkts.append(f.packet("PING", time_usec=41_000, seq=1, target_system=0, target_component=0))
    return pkts


def extra_tail(f: Frames, t0_ms: int) -> list[bytes]:
    """Frames after the stream: SCALED_IMU (now shadowed by RAW_IMU), a NaN attitude, a step back in
    SCALED_IMU2 time, BATTERY_STATUS with cell arrays and an extension array."""
    nan = float("nan")
    return [
        f.packet("SCALED_IMU", **imu_fields(t0_ms, "time_boot_ms")),
        f.packet(
            "ATTITUDE",
            time_boot_ms=t0_ms,
            roll=nan,
            pitch=0.0,
            yaw=0.0,
            rollspeed=0.0,
            pitchspeed=0.0,
            yawspeed=0.0,
        ),
        f.packet("SCALED_IMU2", **imu_fields(t0_ms, "time_boot_ms")),
        f.packet("SCALED_IMU2", **imu_fields(t0_ms + 20, "time_boot_ms")),  # confirms the clock's jump
        f.packet("SCALED_IMU2", **imu_fields(t0_ms - 100, "time_boot_ms")),  # 0.12 s back: dropped
        f.packet(
            "BATTERY_STATUS",
            id=1,
            battery_function=0,
            type=1,
            temperature=2500,
            voltages=[4100, 4090, 4080, 0xFFFF, 0xFFFF, 0xFFFF, 0xFFFF, 0xFFFF, 0xFFFF, 0xFFFF],
            current_battery=1234,
            current_consumed=10,
            energy_consumed=20,
            battery_remaining=80,
            time_remaining=0,
            charge_state=1,
            voltages_ext=[4070, 0, 0, 0],
            mode=0,
            fault_bitmask=0,
        ),
    ]


@pytest.fixture(scope="module")
def stream(tmp_path_factory: pytest.TempPathFactory) -> tuple[Frames, list[bytes]]:
    """Records of a 20 s simulated paper flight with three compasses, plus the extra message types."""
    tmp = tmp_path_factory.mktemp("fast")
    sim_path = tmp / "sim.tlog"
    write_tlog(simulate(SimConfig(scenario="paper", duration_s=20, seed=3, n_compasses=3)), sim_path)
    data = sim_path.read_bytes()
    f = Frames()
    records = [f.record(p) for p in extra_head(f)]
    p = 0
    while p < len(data):  # split the simulated tlog into its records (all MAVLink 2, unsigned)
        end = p + 8 + 12 + data[p + 9] + (13 if data[p + 10] & 1 else 0)
        records.append(data[p:end])
        p = end
    records += [f.record(p) for p in extra_tail(f, 25_000)]
    return f, records


def fast_samples(path: Path) -> tuple[list[Any], dict[str, int]]:
    with open_source(path) as src:
        samples = list(src.samples())
        return samples, dict(src.counts)


def reference_samples(path: Path) -> tuple[list[Any], dict[str, int]]:
    """The same walk, decoding each needed frame with pymavlink's ``MAVLink.decode`` (the former path)."""
    with open_source(path) as src:
        assert isinstance(src, MavSource)
        src._reference_decode = True
        samples = list(src.samples())
        return samples, dict(src.counts)


def mavutil_samples(path: Path) -> tuple[list[Any], dict[str, int]]:
    """pymavlink end to end: ``mavlink_connection`` + ``recv_msg`` decode, then the source's conversion."""
    from pymavlink import mavutil

    src = open_source(path)
    assert isinstance(src, MavSource)
    conn = mavutil.mavlink_connection(str(path), dialect="magcomp")
    wanted = set(WANTED_MAVLINK)

    def messages() -> Iterator[tuple[Any, Any]]:
        while (m := conn.recv_msg()) is not None:
            if m.get_type() in wanted:
                src.counts["messages"] += 1
                yield src._conv.mavlink, m

    src._messages = messages  # type: ignore[method-assign]
    try:
        return list(src.samples()), dict(src.counts)
    finally:
        conn.close()
        src.close()


def test_fast_path_equals_pymavlink_decode_on_simulated_tlog_with_every_message_type(
    stream: tuple[Frames, list[bytes]], tmp_path: Path
) -> None:
    _, records = stream
    path = tmp_path / "all.tlog"
    path.write_bytes(b"".join(records))
    fast, fast_counts = fast_samples(path)
    ref, ref_counts = mavutil_samples(path)
    assert [_key(s) for s in fast] == [_key(s) for s in ref]
    assert fast_counts == ref_counts
    # every kind of sample is exercised, including the hand-added message types
    kinds = {_kind(s) for s in fast}
    assert {"ImuSample", "MagSample", "AttitudeSample", "PowerSample", "TemperatureSample", "ThrottleSample",
            "HeartbeatSample", "ParamSample"} <= kinds  # fmt: skip
    assert {s.mag_index for s in fast if isinstance(s, MagSample)} == {0, 1, 2}
    assert {s.sensor for s in fast if isinstance(s, TemperatureSample)} >= {"imu0", "imu1", "baro"}
    assert any(isinstance(s, ParamSample) and s.name == "COMPASS_MOT_XYZA" for s in fast)
    assert any(isinstance(s, ThrottleSample) for s in fast)
    early = [s for s in fast if isinstance(s, ImuSample) and s.t_s < 0.045 and s.imu_index == 0]
    assert len(early) == 5  # SCALED_IMU used before RAW_IMU appears
    assert fast_counts["scaled_imu_shadowed"] == 1
    assert fast_counts["nonfinite"] == 1
    print("COUNTS", fast_counts)
    assert fast_counts["time_backwards"] == 1
    battery1 = [s for s in fast if _kind(s) == "PowerSample" and s.battery_index == 1]
    assert len(battery1) == 1
    assert math.isclose(battery1[0].voltage_v, (4100 + 4090 + 4080 + 4070) * 1e-3)
    assert math.isclose(battery1[0].current_a, 12.34)


def test_fast_path_decodes_mavlink1_and_signed_frames_like_pymavlink(
    stream: tuple[Frames, list[bytes]], tmp_path: Path
) -> None:
    f, records = stream
    mixed = []
    for i, rec in enumerate(records):
        pkt = rec[8:]
        if i % 7 == 3:
            pkt = f.as_v1(pkt)
        elif i % 7 == 5:
            pkt = f.as_signed(pkt)
        mixed.append(rec[:8] + pkt)
    path = tmp_path / "mixed.tlog"
    path.write_bytes(b"".join(mixed))
    fast, fast_counts = fast_samples(path)
    ref, ref_counts = reference_samples(path)
    assert [_key(s) for s in fast] == [_key(s) for s in ref]
    assert fast_counts == ref_counts
    assert fast_counts["messages"] == len(records) - 1  # all but PING
    plain, _ = fast_samples(_write(tmp_path / "plain.tlog", records))
    assert [_key(s) for s in fast] == [_key(s) for s in plain]  # v1 / signed framing changes nothing


def _write(path: Path, records: list[bytes]) -> Path:
    path.write_bytes(b"".join(records))
    return path


def test_corrupted_bytes_give_the_same_counts_and_samples_as_pymavlink_decode(
    stream: tuple[Frames, list[bytes]], tmp_path: Path
) -> None:
    _, records = stream
    rng = np.random.default_rng(17)
    corrupt = list(records)
    n = len(corrupt)
    flipped = rng.choice(np.arange(20, n - 20), size=9, replace=False)
    n_bad = 0
    for i in flipped:  # one payload byte of a needed message: a CRC failure with intact framing
        rec = bytearray(corrupt[i])
        if rec[8 + 7] == 4 or rec[9] == 0:  # PING is not checked; keep a payload byte to flip
            continue
        rec[8 + 10] ^= 0x5A
        corrupt[i] = bytes(rec)
        n_bad += 1
    garbage_at = rng.choice(np.arange(20, n - 20), size=4, replace=False)
    for j, i in enumerate(sorted(garbage_at)):  # runs of junk between records, some holding magic bytes
        junk = bytes(rng.integers(0, 256, size=5 + 3 * j, dtype=np.uint8))
        corrupt[i] = junk + corrupt[i]
    skip_at = int(rng.integers(30, n - 30))  # a record cut short in the middle of the file
    corrupt[skip_at] = corrupt[skip_at][: len(corrupt[skip_at]) // 2]
    data = b"".join(corrupt)
    path = tmp_path / "bad.tlog"
    path.write_bytes(data + records[100][:30])  # truncated tail: header present, frame incomplete
    fast, fast_counts = fast_samples(path)
    ref, ref_counts = reference_samples(path)
    assert fast_counts == ref_counts
    assert [_key(s) for s in fast] == [_key(s) for s in ref]
    assert n_bad >= 6
    assert fast_counts["bad_crc"] >= n_bad
    assert fast_counts["garbage_bytes"] >= 5
    assert fast_counts["truncated"] == 1
    assert fast_counts["messages"] >= len(records) - 1 - n_bad - 8


def test_corrupted_crc_alone_is_counted_once_per_frame_and_nothing_else_changes(
    stream: tuple[Frames, list[bytes]], tmp_path: Path
) -> None:
    _, records = stream
    clean, clean_counts = fast_samples(_write(tmp_path / "clean.tlog", records))
    corrupt = list(records)
    hit = [i for i in range(40, len(records), 97) if records[i][8 + 7] == 30][:4]  # ATTITUDE frames
    for i in hit:
        rec = bytearray(corrupt[i])
        rec[-1] ^= 0xFF  # the CRC's high byte
        corrupt[i] = bytes(rec)
    bad, bad_counts = fast_samples(_write(tmp_path / "crc.tlog", corrupt))
    assert len(hit) >= 2
    assert bad_counts["bad_crc"] == len(hit)
    assert bad_counts["messages"] == clean_counts["messages"] - len(hit)
    assert bad_counts.get("garbage_bytes", 0) == clean_counts.get("garbage_bytes", 0) == 0
    assert len(bad) == len(clean) - len(hit)  # one AttitudeSample per ATTITUDE frame


def _ignored_by_pipeline(sample: Any) -> bool:
    kind = _kind(sample)
    return kind in ("TemperatureSample", "PowerSample") or (kind == "ImuSample" and sample.imu_index != 0)


def test_pipeline_only_source_leaves_out_exactly_what_the_pipeline_ignores(
    stream: tuple[Frames, list[bytes]], tmp_path: Path
) -> None:
    """``pipeline_only`` drops temperature, power and secondary-IMU samples (counted), nothing else: the other
    samples, their order and the source's counts are those of the full source."""
    _, records = stream
    path = tmp_path / "all.tlog"
    path.write_bytes(b"".join(records))
    with open_source(path) as full_src:
        full = list(full_src.samples())
        full_counts = dict(full_src.counts)
        assert full_src.skipped_samples == 0
    with open_source(path, pipeline_only=True) as lean_src:
        lean = list(lean_src.samples())
        lean_counts = dict(lean_src.counts)
        skipped = lean_src.skipped_samples
    kept = [s for s in full if not _ignored_by_pipeline(s)]
    assert [_key(s) for s in lean] == [_key(s) for s in kept]
    assert skipped == len(full) - len(kept) > 0
    left_out = {_kind(s) for s in full if _ignored_by_pipeline(s)}
    assert left_out == {"TemperatureSample", "PowerSample", "ImuSample"}
    assert lean_counts == full_counts


def test_pipeline_only_source_reads_rc_inputs_only_for_an_rc_throttle(
    stream: tuple[Frames, list[bytes]], tmp_path: Path
) -> None:
    """A ``pipeline_only`` source skips the RC inputs' PWM unless the throttle is read from them: with
    ``rc:3`` its throttle samples are the full source's (and come from the RC inputs), with ``auto`` they
    are the full source's too (auto never picks the RC inputs)."""
    _, records = stream
    path = tmp_path / "all.tlog"
    path.write_bytes(b"".join(records))
    for spec in ("rc:3", "auto"):
        got = []
        for lean in (False, True):
            with open_source(path, throttle_source=spec, pipeline_only=lean) as src:
                got.append([_key(s) for s in src.samples() if isinstance(s, ThrottleSample)])
        assert got[0] == got[1]
        assert len(got[0]) > 100
        from_rc = {k[3].startswith("rc") for k in got[0]}  # k[3]: the sample's source field
        assert from_rc == ({True} if spec == "rc:3" else {False})


def test_attitude_rates_read_as_arrays_and_pickled_as_a_plain_sample(
    stream: tuple[Frames, list[bytes]], tmp_path: Path
) -> None:
    """ATTITUDE's body rates stay floats until read; read, they are the message's (float64 array), and a
    pickled sample is a plain AttitudeSample with the same fields."""
    import pickle

    from magcomp.adapters.wire_samples import WireAttitudeSample
    from magcomp.core.types import AttitudeSample

    _, records = stream
    path = tmp_path / "all.tlog"
    path.write_bytes(b"".join(records))
    with open_source(path) as src:
        atts = [s for s in src.samples() if isinstance(s, WireAttitudeSample)]
    assert len(atts) > 100
    s = atts[len(atts) // 2]
    rates = s.rates_b_rad_s
    assert rates.dtype == np.float64 and rates.shape == (3,)
    assert rates.tolist() == list(s.rates_xyz) and s.rates_b_rad_s is rates  # built once
    assert np.abs(np.array([a.rates_xyz for a in atts])).max() > 0.01  # the simulated flight turns
    back = pickle.loads(pickle.dumps(s))
    assert type(back) is AttitudeSample and _key(back) == _key(s)


def test_replay_counts_every_sample_of_the_log_with_the_pipeline_only_source(tmp_path: Path) -> None:
    """The replay reads its log ``pipeline_only``; its summary still counts every sample the log holds."""
    from magcomp.adapters.config import Config
    from magcomp.service.replay import replay_log

    path = tmp_path / "short.tlog"
    write_tlog(simulate(SimConfig(scenario="paper", duration_s=20.0, seed=2)), path)
    with open_source(path) as src:
        n_all = sum(1 for _ in src.samples())
    for two_pass in (False, True):
        report = replay_log(path, Config(), two_pass=two_pass)
        assert report.summary["counts"]["samples"] == n_all
