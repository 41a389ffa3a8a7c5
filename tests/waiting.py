"""Waiting on conditions instead of fixed sleeps (a loaded 2-core machine can be 3x slower than a laptop)."""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import IO, Any

REPO = Path(__file__).resolve().parents[1]


def wait_for(cond: Callable[[], object], timeout_s: float = 60.0, what: str = "condition") -> None:
    """Poll ``cond`` until it is true; fail the test (AssertionError) after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for {what}")
        time.sleep(0.02)


class LineReader:
    """Collects the lines of a process's pipe in a thread, so the test can wait for one of them."""

    def __init__(self, stream: IO[str]) -> None:
        self.lines: list[str] = []
        self._thread = threading.Thread(target=self._read, args=(stream,), daemon=True)
        self._thread.start()

    def _read(self, stream: IO[str]) -> None:
        try:
            for line in stream:
                self.lines.append(line)
        finally:
            stream.close()

    def text(self) -> str:
        return "".join(self.lines)

    def has(self, needle: str) -> bool:
        return any(needle in line for line in list(self.lines))

    def join(self, timeout_s: float = 10.0) -> str:
        self._thread.join(timeout_s)
        return self.text()


def start_magcomp(*args: str) -> tuple[subprocess.Popen[str], LineReader, LineReader]:
    """``python -m magcomp ARGS`` as a child process of this checkout (Rerun's analytics off), with its
    stdout and stderr each read by a :class:`LineReader`."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "RERUN_ANALYTICS": "0"}
    proc = subprocess.Popen([sys.executable, "-m", "magcomp", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, env=env, cwd=REPO, text=True)  # fmt: skip
    assert proc.stdout is not None and proc.stderr is not None
    return proc, LineReader(proc.stdout), LineReader(proc.stderr)


def finish(proc: subprocess.Popen[str], timeout_s: float = 60.0) -> int:
    """Wait for the process to end (kill it after ``timeout_s``, failing the test)."""
    try:
        return proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        raise AssertionError(f"the process did not stop within {timeout_s:.0f} s") from None


def collect_mavlink(sock: Any, stop: threading.Event, out: list[Any], mav: Any,
                    types: tuple[str, ...] | None = None) -> None:  # fmt: skip
    """Until ``stop``: receive datagrams on ``sock`` (a timeout set on it), parse them with ``mav`` (a
    pymavlink MAVLink object) and append the messages (of ``types`` only, when given) to ``out``."""
    while not stop.is_set():
        try:
            data = sock.recv(65536)
        except TimeoutError:
            continue
        for m in mav.parse_buffer(data) or []:
            if types is None or m.get_type() in types:
                out.append(m)


@contextlib.contextmanager
def receiving_mavlink(
    types: tuple[str, ...] | None = None, mav: Any = None
) -> Iterator[tuple[int, list[Any]]]:
    """For the block, a thread collects the MAVLink messages (of ``types`` only, when given) that arrive on a
    :func:`loopback_udp_socket`, parsed with ``mav`` (default: magcomp's dialect, robust parsing); yields the
    socket's port and the list they are appended to. The thread is stopped and the socket closed when the
    block ends, also on failure."""
    if mav is None:
        from magcomp.adapters.dialect import ensure_dialect

        mav = ensure_dialect().MAVLink(None)
        mav.robust_parsing = True
    sock = loopback_udp_socket()
    got: list[Any] = []
    stop = threading.Event()
    rx = threading.Thread(target=collect_mavlink, args=(sock, stop, got, mav, types))
    rx.start()
    try:
        yield sock.getsockname()[1], got
    finally:
        stop.set()
        rx.join()
        sock.close()


def loopback_udp_socket(port: int = 0) -> socket.socket:
    """A UDP socket bound on 127.0.0.1 (``port`` 0: any free one) with a 0.1 s timeout and a 4 MiB receive
    buffer: a listener thread sharing the interpreter can wait for the GIL longer than a default buffer
    (~200 datagrams) lasts on a busy machine."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    sock.bind(("127.0.0.1", port))
    sock.settimeout(0.1)
    return sock


@contextlib.contextmanager
def running_daemon(daemon: Any, join_s: float = 30.0) -> Iterator[threading.Thread]:
    """Run ``daemon`` (a :class:`~magcomp.service.daemon.Daemon`) in a thread for the block, which starts once
    it listens (``connects`` > 0); stopped and joined (up to ``join_s``) when the block ends, also on failure.
    Yields the thread (the caller may assert that it ended)."""
    worker = threading.Thread(target=daemon.run)
    worker.start()
    try:
        wait_for(lambda: daemon.connects > 0 or not worker.is_alive(), 60.0, "the daemon to listen")
        yield worker
    finally:
        daemon.stop()
        worker.join(timeout=join_s)


def send_paced(packets: Sequence[bytes], port: int, every: int = 20, pause_s: float = 0.002) -> None:
    """Send ``packets`` to 127.0.0.1:``port`` over UDP, pausing ``pause_s`` after each ``every`` of them
    (pacing the sender so that loopback does not overrun the receiver's buffer; not waiting for anything)."""
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        for i in range(0, len(packets), every):
            for pkt in packets[i : i + every]:
                tx.sendto(pkt, ("127.0.0.1", port))
            threading.Event().wait(pause_s)
    finally:
        tx.close()
