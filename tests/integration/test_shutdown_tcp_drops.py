"""Issue 25 (1): a TCP link that drops again and again must never make `magcomp run` unstoppable. A
flight controller that serves one client at a time drops the link several times in quick succession;
every ^C / SIGTERM then stops the run with the state saved and the summary printed, and after each drop
the daemon reads from the new connection again."""

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
from pathlib import Path

import pytest

from magcomp.adapters.state_store import StateStore
from tests.waiting import LineReader, finish, wait_for

REPO = Path(__file__).parents[2]
ENV = {**os.environ, "PYTHONPATH": str(REPO)}
#: how long a stopped run may take to exit before the test calls it unstoppable (the issue's bound is
#: 3 s; the test allows for a loaded machine: before the fix the run never exited at all)
STOP_BOUND_S = 20.0


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


def _packets(tmp_path: Path, split_tlog: Callable[[bytes], list[bytes]]) -> list[bytes]:
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate

    result = simulate(SimConfig(scenario="tumble", duration_s=20.0, seed=11, n_compasses=1))
    write_tlog(result, tmp_path / "f.tlog")
    return [r[8:] for r in split_tlog((tmp_path / "f.tlog").read_bytes())]


def _drop_after_data(server: OneClientServer, proc: subprocess.Popen[str], n: int) -> None:
    """Drop connection ``n`` once it carried its data; wait for the daemon's next connection."""
    wait_for(lambda: server.sent_on.get(n, 0) >= 60 or proc.poll() is not None, 60.0, f"data on {n}")
    server.drop()
    wait_for(lambda: server.served > n or proc.poll() is not None, 60.0, f"connection {n + 1}")


@pytest.mark.slow
@pytest.mark.parametrize("run", range(5))
def test_run_stops_after_quick_tcp_drops_with_state_and_summary(
    tmp_path: Path, split_tlog: Callable[[bytes], list[bytes]], run: int
) -> None:
    # the first four connections carry too little for a calibration, the fifth (the last the server
    # accepts) all the rest
    server = OneClientServer(_packets(tmp_path, split_tlog), lambda n: 60 if n < 5 else 10**9, last=5)
    cfg = tmp_path / "c.toml"
    cfg.write_text("[link]\nreconnect_s = 0.1\nheartbeat_hz = 20\n"
                   "[calibration]\nmin_samples = 200\ncheck_every = 100\n")
    state, summary = tmp_path / "state", tmp_path / "sum.json"
    proc = subprocess.Popen(
        [sys.executable, "-m", "magcomp", "run", "--master", f"tcp:127.0.0.1:{server.port}", "--config",
         str(cfg), "--state-dir", str(state), "--json", str(summary)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=ENV, cwd=REPO, text=True,
    )  # fmt: skip
    assert proc.stdout is not None and proc.stderr is not None
    out, err = LineReader(proc.stdout), LineReader(proc.stderr)
    try:
        wait_for(lambda: server.served >= 1 or proc.poll() is not None, 60.0, "the first connection")
        for k in range(2, 6):  # four quick drops; each time the daemon connects again
            _drop_after_data(server, proc, k - 1)
        # after the drops the daemon reads again: the last connection's data reaches the pipeline (the
        # first four carry fewer magnetometer samples than a calibration needs)
        wait_for(lambda: err.has("calibration learned") or proc.poll() is not None, 60.0, "a calibration")
        assert proc.poll() is None, err.join()
        proc.send_signal(signal.SIGINT if run % 2 == 0 else signal.SIGTERM)
        code = finish(proc, STOP_BOUND_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        server.close()
    text = err.join()
    assert code == 0, text
    assert "Traceback" not in text
    doc = json.loads(summary.read_text())
    # every connection the server saw was one the daemon opened and read: none opened behind its back
    # by a writing thread (pymavlink's in-place reconnect, racing the reader)
    assert doc["connects"] == server.served == 5, (doc["connects"], server.served)
    assert doc["counts"]["mag"] > 0
    assert "compass 0:" in out.join()
    # the state saved for compass 0 of system 1, whatever identity the simulated board gave
    saved = StateStore(state).list_states()
    assert any(st.system_id == 1 and st.mag_index == 0 for _, st in saved), saved
