"""Log and link sources turned into the typed samples of :mod:`magcomp.core.types`.

Inputs: MAVLink ``.tlog`` and raw MAVLink streams, ArduPilot DataFlash ``.bin`` / text ``.log``, PX4 ``.ulg``
(:mod:`magcomp.adapters.ulog_source`) and live ``udp``/``tcp``/``serial`` links.

Units at this boundary (everything downstream uses them):
- RAW_IMU / SCALED_IMU*: accel mG -> m/s^2 (x 9.80665e-3), gyro mrad/s -> rad/s, mag mgauss (ArduPilot
  units); temperature cdegC -> degC (0 means "not provided"). RAW_IMU and SCALED_IMU both carry compass 0
  in ArduPilot: once RAW_IMU has been seen, SCALED_IMU is ignored (``counts["scaled_imu_shadowed"]``).
  SCALED_IMU2/3 are compasses (and IMUs) 1 and 2. A (0, 0, 0) field is "no data" (``mag_zero``).
- PX4 (HEARTBEAT autopilot 12): HIGHRES_IMU accel m/s^2, gyro rad/s, mag gauss -> mgauss, each only when its
  ``fields_updated`` bits are set; its IMU 0 replaces SCALED_IMU's, and a compass in SCALED_IMU shadows
  HIGHRES_IMU's (``highres_mag_shadowed``). ATTITUDE_QUATERNION (w, x, y, z) while no ATTITUDE is seen;
  ACTUATOR_OUTPUT_STATUS (PWM us of the ``active`` outputs) while no SERVO_OUTPUT_RAW is seen; throttle
  channels and ranges from PWM_MAIN_FUNCn / PWM_MAIN_MINn (see :mod:`magcomp.adapters.throttle`).
- Position: GPS_RAW_INT (fix_type >= 3 is ``fix_ok``) and GLOBAL_POSITION_INT (lat/lon degE7, alt mm MSL),
  DataFlash GPS/GPS2 (Status >= 3, GPS week + ms -> UTC) and POS become PositionSample; SYSTEM_TIME
  (time_unix_usec, unset clocks ignored) a TimeSample. Stamped with the latest source time.
- SYS_STATUS: voltage_battery mV, current_battery cA (-1 / UINT16_MAX = unknown -> NaN), battery 0.
  BATTERY_STATUS (cell voltages mV summed, current cA) is used for battery 0 only while SYS_STATUS has not
  reported a current.
- DataFlash: MAG/MAG2/MAG3 (or MAG with instance field I) in mgauss, IMU GyrX.. rad/s and AccX.. m/s^2,
  ATT deg, RCOU C1.. / Ch1.. / Chan1.. us, CTUN ThO (0..1) or ThrOut (0..1000) (Plane's CTUN, the one with
  NavRoll: ThO / ThrOut in percent), CURR/BAT Volt and Curr
  (integer columns of old logs are cV / cA), PARM. When MAG records the motor compensation the autopilot
  applied (MOfsX.. / MOX..), it is subtracted by default (``undo_motor_comp``) so that the field is the one
  the motors actually disturbed; not when the logged parameters say the autopilot applies none
  (COMPASS_MOTCT = 0 and no per-motor compensation): a non-zero offset is then a corrupt record
  (``motor_comp_ignored``). MAVLink compass fields carry no such record: with COMPASS_MOTCT = 1 / 2 the
  compensation is rebuilt from COMPASS_MOT*/MOT2*/MOT3* and VFR_HUD.throttle / SYS_STATUS current and
  subtracted from when they are known (:mod:`magcomp.adapters.ardupilot_motcomp`).
- Time: the message's own timestamp (time_boot_ms, time_usec, DataFlash TimeUS / TimeMS) in s. Messages
  without one (VFR_HUD, SYS_STATUS, BATTERY_STATUS, HEARTBEAT, PARAM_VALUE) get the latest time seen. A
  jump back of more than ``RESET_JUMP_S`` is a reboot of the autopilot: an offset keeps ``t_s`` monotonic,
  ``counts["clock_resets"]`` counts them and ``samples()`` yields a ClockResetSample (the pipeline ends its
  calibration window and filters there). A jump either way is believed only once the next timestamp
  confirms it; a lone corrupt timestamp is dropped (``counts["time_jumps"]``). Smaller steps back within
  one message stream are dropped (``counts["time_backwards"]``). Streams stamped ``time_usec`` on a clock
  of their own (ArduCopter 3.1/3.2's RAW_IMU and SERVO_OUTPUT_RAW, 2.57-2.87 s behind ``time_boot_ms``)
  are moved onto the ``time_boot_ms`` clock by an offset measured from messages sent together, by the
  tlog's receive stamps or a link's arrival times (:class:`StreamOffsets`; ``counts["clock_aligned"]``,
  said once per stream).
- Bad input is skipped and counted, never fatal: ``bad_crc``, ``garbage_bytes``, ``truncated``,
  ``nonfinite``. A file with no usable message at all is an :class:`~magcomp.errors.InputError`.

The pieces, by job: framing and decoding of tlogs and raw streams (:mod:`magcomp.adapters.mavlink_frames`),
DataFlash repair and reading (:mod:`magcomp.adapters.dataflash_read`), messages into records
(:mod:`magcomp.adapters.message_convert`), stream clocks (:mod:`magcomp.adapters.stream_clock`), parameter
values (:mod:`magcomp.adapters.param_values`), live links (:mod:`magcomp.adapters.links`) and whole-log
columns (:mod:`magcomp.adapters.log_collect`). This module holds the source itself: :class:`MavSource`,
:func:`open_source`, :func:`load_log` and the one loop from records to samples (:class:`SenderStream`).
On a 600 s simulated tlog the whole source (decode + conversion + throttle) takes ~0.3x the wall time of
``mavlink_connection`` + ``recv_msg`` merely parsing it (benchmarks/source_speed.py).

:func:`load_log` keeps what it needs of each record in compact columns (:mod:`magcomp.adapters.columns`),
not as sample objects: ~8 bytes per value instead of ~150-350 bytes per row.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypedDict, Unpack

from magcomp.adapters import mavlink_frames
from magcomp.adapters.columns import Window
from magcomp.adapters.dataflash_read import (
    DAMAGE_MARGIN_BYTES,
    WANTED_DATAFLASH,
    dataflash_intact_spans,
    dataflash_repaired,
    iter_dataflash,
)
from magcomp.adapters.links import UdpPeerLock, is_live, is_ulog, raise_dropped
from magcomp.adapters.log_collect import collect_log, reporting
from magcomp.adapters.mavlink_frames import (
    READ_CHUNK_BYTES,
    crc_function,
    frame_decoders,
    iter_mavlink_file,
    mavlink_module,
    sniff_mavlink_stream,
)
from magcomp.adapters.message_convert import (
    WANTED_MAVLINK,
    Counts,
    MessageConverter,
    PwmRecord,
    Record,
    ThrottleRecord,
)
from magcomp.adapters.param_values import finite_params, param_value
from magcomp.adapters.quiet import quiet, quiet_c_streams
from magcomp.adapters.stream_clock import OFFSET_MIN_S, StreamOffsets
from magcomp.adapters.throttle import (
    ResolvedThrottle,
    ThrottleSpec,
    parse_throttle_source,
    resolve_throttle,
    throttle_from_pwm,
)
from magcomp.adapters.wire_samples import WireImuSample, WireMagSample
from magcomp.core.types import (
    ClockResetSample,
    HeartbeatSample,
    LogData,
    ParamSample,
    Sample,
    ThrottleSample,
)
from magcomp.errors import InputError

if TYPE_CHECKING:
    from magcomp.adapters.ulog_source import UlogSource

log = logging.getLogger("magcomp.source")

#: the names other modules import from here (the pieces moved out by job; the old private spellings kept
#: for modules that still import them)
__all__ = [
    "DAMAGE_MARGIN_BYTES",
    "OFFSET_MIN_S",
    "READ_CHUNK_BYTES",
    "WANTED_DATAFLASH",
    "WANTED_MAVLINK",
    "Counts",
    "MavSource",
    "SenderStream",
    "SourceOptions",
    "StreamOffsets",
    "WireImuSample",
    "WireMagSample",
    "dataflash_intact_spans",
    "dataflash_repaired",
    "finite_params",
    "frame_decoders",
    "iter_mavlink_file",
    "load_log",
    "open_source",
    "param_value",
    "quiet",
    "quiet_c_streams",
    "sender_stream",
]
_Counts = Counts
_dataflash_repaired = dataflash_repaired
_quiet = quiet
_quiet_c_streams = quiet_c_streams
_crc_function = crc_function
_mavlink_module = mavlink_module
_sniff_mavlink_stream = sniff_mavlink_stream


class MavSource(contextlib.AbstractContextManager["MavSource"]):
    """One source of typed samples. Use :func:`open_source`.

    ``samples()`` streams :data:`~magcomp.core.types.Sample` objects in arrival order (throttle already
    converted
    with the configured source); ``counts`` holds what was skipped and why, plus ``messages`` and
    ``clock_resets``. ``connection`` is the mavutil connection of a live link (None for files), e.g. to send
    MAGCOMP_HEADING back on it.
    """

    def __init__(
        self,
        target: str,
        *,
        throttle_source: str | ThrottleSpec = "auto",
        mag_index: int | None = None,
        undo_motor_comp: bool = True,
        baud: int = 57600,
        live_timeout_s: float = 0.5,
        pipeline_only: bool = False,
        signing_key: bytes | None = None,
    ) -> None:
        self.target = target
        self._signing_key = signing_key
        self.spec = parse_throttle_source(throttle_source)
        self.mag_index = mag_index
        self.counts: dict[str, int] = Counts()
        self.params: dict[str, float] = {}
        self.connection: Any = None
        self._conv = MessageConverter(
            self.counts, mag_index=mag_index, undo_motor_comp=undo_motor_comp, pipeline_only=pipeline_only,
            rc_pwm=not pipeline_only or self.spec.kind == "rc",
        )  # fmt: skip
        self._closed = False
        self._live_timeout_s = live_timeout_s
        self._baud = baud
        self._kind = self._classify(target)
        self._reference_decode = False  # tests: decode tlog frames with pymavlink's MAVLink.decode
        #: live links: polled while the link is quiet or carries only unwanted messages; True ends the
        #: stream (the daemon's stop request, seen by the reading thread itself)
        self.interrupt: Callable[[], bool] | None = None
        self._own_reconnect = False  # a drop ends the source (TCP client links): see _open_live
        self.peer_lock: UdpPeerLock | None = None  # UDP links: the one peer followed
        if self._kind == "live":
            self._open_live()

    @property
    def vehicle_type(self) -> int:
        return self._conv.vehicle_type

    @property
    def skipped_samples(self) -> int:
        """Samples a ``pipeline_only`` source left out so far (0 otherwise)."""
        return self._conv.skipped

    def onboard_motor_comp(self) -> dict[int, dict[str, Any]]:
        """ArduPilot's COMPASS_MOTCT compensation undone per compass (see
        :mod:`magcomp.adapters.ardupilot_motcomp`); empty when there was none."""
        return self._conv.onboard_comp.report()

    @property
    def autopilot(self) -> int:
        return self._conv.autopilot

    def clock_offsets(self) -> dict[str, float]:
        """Streams moved onto the ``time_boot_ms`` clock and the offset added to their times (s)
        (:class:`StreamOffsets`); empty when all streams share one clock."""
        return dict(self._conv.clock.offsets.offset_s)

    def _classify(self, target: str) -> str:
        if is_live(target):
            return "live"
        path = Path(target)
        if not path.exists():
            raise InputError(f"{target}: no such file (and not a link URL such as udpin:0.0.0.0:14550)")
        if not path.is_file():
            raise InputError(f"{target}: not a file")
        try:
            size = path.stat().st_size
            with path.open("rb") as f:
                head = f.read(64)
        except OSError as exc:
            raise InputError(f"{target}: cannot read ({exc.strerror})") from None
        if size == 0:
            raise InputError(f"{target}: empty file")
        suffix = path.suffix.lower()
        if suffix == ".ulg" or head.startswith(b"ULog"):
            return "ulog"
        if suffix == ".bin" or head[:2] == b"\xa3\x95":
            return "dataflash_bin"
        if suffix == ".log" or head.startswith(b"FMT,") or b"\nFMT," in head:
            return "dataflash_text"
        return "mavlink_file"

    def _open_live(self) -> None:
        mavlink_module()  # registers the dialect and sets MAVLINK20 before mavutil is imported
        from pymavlink import mavutil

        url = self.target.removeprefix("serial:")
        baud = self._baud
        match = re.match(r"^(/dev/\S+?|COM\d+):(\d+)$", url)
        if match:
            url, baud = match.group(1), int(match.group(2))
        tcp_client = url.startswith("tcp:")
        try:
            # a TCP client link is not reconnected by pymavlink (its reconnect, run by whichever thread
            # reads or writes first, races between the reader and the heartbeat writer and can leave the
            # reader on a dead socket): a drop ends this source, the daemon opens a new one; one connect
            # attempt (retries=0), no sleeping retries inside the open
            self.connection = mavutil.mavlink_connection(
                url, baud=baud, dialect="magcomp", source_system=255, source_component=191,
                autoreconnect=not tcp_client, retries=0,
            )  # fmt: skip
        except Exception as exc:
            raise InputError(f"cannot open link {self.target}: {exc}") from None
        if self._signing_key is not None:  # only signed frames are read from this link
            from magcomp.adapters.signing import require_signed

            require_signed(self.connection.mav, self._signing_key)
        if isinstance(self.connection, mavutil.mavudp):
            self.peer_lock = UdpPeerLock(self.connection, self.counts, signing_key=self._signing_key)
        if tcp_client:
            self._own_reconnect = True
            self.connection.handle_eof = raise_dropped("connection closed by the other end")
            self.connection.handle_disconnect = raise_dropped("connection reset by the other end")

    def close(self) -> None:
        """Stop streaming and release the link (idempotent)."""
        self._closed = True
        if self.connection is not None:
            with contextlib.suppress(Exception):
                self.connection.close()
            self.connection = None

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- raw message streams --
    def _messages(self) -> Iterator[tuple[Callable[[Any], list[tuple[str, Record]]], Any]]:
        conv = self._conv
        if self._kind == "ulog":
            raise AssertionError("ulog is read by load_log only")  # pragma: no cover
        if self._kind in ("dataflash_bin", "dataflash_text"):
            for m in iter_dataflash(Path(self.target), self.counts, self._kind == "dataflash_text"):
                yield conv.dataflash, m
            if self.counts["messages"] == 0:
                raise InputError(f"{self.target}: no DataFlash messages found (not an ArduPilot log?)")
            return
        if self._kind == "mavlink_file":
            if self._reference_decode:  # tests: pymavlink's decode, dispatched by type name
                yield from ((conv.mavlink, m) for _, m in self._file_messages())
            else:
                yield from self._file_messages()
            return
        yield from ((conv.mavlink, m) for m in self._live_messages())

    def _file_messages(self) -> Iterator[tuple[Callable[[Any], list[tuple[str, Record]]], Any]]:
        path = Path(self.target)
        try:
            f = path.open("rb")
        except OSError as exc:
            raise InputError(f"{path}: cannot read ({exc.strerror})") from None
        with f:
            head = f.read(mavlink_frames.READ_CHUNK_BYTES)
            ts_len = sniff_mavlink_stream(head)
            mod = mavlink_module()
            if ts_len is None:
                if head[:256].isascii():
                    raise InputError(f"{path}: a text file, not a MAVLink log")
                ts_len = 8 if path.suffix.lower() == ".tlog" else 0
            conv = self._conv
            decoders = frame_decoders(mod, {name: getattr(conv, f"_m_{name}") for name in WANTED_MAVLINK})
            yield from iter_mavlink_file(
                f,
                head,
                decoders,
                self.counts,
                ts_len,
                crc16=crc_function(mod),
                ignore_crc=bool(mod.MAVLINK_IGNORE_CRC),
                reference_mav=mod.MAVLink(None) if self._reference_decode else None,
                rx_into=conv.clock,
            )
        if self.counts["messages"] == 0:
            raise InputError(f"{path}: no valid MAVLink messages found")

    def _live_messages(self) -> Iterator[Any]:
        wanted = set(WANTED_MAVLINK)
        while not self._closed and self.connection is not None:
            interrupt = self.interrupt
            if interrupt is not None and interrupt():
                return
            try:
                m = self.connection.recv_match(blocking=True, timeout=self._live_timeout_s)
            except (OSError, ValueError, AttributeError) as exc:
                # (AttributeError: pymavlink's link object after its socket was closed under it)
                if self._own_reconnect:
                    self.close()  # the socket is dead: the daemon reconnects with a new source
                raise InputError(f"link {self.target} failed: {exc}") from None
            if m is None:
                continue
            mtype = m.get_type()
            if mtype == "BAD_DATA":
                reason = str(getattr(m, "reason", ""))
                if "signature" in reason:
                    self.counts["bad_signature"] += 1  # unsigned or signed with another key
                else:
                    self.counts["bad_crc" if "CRC" in reason else "garbage_bytes"] += 1
                continue
            if mtype in wanted:
                self.counts["messages"] += 1
                yield m

    def records(self) -> Iterator[tuple[str, Record]]:
        """(origin, record) pairs: samples plus raw PWM / throttle records, before throttle selection."""
        for handler, msg in self._messages():
            for origin, rec in handler(msg):
                if isinstance(rec, ParamSample):
                    self.params[rec.name] = rec.value
                yield origin, rec

    def samples(self) -> Iterator[Sample]:
        """Stream typed samples; throttle records become ThrottleSample per the configured source (the
        loop of :class:`SenderStream`: parameters are stored before the sample is yielded)."""
        convert = SenderStream(self.spec, self._conv, self.params).convert
        for handler, msg in self._messages():
            yield from convert(handler(msg))

    def vehicle_samples(self) -> Iterator[tuple[tuple[int, int], Sample]]:
        """Live links: ((system id, component id), sample) for every sender on the link, each with its
        own clock (reboots, jumps), parameters and throttle selection: a link carrying several vehicles
        (or components) never mixes their samples. Same samples per sender as :meth:`samples`."""
        if self._kind != "live":
            raise AssertionError("vehicle_samples() is for live links")  # pragma: no cover
        streams: dict[tuple[int, int], SenderStream] = {}
        undo = self._conv.undo_motor_comp
        for msg in self._live_messages():
            key = (int(msg.get_srcSystem()), int(msg.get_srcComponent()))
            st = streams.get(key)
            if st is None:
                conv = self._conv if not streams else MessageConverter(self.counts, mag_index=self.mag_index,
                                                                 undo_motor_comp=undo)  # fmt: skip
                st = streams[key] = SenderStream(self.spec, conv, self.params if not streams else {})
            for sample in st.push(msg):
                yield key, sample


class SenderStream:
    """The samples of one sender, from its records: the one loop of the sources (:meth:`MavSource.samples`
    over a log or link, :meth:`MavSource.vehicle_samples` per sender of a shared link, :func:`sender_stream`
    for a host that owns the link). Throttle records become ThrottleSample per the configured source,
    re-resolved when a new kind of throttle record, a parameter or a HEARTBEAT of another vehicle type
    arrives."""

    def __init__(self, spec: ThrottleSpec, conv: MessageConverter, params: dict[str, float]) -> None:
        self.spec = spec
        self.conv = conv
        self.params = params
        self.available: set[str] = set()
        self.resolved: ResolvedThrottle | None = None
        self.stale = True
        #: the vehicle type :attr:`resolved` was decided for (a HEARTBEAT re-decides only when it changes:
        #: the decision is a function of the spec, the vehicle type, the parameters and the kinds seen)
        self._resolved_type: int | None = None

    def push(self, msg: Any) -> list[Sample]:
        """One MAVLink message's samples."""
        return self.convert(self.conv.mavlink(msg))

    def convert(self, recs: list[tuple[str, Record]]) -> list[Sample]:
        """The samples of one message's records (a ClockResetSample first when the message rebooted the
        clock); parameters are stored as they come."""
        clock = self.conv.clock
        out: list[Sample] = []
        if clock.reboot_pending:
            clock.reboot_pending = False
            out.append(ClockResetSample(clock.last_t_s, clock.offset_s))
        for _, rec in recs:
            cls = type(rec)
            if cls is PwmRecord or cls is ThrottleRecord:
                assert isinstance(rec, PwmRecord | ThrottleRecord)  # for mypy (cheap: few per message)
                if rec.kind not in self.available:
                    self.available.add(rec.kind)
                    self.stale = True
                if self.stale:
                    vtype = self._resolved_type = self.conv.vehicle_type
                    self.resolved = resolve_throttle(self.spec, vtype, self.params, frozenset(self.available))
                    self.stale = False
                thr = throttle_sample(self.resolved, rec)
                if thr is not None:
                    out.append(thr)
                continue
            if cls is ParamSample:
                assert isinstance(rec, ParamSample)
                self.params[rec.name] = rec.value
                self.stale = True
            elif cls is HeartbeatSample and self.conv.vehicle_type != self._resolved_type:
                self.stale = True
            out.append(rec)  # type: ignore[arg-type]
        return out


def sender_stream(spec: str | ThrottleSpec, counts: dict[str, int] | None = None) -> SenderStream:
    """A converter for the messages of one sender handed over one at a time (a host that owns the link:
    :mod:`magcomp.service.companion`); ``push(msg)`` returns that message's samples."""
    counts = counts if counts is not None else Counts()
    conv = MessageConverter(counts, mag_index=None, undo_motor_comp=True)
    return SenderStream(parse_throttle_source(spec), conv, {})


def throttle_sample(
    resolved: ResolvedThrottle | None, rec: PwmRecord | ThrottleRecord
) -> ThrottleSample | None:
    if resolved is None:
        return None
    if isinstance(rec, ThrottleRecord):
        if rec.kind != resolved.kind:
            return None
        return ThrottleSample(rec.t_s, rec.throttle_01, resolved.label)
    if (rec.kind == "rc") != (resolved.kind == "rc") or resolved.kind in ("vfr_hud", "ctun"):
        return None
    out = throttle_from_pwm(resolved, rec.pwm_us)
    if out is None:
        return None
    return ThrottleSample(rec.t_s, out[0], resolved.label, out[1] if resolved.kind == "motors" else ())


class SourceOptions(TypedDict, total=False):
    """The keyword options of :func:`open_source`, as :class:`MavSource` takes them (defaults there)."""

    throttle_source: str | ThrottleSpec
    mag_index: int | None
    undo_motor_comp: bool
    baud: int
    live_timeout_s: float
    pipeline_only: bool
    signing_key: bytes | None


def open_source(
    url_or_path: str | os.PathLike[str], **options: Unpack[SourceOptions]
) -> MavSource | UlogSource:
    """Open a log file (.tlog, raw MAVLink, DataFlash .bin/.log, PX4 .ulg) or a live link URL.

    Links: ``udpin:0.0.0.0:14550``, ``udpout:host:port``, ``tcp:host:port``, ``tcpin:0.0.0.0:5760``,
    ``/dev/ttyACM0:115200`` or ``serial:/dev/ttyUSB0:57600``. Raises InputError for a missing, empty or
    unrecognisable file. ``mag_index`` restricts MagSamples to one compass. A ``.ulg`` gives a
    :class:`~magcomp.adapters.ulog_source.UlogSource` (same interface, no link; ``throttle_source`` and
    ``mag_index`` only). ``pipeline_only``: leave out what :class:`~magcomp.service.pipeline.Pipeline`
    ignores (temperature and power samples, IMUs other than IMU 0; MAVLink and DataFlash), counted in
    ``skipped_samples``, and the PWM of MAVLink RC inputs unless the throttle source is ``rc``.
    """
    target = os.fspath(url_or_path)
    if is_ulog(target):
        from magcomp.adapters.ulog_source import UlogSource

        return UlogSource(
            target, throttle_source=options.get("throttle_source", "auto"), mag_index=options.get("mag_index")
        )
    return MavSource(target, **options)


# --- whole-log loading ---


def load_log(
    path: str | os.PathLike[str],
    throttle_source: str | ThrottleSpec = "auto",
    mag_index: int | None = None,
    *,
    undo_motor_comp: bool = True,
    window: Window | None = None,
    on_progress: Callable[[float], None] | None = None,
) -> LogData:
    """Read a whole log into columns (:class:`~magcomp.core.types.LogData`), in the module's fixed units.

    Unlike streaming, preferences are decided with the whole log known: RAW_IMU over SCALED_IMU for compass 0,
    SYS_STATUS/CURR over BATTERY_STATUS for battery 0, IMU temperature over barometer temperature, and the
    ``auto`` throttle source from the final vehicle type and parameters.

    Memory: the file is read a chunk at a time and each message's values go straight into compact columns
    (:mod:`magcomp.adapters.columns`), ~8 bytes per value kept. ``window`` keeps only the rows in a time
    window (and one neighbour each side), cut while reading; the whole file is still read (parameters and
    the vehicle type can come at any time). PX4 ULog (:func:`~magcomp.adapters.ulog_source.load_ulog`)
    ignores it. ``on_progress``: called every thousand messages or so with the message time reached (s; a
    progress bar), not for ULog (read whole by pyulog).
    """
    target = os.fspath(path)
    if is_ulog(target):
        from magcomp.adapters.ulog_source import load_ulog

        return load_ulog(target, throttle_source, mag_index)
    source = MavSource(
        target, throttle_source=throttle_source, mag_index=mag_index, undo_motor_comp=undo_motor_comp
    )
    if source._kind == "live":
        raise InputError(f"{target}: load_log reads files; use open_source for live links")
    records = source.records()
    if on_progress is not None:
        records = reporting(records, on_progress)
    try:
        return collect_log(source, records, window)
    finally:
        source.close()
