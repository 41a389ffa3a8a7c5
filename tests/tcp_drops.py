"""A flight controller on TCP that serves one client at a time and drops the link on request, and one run
of `magcomp run` through four quick drops stopped by ^C or SIGTERM (issue 25, item 1): used by
tests/integration/test_shutdown_tcp_drops.py (5 runs) and benchmarks/stop_under_drops.py (50 runs)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from magcomp.adapters.state_store import StateStore
from tests.conftest import split_tlog_records
from tests.waiting import LineReader, wait_for

REPO = Path(__file__).parents[1]
ENV = {**os.environ, "PYTHONPATH": str(REPO)}


class OneClientServer:
    """A flight controller on TCP that accepts one client at a time, streams packets to it and drops the
    connection on request (:meth:`drop`), restarting: its port refuses connections for ``down_s``. It
    counts the connections it served."""

    def __init__(
        self, packets: list[bytes], limit: Callable[[int], int], last: int, down_s: float = 0.5
    ) -> None:
        self.packets = packets
        self.last = last  # the last connection served: one more would wait in the listen queue
        self.down_s = down_s
        self.limit = limit  # connection number -> how many packets to send on it (then stay quiet)
        self.sock = self._listen(0)
        self.port = int(self.sock.getsockname()[1])
        self.served = 0
        self.sent_on: dict[int, int] = {}  # connection number -> packets sent on it
        self._drop = threading.Event()
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    @staticmethod
    def _listen(port: int) -> socket.socket:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(("127.0.0.1", port))
        sock.listen(1)
        sock.settimeout(0.1)
        return sock

    def drop(self) -> None:
        self._drop.set()

    def close(self) -> None:
        self._done.set()
        self._thread.join(timeout=10.0)
        with contextlib.suppress(OSError):
            self.sock.close()

    def _serve(self) -> None:
        i = 0
        while not self._done.is_set():
            try:
                conn, _ = self.sock.accept()
            except OSError:
                continue
            self.served += 1
            n = self.served
            self.sent_on[n] = 0
            self._drop.clear()
            conn.settimeout(1.0)
            try:
                while not self._drop.is_set() and not self._done.is_set():
                    if self.sent_on[n] >= self.limit(n):
                        time.sleep(0.01)
                        continue
                    chunk = self.packets[i % len(self.packets) : i % len(self.packets) + 20]
                    i += len(chunk)
                    conn.sendall(b"".join(chunk))
                    self.sent_on[n] += len(chunk)
                    time.sleep(0.005)
            except OSError:
                pass
            finally:
                conn.close()
            if n == self.last:
                return
            if self._drop.is_set() and not self._done.is_set():  # a restart: the port refuses for a while
                self.sock.close()
                self._done.wait(self.down_s)
                self.sock = self._listen(self.port)


def packets(tmp_path: Path) -> list[bytes]:
    """The MAVLink packets of a 20 s simulated tumble (one compass)."""
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate

    result = simulate(SimConfig(scenario="tumble", duration_s=20.0, seed=11, n_compasses=1))
    write_tlog(result, tmp_path / "f.tlog")
    return [r[8:] for r in split_tlog_records((tmp_path / "f.tlog").read_bytes())]


def drop_after_data(server: OneClientServer, proc: subprocess.Popen[str], n: int) -> None:
    """Drop connection ``n`` once it carried its data; wait for the daemon's next connection."""
    wait_for(lambda: server.sent_on.get(n, 0) >= 60 or proc.poll() is not None, 60.0, f"data on {n}")
    server.drop()
    wait_for(lambda: server.served > n or proc.poll() is not None, 60.0, f"connection {n + 1}")


@dataclass
class StopRun:
    """What one run of :func:`stop_after_drops` gave."""

    code: int | None  # None: it did not stop within the bound (killed)
    stop_s: float  # from the signal to the process's exit
    served: int  # connections the server accepted
    summary: dict[str, Any] | None  # the run's --json summary (None: not written)
    state_saved: bool  # compass 0 of system 1 is in the state store
    stdout: str
    stderr: str


def stop_after_drops(tmp_path: Path, sig: int, bound_s: float) -> StopRun:
    """`magcomp run` against a :class:`OneClientServer` that drops the link four times in quick
    succession; once the fifth connection's data gave a calibration, ``sig`` is sent and the exit timed
    (killed after ``bound_s``)."""
    # the first four connections carry too little for a calibration, the fifth (the last the server
    # accepts) all the rest
    server = OneClientServer(packets(tmp_path), lambda n: 60 if n < 5 else 10**9, last=5)
    cfg = tmp_path / "c.toml"
    cfg.write_text("[link]\nreconnect_s = 0.1\nheartbeat_hz = 20\n"
                   "[calibration]\nmin_samples = 200\ncheck_every = 100\n")  # fmt: skip
    state, summary = tmp_path / "state", tmp_path / "sum.json"
    proc = subprocess.Popen(
        [sys.executable, "-m", "magcomp", "run", "--master", f"tcp:127.0.0.1:{server.port}", "--config",
         str(cfg), "--state-dir", str(state), "--json", str(summary)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=ENV, cwd=REPO, text=True,
    )  # fmt: skip
    assert proc.stdout is not None and proc.stderr is not None
    out, err = LineReader(proc.stdout), LineReader(proc.stderr)
    code: int | None = None
    stop_s = float("nan")
    try:
        wait_for(lambda: server.served >= 1 or proc.poll() is not None, 60.0, "the first connection")
        for k in range(2, 6):  # four quick drops; each time the daemon connects again
            drop_after_data(server, proc, k - 1)
        # after the drops the daemon reads again: the last connection's data reaches the pipeline (the
        # first four carry fewer magnetometer samples than a calibration needs)
        wait_for(lambda: err.has("calibration learned") or proc.poll() is not None, 60.0, "a calibration")
        assert proc.poll() is None, err.join()
        t0 = time.monotonic()
        proc.send_signal(sig)
        with contextlib.suppress(subprocess.TimeoutExpired):
            code = proc.wait(timeout=bound_s)
        stop_s = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        server.close()
    doc = json.loads(summary.read_text()) if summary.exists() else None
    saved = StateStore(state).list_states() if state.exists() else []
    kept = any(st.system_id == 1 and st.mag_index == 0 for _, st in saved)
    return StopRun(code, stop_s, server.served, doc, kept, out.join(), err.join())


SIGNALS = (signal.SIGINT, signal.SIGTERM)
