"""Shared test helpers."""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterator

import pytest

# Before any test module imports pyarrow (magcomp fleet's results): its jemalloc would start a background
# thread at import, and the replay's observer / in-flight helpers then rightly refuse to fork for the rest
# of the session (magcomp/fleet/store.py sets the same for the product).
os.environ.setdefault("JE_ARROW_MALLOC_CONF", "background_thread:false")


@pytest.fixture(autouse=True)
def restore_magcomp_logging() -> Iterator[None]:
    """The commands, run in-process, point the 'magcomp' logger at the (captured) stderr of their test;
    give every later test its own back (else it logs into a closed stream: "--- Logging error ---")."""
    logger = logging.getLogger("magcomp")
    handlers, level = logger.handlers[:], logger.level
    yield
    logger.handlers[:] = handlers
    logger.setLevel(level)


def split_tlog_records(data: bytes) -> list[bytes]:
    """The records of a clean tlog of MAVLink 2 packets, each an 8-byte big-endian stamp (microseconds since
    the Unix epoch) + one packet (length from its header, + 13 signature bytes if flagged signed)."""
    out, p = [], 0
    while p < len(data):
        n = 8 + 12 + data[p + 9] + (13 if data[p + 10] & 1 else 0)
        out.append(data[p : p + n])
        p += n
    return out


@pytest.fixture(scope="session")
def split_tlog() -> Callable[[bytes], list[bytes]]:
    """:func:`split_tlog_records` as a fixture (test modules do not import conftest). Record ``r``'s stamp
    is ``int.from_bytes(r[:8], "big") * 1e-6`` s, its packet ``r[8:]``."""
    return split_tlog_records
