"""Publishing: MAGCOMP_HEADING (MAVLink 2, magcomp dialect) to links and to tlog files.

One :class:`HeadingEncoder` packs each estimate once; the bytes go to every sink (the master link, each
``--out``, an ``--emit`` tlog), so all of them carry the same sequence numbers.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import stat
import struct
import tempfile
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from magcomp.adapters.files import current_umask
from magcomp.core.types import (
    FLAG_CALIBRATED,
    FLAG_INPUTS_STALE,
    FLAG_NO_THROTTLE,
    FLAG_THETA_CONVERGED,
    HeadingEstimate,
)
from magcomp.errors import InputError

log = logging.getLogger("magcomp.publish")

_TLOG_STAMP = struct.Struct(">Q")
#: MAVLink 2 header: magic, payload length, incompat and compat flags, sequence, system, component, message
#: id (24 bits, little-endian); then the payload and the CRC-16/MCRF4XX
_V2_HEADER = struct.Struct("<BBBBBBBHB")
_CRC = struct.Struct("<H")

F64 = NDArray[np.float64]
Float3 = tuple[float, float, float]

#: a block's frames are packed at full length (10 header bytes, the payload, the CRC), its times below this
#: (ms, us: the integers a float holds exactly); beyond it (or non-finite), one frame at a time
_BLOCK_MAX_INT = 2.0**52


class ByteSink(Protocol):
    def write_packet(self, t_s: float, packet: bytes) -> None: ...

    def close(self) -> None: ...


class HeadingEncoder:
    """Packs MAGCOMP_HEADING. ``src_system`` 0 means "the vehicle's own id" (set with :meth:`set_system`)."""

    def __init__(self, src_system: int = 0, src_component: int = 191) -> None:
        from magcomp.adapters.dialect import ensure_dialect

        self._mod = ensure_dialect()
        self._fixed_system = src_system != 0
        self.mav: Any = self._mod.MAVLink(None, srcSystem=src_system or 1, srcComponent=src_component)
        self._msg_cls = self._mod.MAVLink_magcomp_heading_message
        self._payload: struct.Struct = self._msg_cls.unpacker
        self._crc_extra = bytes((self._msg_cls.crc_extra,))
        self._header = _V2_HEADER
        self._id_lo, self._id_hi = self._msg_cls.id & 0xFFFF, self._msg_cls.id >> 16
        # CRC-16/MCRF4XX as the dialect computes it: fastcrc's when installed, else pymavlink's own
        fast = getattr(self._mod, "mcrf4xx", None)
        slow = self._mod.x25crc
        self._crc: Any = (lambda b: fast(b, 0xFFFF)) if fast is not None else (lambda b: slow(b).crc)

    @property
    def module(self) -> Any:
        """The generated dialect module (message classes and enums)."""
        return self._mod

    def set_system(self, system_id: int) -> None:
        if not self._fixed_system:
            self.mav.srcSystem = int(system_id) & 0xFF

    def encode(self, est: HeadingEstimate) -> bytes:
        """MAVLink 2 bytes of one MAGCOMP_HEADING."""
        th = est.theta_mgauss
        b = est.bias_mgauss
        t_boot = est.t_boot_s if est.t_boot_s == est.t_boot_s else est.t_s  # NaN: the same clock
        return self.encode_values(
            t_boot,
            float(est.heading_deg),
            float(est.heading_raw_deg),
            (float(th[0]), float(th[1]), float(th[2])),
            (float(b[0]), float(b[1]), float(b[2])),
            float(est.throttle_01),
            int(est.mag_index),
            int(est.flags),
        )

    def encode_values(
        self,
        t_boot_s: float,
        heading_deg: float,
        heading_raw_deg: float,
        theta: tuple[float, float, float],
        bias: tuple[float, float, float],
        throttle_01: float,
        mag_index: int,
        flags: int,
    ) -> bytes:
        """:meth:`encode` from plain values. The frame is packed here (the bytes pymavlink's message
        object would pack, tested against it) at a third of the cost; signed links go through pymavlink."""
        t_ms = round(t_boot_s * 1000.0) & 0xFFFFFFFF
        mav = self.mav
        seq = mav.seq
        if mav.signing.sign_outgoing:
            out = bytes(self._msg_cls(t_ms, heading_deg, heading_raw_deg, theta, bias, throttle_01,
                                      mag_index & 0xFF, flags & 0xFF).pack(mav))  # fmt: skip
            mav.seq = (seq + 1) & 0xFF  # as pymavlink's send() counts (pack() alone does not)
            return out
        mav.seq = (seq + 1) & 0xFF  # the link's packet counter: a ground station counts losses by it
        payload = self._payload.pack(t_ms, heading_deg, heading_raw_deg, *theta, *bias, throttle_01,
                                     mag_index & 0xFF, flags & 0xFF)  # fmt: skip
        if not payload[-1]:  # MAVLink 2 drops trailing zero bytes (not the first)
            payload = payload.rstrip(b"\0") or payload[:1]
        frame = self._header.pack(0xFD, len(payload), 0, 0, seq, mav.srcSystem, mav.srcComponent,
                                  self._id_lo, self._id_hi) + payload  # fmt: skip
        return frame + _CRC.pack(self._crc(frame[1:] + self._crc_extra))

    def encode_block(
        self,
        t_boot_s: F64,
        heading_deg: F64,
        heading_raw_deg: F64,
        theta: F64,
        bias: F64,
        throttle_01: F64,
        mag_index: NDArray[np.int64],
        flags: NDArray[np.int64],
    ) -> tuple[NDArray[np.uint8], NDArray[np.int64]] | None:
        """:meth:`encode_values` of n frames at once (theta and bias (n, 3), the rest (n,)), on consecutive
        sequence numbers: each frame's bytes left-aligned in a row of (n, full frame length) and each
        frame's length (the same bytes as :meth:`encode_values`, tested against it). None (nothing
        packed, the counter untouched): a signed link, a time a frame at a time handles
        (:data:`_BLOCK_MAX_INT`), or a value beyond float32 (a frame at a time refuses it)."""
        mav = self.mav
        n = len(heading_deg)
        t_ms = np.rint(np.asarray(t_boot_s, dtype=float) * 1000.0)  # round(): half to even, as np.rint
        if mav.signing.sign_outgoing or not bool(np.all(np.abs(t_ms) < _BLOCK_MAX_INT)):
            return None
        floats = np.column_stack((heading_deg, heading_raw_deg, theta, bias, throttle_01))
        with np.errstate(over="ignore"):  # an overflow is looked for just below
            f32 = floats.astype("<f4")
        if bool(np.any(np.isinf(f32) & ~np.isinf(floats))):
            return None  # beyond float32: struct refuses it a frame at a time, astype would write inf
        plen = self._payload.size
        hlen = _V2_HEADER.size
        out = np.zeros((n, hlen + plen + _CRC.size), dtype=np.uint8)

        def put(col: int, values: Any, dtype: str) -> None:
            v = np.ascontiguousarray(np.asarray(values).astype(dtype).reshape(n, -1))
            out[:, col : col + v.shape[1] * v.itemsize] = v.view(np.uint8)

        seq0 = mav.seq
        out[:, 0] = 0xFD
        put(4, (seq0 + np.arange(n)) & 0xFF, "u1")
        out[:, 5], out[:, 6] = mav.srcSystem, mav.srcComponent
        put(7, np.full(n, self._id_lo), "<u2")
        out[:, 9] = self._id_hi
        # the payload in its fields' order (self._payload: "<Iff3f3ffBB")
        put(hlen, t_ms.astype(np.int64) & 0xFFFFFFFF, "<u4")
        put(hlen + 4, f32, "<f4")
        put(hlen + plen - 2, np.asarray(mag_index) & 0xFF, "u1")
        put(hlen + plen - 1, np.asarray(flags) & 0xFF, "u1")
        # MAVLink 2 drops the payload's trailing zero bytes (not the first)
        nonzero = out[:, hlen : hlen + plen] != 0
        last = plen - np.argmax(nonzero[:, ::-1], axis=1)
        payload_len = np.where(nonzero.any(axis=1), last, 1)
        out[:, 1] = payload_len
        sizes = hlen + payload_len + _CRC.size
        buf = out.tobytes()
        width = out.shape[1]
        crc, extra = self._crc, self._crc_extra
        crcs = np.array([crc(buf[k * width + 1 : k * width + hlen + m] + extra)
                         for k, m in enumerate(payload_len.tolist())], dtype="<u2")  # fmt: skip
        rows = np.arange(n)
        crc_bytes = crcs.reshape(n, 1).view(np.uint8)
        out[rows, hlen + payload_len] = crc_bytes[:, 0]
        out[rows, hlen + payload_len + 1] = crc_bytes[:, 1]
        mav.seq = (seq0 + n) & 0xFF  # as n calls of encode_values count
        return out, sizes.astype(np.int64)

    def named_value(self, t_boot_s: float, name: str, value: float) -> bytes:
        """One NAMED_VALUE_FLOAT (``name`` at most 10 characters) on this encoder's link sequence."""
        m = self._mod
        t_ms = round(t_boot_s * 1000.0) & 0xFFFFFFFF if math.isfinite(t_boot_s) else 0
        msg = m.MAVLink_named_value_float_message(t_ms, name.encode("ascii"), float(value))
        out = bytes(msg.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) & 0xFF
        return out

    def identity_requests(self, target_system: int, target_component: int) -> list[bytes]:
        """Asking a vehicle for AUTOPILOT_VERSION (its unique id keys its saved state), as a ground station
        does at connect: MAV_CMD_REQUEST_MESSAGE and the older MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES."""
        m = self._mod
        out = []
        for cmd, p1 in ((m.MAV_CMD_REQUEST_MESSAGE, 148.0), (m.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 1.0)):
            msg = m.MAVLink_command_long_message(target_system, target_component, cmd, 0, p1, *(0,) * 6)
            out.append(bytes(msg.pack(self.mav)))
            self.mav.seq = (self.mav.seq + 1) & 0xFF
        return out

    def heartbeat(self) -> bytes:
        """A HEARTBEAT of an onboard companion (MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID)."""
        m = self._mod
        msg = m.MAVLink_heartbeat_message(m.MAV_TYPE_ONBOARD_CONTROLLER, m.MAV_AUTOPILOT_INVALID, 0, 0,
                                          m.MAV_STATE_ACTIVE, 3)  # fmt: skip
        out = bytes(msg.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) & 0xFF
        return out


#: the arguments of :meth:`HeadingEncoder.encode_values`: time since boot (s), heading and uncorrected heading
#: (deg), theta and bias (mgauss), throttle (0..1), compass index, flags
HeadingValues = tuple[float, float, float, Float3, Float3, float, int, int]
#: MAGCOMP_HEADING frames a :class:`FrameQueue` holds before it packs and writes them
QUEUE_FRAMES = 2048


def write_headings(encoder: HeadingEncoder, writer: TlogWriter, t_s: F64, t_boot_s: F64, heading_deg: F64,
                   heading_raw_deg: F64, theta_mgauss: F64, bias_mgauss: F64, throttle_01: F64,
                   mag_index: NDArray[np.int64], flags: NDArray[np.int64]) -> None:  # fmt: skip
    """MAGCOMP_HEADING of a block of samples (columns; theta and bias (n, 3)) into the tlog at times ``t_s``:
    packed at once (:meth:`HeadingEncoder.encode_block`, :meth:`TlogWriter.write_frames`), or, where the
    block framer refuses the block (a signed link, a value beyond float32), one frame at a time
    (:meth:`HeadingEncoder.encode_values`, :meth:`TlogWriter.write_packet`): the same bytes either way."""
    block = encoder.encode_block(t_boot_s, heading_deg, heading_raw_deg, theta_mgauss, bias_mgauss,
                                 throttle_01, mag_index, flags)  # fmt: skip
    if block is not None:
        writer.write_frames(t_s, *block)
        return
    encode, write = encoder.encode_values, writer.write_packet
    theta = [(a, b, c) for a, b, c in np.asarray(theta_mgauss).tolist()]
    bias = [(a, b, c) for a, b, c in np.asarray(bias_mgauss).tolist()]
    lists = [np.asarray(c).tolist() for c in (t_boot_s, heading_deg, heading_raw_deg, throttle_01, mag_index,
                                               flags)]  # fmt: skip
    cols = (*lists[:3], theta, bias, *lists[3:])
    for t, v in zip(np.asarray(t_s).tolist(), zip(*cols, strict=True), strict=True):
        write(t, encode(*v))


class FrameQueue:
    """MAGCOMP_HEADING for a tlog, queued and packed a block at a time (:func:`write_headings`): the same
    bytes, sequence numbers and times as :meth:`HeadingEncoder.encode_values` then
    :meth:`TlogWriter.write_packet` of each frame in turn, at a third less of the cost. The encoder is this
    queue's alone until :meth:`flush` (it numbers the frames when it packs them)."""

    def __init__(self, encoder: HeadingEncoder, writer: TlogWriter, size: int = QUEUE_FRAMES) -> None:
        self.encoder, self.writer = encoder, writer
        self._size = size
        self._rows: list[tuple[float, HeadingValues]] = []

    def add(self, t_s: float, values: HeadingValues) -> None:
        """One frame at ``t_s`` (the tlog's time), ``values`` the arguments of
        :meth:`HeadingEncoder.encode_values`."""
        rows = self._rows
        rows.append((t_s, values))
        if len(rows) >= self._size:
            self.flush()

    def flush(self) -> None:
        """Pack and write every frame queued. The frames stay queued until written: a ^C or an error while
        they are packed leaves them for the next flush (the one at close)."""
        rows = self._rows
        if not rows:
            return
        t_s, values = zip(*rows, strict=True)
        t_boot, head, head_raw, theta, bias, thr, mag, flags = zip(*values, strict=True)
        f, i = float, np.int64
        write_headings(self.encoder, self.writer, np.array(t_s, dtype=f), np.array(t_boot, dtype=f),
                       np.array(head, dtype=f), np.array(head_raw, dtype=f),
                       np.array(theta, dtype=f).reshape(-1, 3), np.array(bias, dtype=f).reshape(-1, 3),
                       np.array(thr, dtype=f), np.array(mag, dtype=i), np.array(flags, dtype=i))  # fmt: skip
        self._rows = []


#: NAMED_VALUE_FLOAT names (the compass index appended; at most 10 characters): corrected heading (deg),
#: |theta| (mgauss per unit throttle squared), status (:func:`pilot_status`). Documented in docs/pilots.md.
NV_HEADING = "MC_HDG"
NV_THETA = "MC_THETA"
NV_STATUS = "MC_STAT"
#: MC_STATn values
STATUS_UNCORRECTED = 0.0  # no calibration yet, or no throttle: the heading is not compensated
STATUS_LEARNING = 1.0  # compensated, theta still converging
STATUS_CONVERGED = 2.0  # compensated, theta converged
STATUS_STALE = 3.0  # attitude, gyro or throttle inputs are late: the output may be stale


def pilot_status(flags: int) -> float:
    """The one number a pilot reads (MC_STATn) from MAGCOMP_HEADING's flags."""
    if flags & FLAG_INPUTS_STALE:
        return STATUS_STALE
    if not flags & FLAG_CALIBRATED or flags & FLAG_NO_THROTTLE:
        return STATUS_UNCORRECTED
    return STATUS_CONVERGED if flags & FLAG_THETA_CONVERGED else STATUS_LEARNING


def named_value_names(mag_index: int) -> tuple[str, str, str]:
    """The three NAMED_VALUE_FLOAT names of compass ``mag_index``."""
    return f"{NV_HEADING}{mag_index}", f"{NV_THETA}{mag_index}", f"{NV_STATUS}{mag_index}"


class NamedValues:
    """NAMED_VALUE_FLOAT for ground stations without the dialect (Mission Planner shows MAV_MC_HDG0 ...,
    MAVProxy and Cockpit their names): per compass at most ``rate_hz`` on message time, packed with
    ``encoder``'s link sequence. ``rate_hz`` 0: none."""

    def __init__(self, encoder: HeadingEncoder, rate_hz: float) -> None:
        self._encoder = encoder
        self._period = 1.0 / rate_hz if rate_hz > 0 else math.inf
        self._last: dict[int, float] = {}

    def packets(
        self,
        t_s: float,
        t_boot_s: float,
        mag_index: int,
        heading_deg: float,
        theta: tuple[float, float, float] | NDArray[np.float64],
        flags: int,
    ) -> list[bytes]:
        """The frames due for this estimate (none most of the time)."""
        if self._period == math.inf:
            return []
        last = self._last.get(mag_index)
        if last is not None and last <= t_s < last + self._period:  # (a clock that ran back: due now)
            return []
        self._last[mag_index] = t_s
        norm = math.sqrt(float(theta[0]) ** 2 + float(theta[1]) ** 2 + float(theta[2]) ** 2)
        values = (float(heading_deg) % 360.0, norm, pilot_status(int(flags)))
        enc = self._encoder
        return [enc.named_value(t_boot_s, name, v) for name, v in zip(named_value_names(mag_index), values,
                                                                       strict=True)]  # fmt: skip


class TlogWriter:
    """A ``.tlog``: each packet preceded by an 8-byte big-endian timestamp in microseconds.

    The timestamp is the estimate's message time (the input's clock), not wall-clock time, so the
    same replay always writes the same file.

    A regular file (or a path that does not exist yet) is written beside it under a temporary name and
    renamed over it by :meth:`close`: a reader never sees half a file, and a write that fails, or a
    replay that ends with nothing to write (:meth:`close` with ``commit=False``, or no packet at all),
    leaves the path exactly as it was. Only the temporary file, ours, is ever removed. Anything else
    (a device such as ``/dev/null``, a FIFO) is written in place and never removed.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.packets = 0
        self._tmp: Path | None = None
        try:
            st: os.stat_result | None = os.stat(self.path)
        except FileNotFoundError:
            st = None
        except OSError as exc:
            raise InputError(f"cannot write {self.path}: {exc.strerror}") from None
        try:
            if st is None or stat.S_ISREG(st.st_mode):
                target = self.path.resolve() if st is not None else self.path  # (through a symlink)
                fd, name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".part", dir=target.parent)
                self._target, self._tmp = target, Path(name)
                mode = stat.S_IMODE(st.st_mode) if st is not None else 0o666 & ~current_umask()
                with contextlib.suppress(OSError):
                    os.fchmod(fd, mode)
                self._f = os.fdopen(fd, "wb")
            else:
                self._target = self.path
                self._f = self.path.open("wb")
        except OSError as exc:
            raise InputError(f"cannot write {self.path}: {exc.strerror or exc}") from None

    def write_packet(self, t_s: float, packet: bytes) -> None:
        try:
            self._f.write(_TLOG_STAMP.pack(max(0, round(t_s * 1e6))) + packet)
        except OSError as exc:  # a full disk or a vanished device: one line, not a traceback
            self._abandon()
            raise InputError(f"cannot write {self.path}: {exc.strerror or exc}") from None
        self.packets += 1

    def write_frames(self, t_s: F64, frames: NDArray[np.uint8], sizes: NDArray[np.int64]) -> None:
        """:meth:`write_packet` of each of :meth:`HeadingEncoder.encode_block`'s frames (the first ``sizes``
        bytes of each row of ``frames``) at its time, in one write (a time beyond :data:`_BLOCK_MAX_INT`:
        one packet at a time)."""
        us = np.maximum(np.rint(np.asarray(t_s, dtype=float) * 1e6), 0.0)  # max(0, round()), as np.rint
        if not bool(np.all(us < _BLOCK_MAX_INT)):
            times, lengths = np.asarray(t_s).tolist(), np.asarray(sizes).tolist()
            for t, row, size in zip(times, frames, lengths, strict=True):
                self.write_packet(t, row[:size].tobytes())
            return
        n, width = frames.shape
        stamp = _TLOG_STAMP.size
        rec = np.empty((n, stamp + width), dtype=np.uint8)
        rec[:, :stamp] = us.astype(">u8").reshape(n, 1).view(np.uint8)
        rec[:, stamp:] = frames
        keep = np.arange(stamp + width) < (stamp + np.asarray(sizes)).reshape(n, 1)
        try:
            self._f.write(rec[keep].tobytes())
        except OSError as exc:  # as write_packet
            self._abandon()
            raise InputError(f"cannot write {self.path}: {exc.strerror or exc}") from None
        self.packets += n

    def _abandon(self) -> None:
        """After a failed write: close without flushing again (the flush would fail the same way) and
        remove the temporary file; the path itself stays as it was."""
        with contextlib.suppress(OSError, ValueError):
            self._f.close()
        self._discard_tmp()

    def _discard_tmp(self) -> None:
        tmp, self._tmp = self._tmp, None
        if tmp is not None:
            with contextlib.suppress(OSError):
                tmp.unlink()

    def close(self, commit: bool = True) -> None:
        """Finish the file (idempotent). ``commit``: rename the temporary file over the path, when it
        holds at least one packet; otherwise it is removed and the path left as it was."""
        if not self._f.closed:
            try:
                self._f.close()
            except OSError as exc:
                self._discard_tmp()
                raise InputError(f"cannot write {self.path}: {exc.strerror or exc}") from None
        if self._tmp is None:
            return
        if not commit or self.packets == 0:
            self._discard_tmp()
            return
        try:
            os.replace(self._tmp, self._target)
        except OSError as exc:
            self._discard_tmp()
            raise InputError(f"cannot write {self.path}: {exc.strerror or exc}") from None
        self._tmp = None


class LinkSink:
    """Writes packets to a mavutil connection; a failed write is counted and logged, never raised."""

    def __init__(self, name: str, connection: Any) -> None:
        self.name = name
        self.connection = connection
        self.packets = 0
        self.errors = 0

    def write_packet(self, t_s: float, packet: bytes) -> None:
        try:
            self.connection.write(packet)
            self.packets += 1
        except Exception as exc:  # OSError, and pymavlink's link object in a state between two sockets
            self.errors += 1
            if self.errors == 1 or self.errors % 1000 == 0:
                log.warning("output %s: write failed (%s); %d failures so far", self.name, exc, self.errors)

    def close(self) -> None:
        try:
            self.connection.close()
        except Exception as exc:  # closing a dead link must not stop the shutdown
            log.debug("output %s: close failed: %s", self.name, exc)
