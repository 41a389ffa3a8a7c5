"""A vehicle's unique hardware id, as the logs and links carry it, reduced to one lower-case hex string.

- MAVLink AUTOPILOT_VERSION: ``uid2`` (up to 18 bytes, the MCU's unique id, zero-padded) when it is not all
  zeros, else ``uid`` (64 bits, its bytes in little-endian order); trailing zero bytes dropped.
- ArduPilot DataFlash: the board-id line its boot writes to MSG, ``NAME XXXXXXXX XXXXXXXX XXXXXXXX``: three
  32-bit words, each printed most significant byte first from the id's little-endian bytes (read back into
  the byte order of ``uid2``, so that a tlog and a .bin of one board name the same vehicle).
- PX4 ULog: the ``sys_uuid`` info string (hex).

The simulator has an identity of its own (:data:`SIM_UID`, ``simulate --uid``).
"""

from __future__ import annotations

import re
from collections.abc import Sequence

#: the simulator's board id: "MAGCOMP-SIM" + 0x01
SIM_UID = b"MAGCOMP-SIM\x01".hex()
_HEX = re.compile(r"^[0-9a-f]{2,64}$")
_BOARD_MSG = re.compile(r"^(\S+) ([0-9A-Fa-f]{8}) ([0-9A-Fa-f]{8}) ([0-9A-Fa-f]{8})\s*$")


def normal_uid(text: str) -> str | None:
    """``text`` as an identity (lower-case hex, even length, not all zeros), or None."""
    t = text.strip().lower().removeprefix("0x")
    if len(t) % 2:
        t = "0" + t
    if not _HEX.match(t) or not t.strip("0"):
        return None
    return t


def uid_from_autopilot_version(uid: int, uid2: Sequence[int] | bytes | None) -> str | None:
    """The identity in an AUTOPILOT_VERSION message (None: the autopilot sent none)."""
    raw = bytes(int(b) & 0xFF for b in (uid2 or ()))
    if not any(raw):
        raw = int(uid).to_bytes(8, "little") if 0 < int(uid) < (1 << 64) else b""
    raw = raw.rstrip(b"\0")
    return raw.hex() if raw else None


def uid_from_board_msg(text: str) -> str | None:
    """The identity in an ArduPilot boot MSG line ``BOARD XXXXXXXX XXXXXXXX XXXXXXXX`` (None otherwise)."""
    m = _BOARD_MSG.match(text.strip())
    if m is None:
        return None
    raw = b"".join(bytes.fromhex(w)[::-1] for w in m.groups()[1:]).rstrip(b"\0")
    return raw.hex() if raw else None


def board_msg(uid: str, board: str = "MAGCOMP-SIM") -> str:
    """The boot MSG line ArduPilot would write for a 12-byte identity (the simulator's DataFlash writer)."""
    raw = bytes.fromhex(uid).ljust(12, b"\0")[:12]
    words = [raw[i : i + 4][::-1].hex().upper() for i in (0, 4, 8)]
    return f"{board} {' '.join(words)}"


def uid2_bytes(uid: str) -> list[int]:
    """An identity as AUTOPILOT_VERSION's ``uid2`` (18 bytes, zero-padded)."""
    return list(bytes.fromhex(uid).ljust(18, b"\0")[:18])


def uid64(uid: str) -> int:
    """An identity's first 8 bytes as AUTOPILOT_VERSION's ``uid`` (little-endian)."""
    return int.from_bytes(bytes.fromhex(uid).ljust(8, b"\0")[:8], "little")
