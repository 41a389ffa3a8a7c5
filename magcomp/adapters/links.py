"""Live links: telling a link URL or device from a file, and the trust boundary of a UDP link
(:class:`UdpPeerLock`)."""

from __future__ import annotations

import contextlib
import errno
import logging
import math
import os
import re
import stat
from collections.abc import Callable
from pathlib import Path
from typing import Any

from magcomp.adapters.mavlink_frames import mavlink_module
from magcomp.adapters.message_convert import MAV_TYPE_GCS, WANTED_MAVLINK

log = logging.getLogger("magcomp.source")

LIVE_PREFIXES = ("udp:", "udpin:", "udpout:", "udpbcast:", "tcp:", "tcpin:", "serial:")


def is_live(target: str) -> bool:
    if target.startswith(LIVE_PREFIXES):
        return True
    dev = target.rsplit(":", 1)[0] if re.search(r":\d+$", target) else target
    try:
        return stat.S_ISCHR(os.stat(dev).st_mode)
    except OSError:
        return False


def is_ulog(target: str) -> bool:
    """A ULog file: ``.ulg`` or the ULog magic, read from a regular file only (never from a link)."""
    if is_live(target):
        return False
    path = Path(target)
    if path.suffix.lower() == ".ulg":
        return path.is_file()
    try:
        with path.open("rb") as f:
            return f.read(4) == b"ULog"
    except OSError:
        return False


#: a locked UDP peer silent this long may be replaced by another sender of vehicle data (a flight
#: controller that restarted on a new port); until then, datagrams from anyone else are dropped
PEER_RELOCK_S = 5.0
#: foreign senders named in a warning; the rest are counted only
FOREIGN_NAMED = 5


class UdpPeerLock:
    """The trust boundary of a UDP link (``udpin:``, ``udp:``, ``udpout:``): the link follows one peer.

    ``udpin``: the first address whose datagram carries vehicle data (a sensor, attitude, output or
    parameter message, or a HEARTBEAT that is not a ground station's) becomes the flight controller;
    datagrams from any other address are dropped before the MAVLink parser sees them (counted as
    ``foreign_datagrams``, the first senders named in a warning), and what the link sends goes to that
    address only (pymavlink would send to every address that ever sent a datagram). A peer silent for
    :data:`PEER_RELOCK_S` may be replaced by the next sender of vehicle data (logged). ``udpout``: only the
    destination's replies are read. Installed by replacing the connection's ``recv``."""

    def __init__(
        self,
        conn: Any,
        counts: dict[str, int],
        signing_key: bytes | None = None,
    ) -> None:
        import socket

        self.conn = conn
        self.counts = counts
        self.peer: tuple[Any, ...] | None = None
        self.vehicle: tuple[int, int] | None = None
        self._last_from_peer = -math.inf
        self._foreign: set[tuple[Any, ...]] = set()
        self._probe = mavlink_module().MAVLink(None)
        self._probe.robust_parsing = True
        if signing_key is not None:  # a signed link locks onto signed vehicle data only
            from magcomp.adapters.signing import require_signed

            require_signed(self._probe, signing_key)
        self._wanted = frozenset(WANTED_MAVLINK)
        self._socket_error = socket.error
        self._relockable = bool(conn.udp_server or conn.broadcast)  # (udpbcast: the first replier)
        if not self._relockable:  # udpout: the destination is the peer, by construction
            with contextlib.suppress(OSError):
                host, port = conn.destination_addr
                self.peer = (socket.gethostbyname(host), int(port))
        conn.clients.clear()
        conn.recv = self.recv

    def recv(self, n: int | None = None) -> bytes:
        import time

        conn = self.conn
        try:
            data, addr = conn.port.recvfrom(65535)
        except self._socket_error as exc:
            if exc.errno in (errno.EAGAIN, errno.EWOULDBLOCK, errno.ECONNREFUSED):
                return b""
            raise
        now = time.monotonic()
        if addr == self.peer:
            self._last_from_peer = now
            return bytes(data)
        if self.peer is not None and (not self._relockable or now - self._last_from_peer < PEER_RELOCK_S):
            self._refuse(addr)
            return b""
        vehicle = self._vehicle_in(data)
        if vehicle is None:
            self._refuse(addr)
            return b""
        if self.peer is not None:
            log.warning("the flight controller at %s:%s was silent for %.0f s; now following %s:%s "
                        "(system %d component %d)", *self.peer[:2], now - self._last_from_peer, *addr[:2],
                        *vehicle)  # fmt: skip
        else:
            log.info("following the flight controller at %s:%s (system %d component %d); vehicle data "
                     "from other addresses is ignored", *addr[:2], *vehicle)  # fmt: skip
        self.peer, self.vehicle, self._last_from_peer = addr, vehicle, now
        self._foreign.discard(addr)
        conn.clients.clear()
        conn.clients.add(addr)
        conn.clients_last_alive[addr] = time.time()
        if conn.broadcast:
            conn.last_address = addr
        return bytes(data)

    def _vehicle_in(self, data: bytes) -> tuple[int, int] | None:
        """(system, component) of the first vehicle message in a datagram, None when it has none."""
        try:
            msgs = self._probe.parse_buffer(bytearray(data)) or []
        except Exception:  # whatever the parser makes of hostile bytes: not vehicle data
            return None
        finally:
            self._probe.buf = bytearray()  # each datagram on its own: nothing carried to the next
            self._probe.buf_index = 0
        for m in msgs:
            mtype = m.get_type()
            if mtype not in self._wanted:
                continue
            if mtype == "HEARTBEAT" and getattr(m, "type", None) == MAV_TYPE_GCS:
                continue
            return int(m.get_srcSystem()), int(m.get_srcComponent())
        return None

    def _refuse(self, addr: tuple[Any, ...]) -> None:
        self.counts["foreign_datagrams"] += 1
        if addr in self._foreign or len(self._foreign) >= FOREIGN_NAMED:
            return
        self._foreign.add(addr)
        follows = f"{self.peer[0]}:{self.peer[1]}" if self.peer is not None else "no flight controller yet"
        more = " (further senders are counted only)" if len(self._foreign) == FOREIGN_NAMED else ""
        log.warning("ignoring datagrams from %s:%s, not the flight controller (following %s)%s",
                    *addr[:2], follows, more)  # fmt: skip


def raise_dropped(reason: str) -> Callable[[], None]:
    """A replacement for pymavlink's TCP ``handle_eof`` / ``handle_disconnect`` (which reconnect in place,
    printing on stdout): the drop becomes an error of the reading (or writing) call."""

    def dropped() -> None:
        raise ConnectionResetError(reason)

    return dropped
