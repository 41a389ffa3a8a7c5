"""Who flew a log, with what firmware, when: a light scan of the log's boot messages (no replay).

- **PX4 ULog**: the header's info fields (``sys_uuid`` or ``mcu_id``, ``ver_hw``, ``ver_sw_release`` /
  ``ver_sw``, ``sys_name``) and the first GNSS UTC time (``vehicle_gps_position`` / ``sensor_gps``).
- **ArduPilot DataFlash** (.bin, .log): the boot text (``MSG``): the firmware line ("ArduCopter V4.5.7
  (abc123)") and the board's unique id line ("CubeOrange 00400029 3238510F 36363930"); ``VER``
  (board type, firmware string); the first GPS week + ms of week.
- **tlog / raw MAVLink**: ``AUTOPILOT_VERSION`` (uid, uid2, flight_sw_version), the same boot text in
  ``STATUSTEXT``, ``HEARTBEAT`` (autopilot, vehicle type, system id), ``SYSTEM_TIME`` (Unix time from GNSS),
  else the ground station's own recording clock (the tlog's frame timestamps).

Each compass slot's sensor (device id): the parameters that name it (``COMPASS_DEV_ID*`` /
``COMPASS_EXTERN*``; PX4 ``CAL_MAGn_ID`` / ``CAL_MAGn_ROT``; :mod:`magcomp.diagnosis.identity` reads
them) from the ULog's initial parameters, the DataFlash ``PARM`` records of the scanned part, a tlog's
``PARAM_VALUE``.

When the log names no board, the vehicle is a guess: the folder it lies in and the MAVLink system id
(``identity_source`` says so); a mapping file (:mod:`magcomp.fleet.mapping`) names vehicles for certain.
"""

from __future__ import annotations

import math
import mmap
import re
import struct
from collections import defaultdict
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

from magcomp.diagnosis.identity import sensor_identity

#: bytes of a DataFlash log read for its boot messages and first GPS time (the boot text comes first)
DATAFLASH_SCAN_BYTES = 16 << 20
#: lines of a text DataFlash log read for the same
TEXT_SCAN_LINES = 200_000

_BOARD_LINE = re.compile(
    r"^\s*([A-Za-z][\w\-.]*)\s+([0-9A-Fa-f]{8})\s+([0-9A-Fa-f]{8})\s+([0-9A-Fa-f]{8})\s*$"
)
_FIRMWARE_LINE = re.compile(r"(Ardu\w+|APM:\w+|Blimp|AntennaTracker)\s+V?(\d+\.\d+(?:\.\d+)?[\w\-.]*)")
_GPS_EPOCH = datetime(1980, 1, 6, tzinfo=UTC)
_MAV_AUTOPILOT = {3: "ArduPilot", 12: "PX4"}


@dataclass
class LogIdentity:
    """What the log says about its vehicle. Empty strings where it says nothing."""

    format: str  # tlog | dataflash | ulog
    autopilot: str = ""
    firmware: str = ""
    board: str = ""
    board_uid: str = ""
    system_id: int = -1
    date_utc: datetime | None = None
    date_source: str = ""  # gps | gps-system-time | tlog-clock | ulog-time-ref | ""
    #: the parameters naming each compass slot's sensor (:func:`sensor_param`)
    params: dict[str, float] = field(default_factory=dict)

    def compass_sensor(self, index: int) -> str | None:
        """The sensor in compass slot ``index`` (its device id as text); None: the log does not name it."""
        return sensor_identity(self.params, index).key

    def vehicle_id(self, path: Path) -> tuple[str, str]:
        """(vehicle id, how it was found)."""
        if self.board_uid:
            prefix = "px4" if self.autopilot == "PX4" else "ardupilot" if self.autopilot else "board"
            board = f"{self.board}-" if self.board else ""
            return f"{prefix}:{board}{self.board_uid}", "board unique id"
        sys_part = f"sys{self.system_id}" if self.system_id >= 0 else "sys?"
        return f"guess:{path.parent.name or '.'}/{sys_part}", "guess: folder and system id"


def scan_identity(path: Path) -> LogIdentity:
    """The identity of one log; never raises for a damaged log (what could not be read stays empty)."""
    fmt = log_format(path)
    try:
        if fmt == "ulog":
            return _scan_ulog(path)
        if fmt == "dataflash":
            if path.suffix.lower() == ".log" and not _looks_binary(path):
                return _scan_dataflash_text(path)
            return _scan_dataflash_binary(path)
        return _scan_tlog(path)
    except (OSError, ValueError, struct.error, IndexError, KeyError, UnicodeDecodeError, TypeError):
        return LogIdentity(format=fmt)


_SENSOR_PARAM = re.compile(r"^(COMPASS_DEV_ID\d?|COMPASS_EXTERN(AL|\d)|CAL_MAG\d_(ID|ROT))$")


def sensor_param(name: str) -> bool:
    """Is ``name`` one of the parameters that say which sensor sits in a compass slot?"""
    return _SENSOR_PARAM.match(name) is not None


def _param(ident: LogIdentity, name: str, value: Any) -> None:
    if sensor_param(name):
        try:
            v = float(value)
        except (TypeError, ValueError):
            return
        if math.isfinite(v):
            ident.params[name] = v


def log_format(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix == ".ulg":
        return "ulog"
    if suffix in (".bin", ".log"):
        return "dataflash"
    return "tlog"


def _looks_binary(path: Path) -> bool:
    with path.open("rb") as f:
        head = f.read(64)
    return head[:2] == b"\xa3\x95"


def _gps_datetime(week: float, ms: float) -> datetime | None:
    if not (math.isfinite(week) and math.isfinite(ms)) or week <= 0:
        return None
    try:
        when = _GPS_EPOCH + timedelta(weeks=float(week), milliseconds=float(ms))
    except OverflowError:
        return None
    return when if 2010 <= when.year <= 2100 else None


def _unix_datetime(unix_s: float) -> datetime | None:
    if not math.isfinite(unix_s) or unix_s < 1_262_304_000.0:  # before 2010: a clock never set
        return None
    try:
        when = datetime.fromtimestamp(unix_s, tz=UTC)
    except (OverflowError, OSError, ValueError):
        return None
    return when if when.year <= 2100 else None


def canonical_uid(words: list[str]) -> str:
    """The board's 96-bit id from its three 32-bit words as printed at boot. ArduPilot versions print the
    words in different byte orders (3.1: "2D001A00 17473235 ...", 3.2: "001A002D 35324717 ..." on the same
    board): the smaller of the two spellings is the id, so that both name one vehicle."""
    swapped = ["".join(reversed([w[i : i + 2] for i in range(0, 8, 2)])) for w in words]
    return min("".join(words), "".join(swapped))


def _text(ident: LogIdentity, text: str) -> None:
    """A boot message: the firmware line or the board's unique id line."""
    m = _BOARD_LINE.match(text)
    if m and not ident.board_uid:
        ident.board = m.group(1)
        ident.board_uid = canonical_uid([g.upper() for g in m.groups()[1:]])
        return
    f = _FIRMWARE_LINE.search(text)
    if f and not ident.firmware:
        ident.firmware = f"{f.group(1)} V{f.group(2)}"
        ident.autopilot = ident.autopilot or "ArduPilot"


# --- PX4 ULog -----------------------------------------------------------------------------------------


def _scan_ulog(path: Path) -> LogIdentity:
    from pyulog import ULog

    ident = LogIdentity(format="ulog", autopilot="PX4")
    ulog = ULog(str(path), ["vehicle_gps_position", "sensor_gps"], True, False)
    info: dict[str, Any] = ulog.msg_info_dict
    uid = str(info.get("sys_uuid") or info.get("mcu_id") or "").strip()
    ident.board_uid = uid.replace(" ", "")
    ident.board = str(info.get("ver_hw", "") or "")
    release = info.get("ver_sw_release")
    if isinstance(release, int) and release > 0:  # 0xAABBCCTT: major, minor, patch, type
        ident.firmware = f"PX4 v{release >> 24}.{(release >> 16) & 0xFF}.{(release >> 8) & 0xFF}"
    elif info.get("ver_sw"):
        ident.firmware = f"PX4 {str(info['ver_sw'])[:12]}"
    sys_name = str(info.get("sys_name", "") or "")
    if sys_name and sys_name != "PX4":
        ident.autopilot = sys_name
    for name, value in ulog.initial_parameters.items():
        _param(ident, str(name), value)
    for d in ulog.data_list:
        utc = d.data.get("time_utc_usec")
        if utc is None:
            continue
        for v in utc:
            when = _unix_datetime(float(v) * 1e-6)
            if when is not None:
                ident.date_utc, ident.date_source = when, "gps"
                return ident
    return ident


# --- ArduPilot DataFlash ------------------------------------------------------------------------------

_DF_STRUCT = {
    "a": "64s",
    "b": "b",
    "B": "B",
    "g": "e",
    "h": "h",
    "H": "H",
    "i": "i",
    "I": "I",
    "f": "f",
    "n": "4s",
    "N": "16s",
    "Z": "64s",
    "c": "h",
    "C": "H",
    "e": "i",
    "E": "I",
    "L": "i",
    "d": "d",
    "M": "B",
    "q": "q",
    "Q": "Q",
}
_DF_FMT_ID = 128
_DF_FMT_LEN = 89


def _cstr(raw: bytes) -> str:
    return raw.split(b"\0", 1)[0].decode("ascii", errors="replace")


def _scan_dataflash_binary(path: Path) -> LogIdentity:
    ident = LogIdentity(format="dataflash", autopilot="ArduPilot")
    with path.open("rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mm:
        n = min(len(mm), DATAFLASH_SCAN_BYTES)
        data = mm[:n]
    formats: dict[int, tuple[str, struct.Struct, list[str], int]] = {}
    wanted = {"MSG", "VER", "GPS", "PARM"}
    p = 0
    while p + 3 <= n:
        if data[p] != 0xA3 or data[p + 1] != 0x95:
            q = data.find(b"\xa3\x95", p + 1)
            if q < 0:
                break
            p = q
            continue
        mtype = data[p + 2]
        if mtype == _DF_FMT_ID:
            if p + _DF_FMT_LEN > n:
                break
            typ, length = data[p + 3], data[p + 4]
            name = _cstr(data[p + 5 : p + 9])
            fmt = _cstr(data[p + 9 : p + 25])
            cols = _cstr(data[p + 25 : p + 89]).split(",")
            try:
                st = struct.Struct("<" + "".join(_DF_STRUCT[c] for c in fmt))
            except KeyError:
                p += 1
                continue
            if st.size + 3 == length:
                formats[typ] = (name, st, cols, length)
            p += _DF_FMT_LEN
            continue
        entry = formats.get(mtype)
        if entry is None:
            p += 1
            continue
        name, st, cols, length = entry
        if p + length > n:
            break
        if name in wanted:
            values = dict(zip(cols, st.unpack_from(data, p + 3), strict=False))
            if _df_record(ident, name, values):
                break
        p += length
    return ident


def _df_record(ident: LogIdentity, name: str, values: dict[str, Any]) -> bool:
    """One MSG / VER / GPS / PARM record into ``ident``; True when nothing more is needed."""
    if name == "PARM":
        raw = values.get("Name", b"")
        _param(ident, _cstr(raw) if isinstance(raw, bytes) else str(raw), values.get("Value"))
    elif name == "MSG":
        raw = values.get("Message", b"")
        _text(ident, _cstr(raw) if isinstance(raw, bytes) else str(raw))
    elif name == "VER":
        fws = values.get("FWS", b"")
        fws_s = _cstr(fws) if isinstance(fws, bytes) else str(fws)
        if fws_s and not ident.firmware:
            _text(ident, fws_s)
        if not ident.board and "BU" in values:
            ident.board = f"board-type-{int(values['BU'])}"
    elif name == "GPS" and ident.date_utc is None:
        week = values.get("GWk", values.get("Week"))
        ms = values.get("GMS", values.get("TimeMS"))
        if week is not None and ms is not None:
            when = _gps_datetime(float(week), float(ms))
            if when is not None:
                ident.date_utc, ident.date_source = when, "gps"
    return ident.date_utc is not None and bool(ident.board_uid) and bool(ident.firmware)


def _scan_dataflash_text(path: Path) -> LogIdentity:
    ident = LogIdentity(format="dataflash", autopilot="ArduPilot")
    columns: dict[str, list[str]] = {}
    with path.open("r", encoding="ascii", errors="replace") as f:
        for i, line in enumerate(f):
            if i >= TEXT_SCAN_LINES:
                break
            parts = [s.strip() for s in line.split(",")]
            if not parts or not parts[0]:
                continue
            name = parts[0]
            if name == "FMT" and len(parts) >= 5:
                columns[parts[3]] = parts[5:]
                continue
            if i < 3 and len(parts) == 1:  # old logs start with the firmware line on its own
                _text(ident, line.strip())
                continue
            if name == "MSG":
                _text(
                    ident, ",".join(parts[2:]) if "TimeUS" in columns.get("MSG", []) else ",".join(parts[1:])
                )
            elif name in ("VER", "GPS", "PARM") and name in columns:
                values: dict[str, Any] = {}
                for col, raw in zip(columns[name], parts[1:], strict=False):
                    try:
                        values[col] = float(raw)
                    except ValueError:
                        values[col] = raw.encode()
                if _df_record(ident, name, values):
                    break
    return ident


# --- tlog / raw MAVLink -------------------------------------------------------------------------------


def _scan_tlog(path: Path) -> LogIdentity:
    from magcomp.adapters.mavlink_frames import crc_function as _crc_function
    from magcomp.adapters.mavlink_frames import frame_decoders, iter_mavlink_file
    from magcomp.adapters.mavlink_frames import mavlink_module as _mavlink_module
    from magcomp.adapters.mavlink_frames import sniff_mavlink_stream as _sniff_mavlink_stream

    ident = LogIdentity(format="tlog")
    mod = _mavlink_module()
    from magcomp.adapters.param_values import param_value

    names = ("HEARTBEAT", "AUTOPILOT_VERSION", "STATUSTEXT", "SYSTEM_TIME", "PARAM_VALUE")
    decoders = frame_decoders(mod, {name: (lambda m: None) for name in names})
    counts: dict[str, int] = defaultdict(int)
    system_ids: dict[int, int] = defaultdict(int)
    with path.open("rb") as f:
        head = f.read(64)
        ts_len = _sniff_mavlink_stream(head)
        if ts_len is None:
            return ident
        if ts_len == 8:
            when = _unix_datetime(int.from_bytes(head[:8], "big") * 1e-6)
            if when is not None:
                ident.date_utc, ident.date_source = when, "tlog-clock"
        for _handler, msg in iter_mavlink_file(f, head, decoders, counts, ts_len, crc16=_crc_function(mod)):
            kind = msg.get_type()
            if kind == "HEARTBEAT":
                if msg.type in (6, 18, 26, 27):  # GCS, onboard controllers, gimbals: not the vehicle
                    continue
                system_ids[msg.get_srcSystem()] += 1
                if not ident.autopilot and msg.autopilot in _MAV_AUTOPILOT:
                    ident.autopilot = _MAV_AUTOPILOT[msg.autopilot]
            elif kind == "AUTOPILOT_VERSION":
                _autopilot_version(ident, msg)
            elif kind == "STATUSTEXT":
                _text(ident, str(msg.text))
            elif kind == "PARAM_VALUE":
                pid = msg.param_id
                pid = pid.decode(errors="replace") if isinstance(pid, bytes) else str(pid)
                bytewise = ident.autopilot == "PX4"  # PX4 copies an integer's bytes (adapters.param_values)
                _param(
                    ident,
                    pid.rstrip("\0"),
                    param_value(float(msg.param_value), int(msg.param_type), bytewise),
                )
            elif kind == "SYSTEM_TIME" and ident.date_source != "gps-system-time":
                when = _unix_datetime(msg.time_unix_usec * 1e-6)
                if when is not None:
                    ident.date_utc, ident.date_source = when, "gps-system-time"
    if system_ids:
        ident.system_id = max(system_ids.items(), key=lambda kv: kv[1])[0]
    return ident


def _autopilot_version(ident: LogIdentity, msg: Any) -> None:
    uid2 = bytes(int(b) & 0xFF for b in getattr(msg, "uid2", []) or [])
    if any(uid2):
        ident.board_uid = uid2.rstrip(b"\0").hex().upper()
    elif int(msg.uid):
        ident.board_uid = f"{int(msg.uid):016X}"
    sw = int(msg.flight_sw_version)
    if sw and not ident.firmware:
        ident.firmware = f"V{sw >> 24}.{(sw >> 16) & 0xFF}.{(sw >> 8) & 0xFF}"
