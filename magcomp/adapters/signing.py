"""MAVLink 2 signing of a live link (pymavlink's implementation): a key file, the signing of what magcomp
sends (MAGCOMP_HEADING, HEARTBEAT) and, when a key is set, the refusal of what arrives unsigned or with a
bad signature.

Key file: 32 raw bytes, or 64 hex digits, or a passphrase on one line whose SHA-256 is the key (the
convention of MAVProxy's ``signing setup`` and of Mission Planner).
"""

from __future__ import annotations

import hashlib
import os
import time
from pathlib import Path
from typing import Any

from magcomp.errors import InputError

#: MAVLink signing timestamps count 10 us units from 2015-01-01 00:00 UTC
SIGNING_EPOCH_UNIX_S = 1420070400
#: the link id magcomp signs with
LINK_ID = 0


def read_signing_key(path: str | os.PathLike[str]) -> bytes:
    """The 32-byte secret key in ``path`` (see the module docstring); a one-line error otherwise."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise InputError(f"--signing-key {p}: cannot read ({exc.strerror or exc})") from None
    if len(raw) == 32:
        return raw
    try:
        text = raw.decode("utf-8").strip()
    except UnicodeDecodeError:
        raise InputError(f"--signing-key {p}: expected 32 bytes, 64 hex digits or a passphrase") from None
    if not text:
        raise InputError(f"--signing-key {p}: the file is empty")
    if len(text) == 64:
        try:
            return bytes.fromhex(text)
        except ValueError:
            pass
    return hashlib.sha256(text.encode("utf-8")).digest()


def signing_timestamp() -> int:
    """Now, as a MAVLink signing timestamp (10 us units since 2015-01-01)."""
    return int((max(time.time(), SIGNING_EPOCH_UNIX_S) - SIGNING_EPOCH_UNIX_S) * 100_000)


def sign_outgoing(mav: Any, key: bytes) -> None:
    """Sign every frame ``mav`` (a pymavlink MAVLink object) packs from now on."""
    mav.signing.secret_key = key
    mav.signing.sign_outgoing = True
    mav.signing.link_id = LINK_ID
    mav.signing.timestamp = max(int(mav.signing.timestamp), signing_timestamp())


def require_signed(mav: Any, key: bytes) -> None:
    """Make ``mav`` (a pymavlink MAVLink parser) accept only frames signed with ``key``: an unsigned or
    badly signed one becomes BAD_DATA ("Invalid signature")."""
    mav.signing.secret_key = key
    mav.signing.sign_outgoing = False
    mav.signing.allow_unsigned_callback = None
