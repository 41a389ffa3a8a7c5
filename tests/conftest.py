"""Shared test helpers."""

from __future__ import annotations

import logging
import os
import signal
import threading
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


_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@pytest.fixture(autouse=True)
def restore_signal_state(request: pytest.FixtureRequest) -> Iterator[None]:
    """The main thread's signal mask and the SIGINT / SIGTERM handlers as they were before the test: a
    subprocess inherits a blocked or ignored signal across exec, so one test that leaves SIGINT blocked
    makes every later test that stops a child with a signal fail. What a test changed is restored and
    named in the test's output (where it is seen)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, set())
    handlers = {s: signal.getsignal(s) for s in _SIGNALS}
    yield
    now_mask = signal.pthread_sigmask(signal.SIG_BLOCK, set())
    if now_mask != mask:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        print(f"{request.node.nodeid} left the signal mask {sorted(now_mask)}; restored")
    for s, h in handlers.items():
        if signal.getsignal(s) is not h and h is not None:
            signal.signal(s, h)
            print(f"{request.node.nodeid} left the {s.name} handler changed; restored")


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
