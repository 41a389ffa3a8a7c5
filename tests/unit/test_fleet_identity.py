"""Who flew a log (magcomp/fleet/identity.py): board unique ids, firmware and GPS dates of each format."""

from __future__ import annotations

import struct
from datetime import UTC, datetime
from pathlib import Path

import pytest

from magcomp.fleet.identity import canonical_uid, scan_identity

SHARED = Path(__file__).parents[2].parent / "shared" / "data" / "measured"


def _tlog(path: Path, frames: list[bytes], start_us: int = 1_700_000_000_000_000) -> None:
    path.write_bytes(b"".join((start_us + i).to_bytes(8, "big") + f for i, f in enumerate(frames)))


def test_tlog_autopilot_version_and_boot_text(tmp_path: Path) -> None:
    from magcomp.adapters.dialect import ensure_dialect

    mod = ensure_dialect()
    mav = mod.MAVLink(None, srcSystem=7, srcComponent=1)
    frames = [
        bytes(mav.heartbeat_encode(2, 3, 0, 0, 0, 3).pack(mav)),  # quadrotor, ArduPilot
        bytes(mav.statustext_encode(6, b"ArduCopter V4.5.7 (2a3dc4b7)").pack(mav)),
        bytes(mav.statustext_encode(6, b"CubeOrange 00400029 3238510F 36363930").pack(mav)),
        bytes(mav.system_time_encode(1_750_000_000_000_000, 1000).pack(mav)),
    ]
    p = tmp_path / "a.tlog"
    _tlog(p, frames)
    ident = scan_identity(p)
    assert ident.autopilot == "ArduPilot"
    assert ident.firmware == "ArduCopter V4.5.7"
    assert (ident.board, ident.board_uid) == ("CubeOrange", "004000293238510F36363930")
    assert ident.system_id == 7
    assert ident.date_source == "gps-system-time"
    assert ident.date_utc == datetime.fromtimestamp(1_750_000_000, tz=UTC)
    assert ident.vehicle_id(p) == ("ardupilot:CubeOrange-004000293238510F36363930", "board unique id")


def test_tlog_without_a_board_falls_back_to_a_labelled_guess(tmp_path: Path) -> None:
    from magcomp.adapters.dialect import ensure_dialect

    mod = ensure_dialect()
    mav = mod.MAVLink(None, srcSystem=3, srcComponent=1)
    uid2 = list(range(1, 13)) + [0] * 6
    frames = [
        bytes(mav.heartbeat_encode(2, 12, 0, 0, 0, 3).pack(mav)),  # PX4
        bytes(
            mav.autopilot_version_encode(
                0, (1 << 24) | (14 << 16) | (3 << 8), 0, 0, 0, b"\0" * 8, b"\0" * 8, b"\0" * 8, 0, 0, 0, uid2
            ).pack(mav)
        ),
    ]
    p = tmp_path / "vehicle9" / "b.tlog"
    p.parent.mkdir()
    _tlog(p, frames)
    ident = scan_identity(p)
    assert ident.autopilot == "PX4" and ident.firmware == "V1.14.3"
    assert ident.board_uid == bytes(range(1, 13)).hex().upper()
    assert ident.date_source == "tlog-clock"
    frames2 = [bytes(mav.heartbeat_encode(2, 3, 0, 0, 0, 3).pack(mav))]
    q = tmp_path / "vehicle9" / "c.tlog"
    _tlog(q, frames2)
    vid, how = scan_identity(q).vehicle_id(q)
    assert (vid, how) == ("guess:vehicle9/sys3", "guess: folder and system id")


def test_ulog_sys_uuid_firmware_and_gps_time(tmp_path: Path) -> None:
    from magcomp.adapters.ulog_writer import UlogWriter

    w = UlogWriter()
    w.info("sys_name", "PX4")
    w.info("ver_hw", "PX4_FMU_V6C")
    w.info("sys_uuid", "000600000000363633385111000b0034")
    w.topic("sensor_gps", [("uint64_t", "timestamp"), ("uint64_t", "time_utc_usec")])
    w.data("sensor_gps", 0, [1_000_000, 0])  # no fix yet
    w.data("sensor_gps", 0, [2_000_000, 1_687_336_568_000_000])
    p = tmp_path / "f.ulg"
    w.write(p)
    ident = scan_identity(p)
    assert ident.vehicle_id(p) == ("px4:PX4_FMU_V6C-000600000000363633385111000b0034", "board unique id")
    assert ident.date_utc == datetime.fromtimestamp(1_687_336_568, tz=UTC)
    assert ident.date_source == "gps"


_DF_SIZES = {"B": 1, "H": 2, "I": 4, "Q": 8, "f": 4, "n": 4, "N": 16, "Z": 64}


def _df_fmt(typ: int, name: str, fmt: str, cols: str) -> bytes:
    size = sum(_DF_SIZES[c] for c in fmt)
    return b"\xa3\x95\x80" + struct.pack(
        "<BB4s16s64s", typ, size + 3, name.encode(), fmt.encode(), cols.encode()
    )


def test_dataflash_binary_boot_messages_and_gps_week(tmp_path: Path) -> None:
    data = _df_fmt(128, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns")
    data += _df_fmt(91, "MSG", "QZ", "TimeUS,Message")
    data += _df_fmt(92, "GPS", "QBIH", "TimeUS,Status,GMS,GWk")
    data += b"\xa3\x95\x5b" + struct.pack("<Q64s", 1, b"ArduPlane V4.5.1 (abcdef)")
    data += b"\xa3\x95\x5b" + struct.pack("<Q64s", 2, b"MatekH743 00310041 3431510E 30383738")
    data += b"\xa3\x95\x5c" + struct.pack("<QBIH", 3, 1, 0, 0)  # no fix yet: week 0
    data += b"\xa3\x95\x5c" + struct.pack("<QBIH", 4, 3, 345_600_000, 2300)
    p = tmp_path / "00000042.BIN"
    p.write_bytes(data)
    ident = scan_identity(p)
    assert ident.firmware == "ArduPlane V4.5.1"
    assert ident.vehicle_id(p)[0] == "ardupilot:MatekH743-003100413431510E30383738"
    assert ident.date_utc == datetime(2024, 2, 8, tzinfo=UTC)  # GPS week 2300 + 4 days (no leap seconds)


def test_garbage_gives_an_empty_identity_not_an_error(tmp_path: Path) -> None:
    p = tmp_path / "x.bin"
    p.write_bytes(b"\xa3\x95\x80" + b"\xff" * 500)
    ident = scan_identity(p)
    assert ident.board_uid == "" and ident.date_utc is None


@pytest.mark.needs_shared
def test_measured_dataflash_logs_name_their_board() -> None:
    log171 = SHARED / "dronekit_log171_copter33_quad.bin"
    text = SHARED / "ardupilot_loganalyzer_nan_copter311.log"
    if not log171.exists():
        pytest.skip("../shared/data/measured is absent")
    a = scan_identity(log171)
    assert (a.board, a.firmware) == ("PX4v2", "APM:Copter V3.3-dev")
    assert a.board_uid == "004A002F3334511932383433" and a.date_utc is not None and a.date_utc.year == 2015
    b = scan_identity(text)
    # printed "26002600 0A473234 33353231"
    assert b.firmware == "ArduCopter V3.1" and b.board_uid == "002600263432470A31323533"
    assert b.date_utc is not None and b.date_utc.year == 2014


def test_a_board_id_printed_in_either_byte_order_is_one_id() -> None:
    # ArduCopter 3.1.5 and 3.2 on one board (squilter/gridlines' kresge logs)
    a = canonical_uid(["2D001A00", "17473235", "32303436"])
    b = canonical_uid(["001A002D", "35324717", "36343032"])
    assert a == b == "001A002D3532471736343032"
    assert canonical_uid(["001A002D", "35324717", "36343033"]) != a


def test_each_format_names_its_compass_sensors(tmp_path: Path) -> None:
    """The slot's sensor from the log's parameters: a tlog's PARAM_VALUE (ArduPilot casts, PX4 copies an
    integer's bytes), a DataFlash PARM record, a ULog's initial parameters; a slot without one: None."""
    from magcomp.adapters.dialect import ensure_dialect
    from magcomp.adapters.ulog_writer import UlogWriter

    mod = ensure_dialect()
    mav = mod.MAVLink(None, srcSystem=1, srcComponent=1)
    frames = [
        bytes(mav.heartbeat_encode(2, 3, 0, 0, 0, 3).pack(mav)),
        bytes(mav.param_value_encode(b"COMPASS_DEV_ID", 466441.0, 6, 3, 0).pack(mav)),
        bytes(mav.param_value_encode(b"COMPASS_DEV_ID2", 131594.0, 6, 3, 1).pack(mav)),
        bytes(mav.param_value_encode(b"COMPASS_MOTCT", 1.0, 2, 3, 2).pack(mav)),  # not an identity
    ]
    p = tmp_path / "a.tlog"
    _tlog(p, frames)
    a = scan_identity(p)
    assert [a.compass_sensor(i) for i in range(3)] == ["466441", "131594", None]
    assert "COMPASS_MOTCT" not in a.params
    px4_id = struct.unpack("<f", struct.pack("<i", 396321))[0]  # PX4: the int32's bytes in the float
    frames = [
        bytes(mav.heartbeat_encode(2, 12, 0, 0, 0, 3).pack(mav)),
        bytes(mav.param_value_encode(b"CAL_MAG0_ID", px4_id, 6, 1, 0).pack(mav)),
    ]
    q = tmp_path / "b.tlog"
    _tlog(q, frames)
    assert scan_identity(q).compass_sensor(0) == "396321"

    data = _df_fmt(128, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns")
    data += _df_fmt(64, "PARM", "QNf", "TimeUS,Name,Value")
    data += b"\xa3\x95\x40" + struct.pack("<Q16sf", 1, b"COMPASS_DEV_ID", 131594.0)
    d = tmp_path / "00000003.BIN"
    d.write_bytes(data)
    assert scan_identity(d).compass_sensor(0) == "131594"

    w = UlogWriter()
    w.info("sys_name", "PX4")
    w.param("CAL_MAG1_ID", 396817, is_int=True)
    w.param("CAL_MAG1_ROT", 10, is_int=True)
    u = tmp_path / "c.ulg"
    w.write(u)
    b = scan_identity(u)
    assert (b.compass_sensor(0), b.compass_sensor(1)) == (None, "396817")
