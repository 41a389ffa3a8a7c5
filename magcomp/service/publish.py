"""Publishing: MAGCOMP_HEADING (MAVLink 2, magcomp dialect) to links and to tlog files.

One :class:`HeadingEncoder` packs each estimate once; the bytes go to every sink (the master link, each
``--out``, an ``--emit`` tlog), so all of them carry the same sequence numbers.
"""

from __future__ import annotations

import contextlib
import logging
import struct
from pathlib import Path
from typing import Any, Protocol

from magcomp.core.types import HeadingEstimate
from magcomp.errors import InputError

log = logging.getLogger("magcomp.publish")

_TLOG_STAMP = struct.Struct(">Q")


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

    def set_system(self, system_id: int) -> None:
        if not self._fixed_system:
            self.mav.srcSystem = int(system_id) & 0xFF

    def encode(self, est: HeadingEstimate) -> bytes:
        """MAVLink 2 bytes of one MAGCOMP_HEADING (advances the sequence number)."""
        th = est.theta_mgauss
        b = est.bias_mgauss
        t_boot = est.t_boot_s if est.t_boot_s == est.t_boot_s else est.t_s  # NaN: the same clock
        msg = self._msg_cls(
            round(t_boot * 1000.0) & 0xFFFFFFFF,
            float(est.heading_deg),
            float(est.heading_raw_deg),
            [float(th[0]), float(th[1]), float(th[2])],
            [float(b[0]), float(b[1]), float(b[2])],
            float(est.throttle_01),
            int(est.mag_index) & 0xFF,
            int(est.flags) & 0xFF,
        )
        return bytes(msg.pack(self.mav))

    def heartbeat(self) -> bytes:
        """A HEARTBEAT of an onboard companion (MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID)."""
        m = self._mod
        msg = m.MAVLink_heartbeat_message(m.MAV_TYPE_ONBOARD_CONTROLLER, m.MAV_AUTOPILOT_INVALID, 0, 0,
                                          m.MAV_STATE_ACTIVE, 3)  # fmt: skip
        return bytes(msg.pack(self.mav))


class TlogWriter:
    """A ``.tlog``: each packet preceded by an 8-byte big-endian timestamp in microseconds.

    The timestamp is the estimate's message time (the input's clock), not wall-clock time, so the
    same replay always writes the same file.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            self._f = self.path.open("wb")
        except OSError as exc:
            raise InputError(f"cannot write {self.path}: {exc.strerror}") from None
        self.packets = 0

    def write_packet(self, t_s: float, packet: bytes) -> None:
        try:
            self._f.write(_TLOG_STAMP.pack(max(0, round(t_s * 1e6))) + packet)
        except OSError as exc:  # a full disk or a vanished device: one line, not a traceback
            self._abandon()
            raise InputError(f"cannot write {self.path}: {exc.strerror or exc}") from None
        self.packets += 1

    def _abandon(self) -> None:
        """Close after a failed write without flushing again (the flush would fail the same way)."""
        with contextlib.suppress(OSError):
            self._f.close()

    def close(self) -> None:
        if not self._f.closed:
            try:
                self._f.close()
            except OSError as exc:
                raise InputError(f"cannot write {self.path}: {exc.strerror or exc}") from None


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
        except OSError as exc:
            self.errors += 1
            if self.errors == 1 or self.errors % 1000 == 0:
                log.warning("output %s: write failed (%s); %d failures so far", self.name, exc, self.errors)

    def close(self) -> None:
        try:
            self.connection.close()
        except Exception as exc:  # closing a dead link must not stop the shutdown
            log.debug("output %s: close failed: %s", self.name, exc)
