"""Real MAVProxy (the package index's MAVProxy, a test dependency) with ``module load magcomp``, headless:
the simulator plays the paper's flight as the flight controller into MAVProxy's master link, MAVProxy's
``--out`` feeds a listener that decodes MAGCOMP_HEADING (magcomp's dialect) and NAMED_VALUE_FLOAT. The
corrected heading read back must follow the simulated truth once the motor runs, where the uncorrected
heading does not; the headings also go back to the flight controller on the master link.

Skipped, with the reason, where MAVProxy is not installed (``pip install -e '.[dev]'`` installs it)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from magcomp.service.demo import free_udp_port, truth_at
from tests.waiting import LineReader, collect_mavlink, loopback_udp_socket, wait_for

pytest.importorskip("MAVProxy", reason="MAVProxy is not installed (pip install MAVProxy; in the dev extra)")


def _mavproxy_script() -> Path | None:
    script = Path(sys.executable).parent / "mavproxy.py"
    return script if script.is_file() else None


def _listen(sock: socket.socket, stop: threading.Event, out: list[Any]) -> None:
    from magcomp.adapters.dialect import ensure_dialect

    mav = ensure_dialect().MAVLink(None)
    mav.robust_parsing = True
    collect_mavlink(sock, stop, out, mav, ("MAGCOMP_HEADING", "NAMED_VALUE_FLOAT"))


def _stop_group(proc: subprocess.Popen[str]) -> None:
    for sig in (signal.SIGINT, signal.SIGKILL):
        if proc.poll() is not None:
            return
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            continue


class _Quiet:
    """True once ``count()`` reached ``target`` or has not grown for ``quiet_s`` (the stream is through)."""

    def __init__(self, count: Callable[[], int], target: int, quiet_s: float = 2.0) -> None:
        self.count, self.target, self.quiet_s = count, target, quiet_s
        self.last, self.since = -1, time.monotonic()

    def __call__(self) -> bool:
        n = self.count()
        if n != self.last:
            self.last, self.since = n, time.monotonic()
        return n >= self.target or time.monotonic() - self.since > self.quiet_s


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + 180.0) % 360.0 - 180.0


@pytest.mark.slow
def test_real_mavproxy_with_module_load_magcomp_publishes_corrected_headings(tmp_path: Path) -> None:
    from magcomp.adapters.mavlink_emit import stream_to_link
    from magcomp.sim import SimConfig, simulate

    script = _mavproxy_script()
    if script is None:
        pytest.skip(f"MAVProxy is importable but mavproxy.py is not beside {sys.executable}")
    result = simulate(SimConfig(scenario="paper", duration_s=90.0, seed=0))

    sock = loopback_udp_socket()
    got: list[Any] = []
    stop = threading.Event()
    rx = threading.Thread(target=_listen, args=(sock, stop, got), daemon=True)
    rx.start()

    port = free_udp_port()
    env = dict(os.environ, MAGCOMP_STATE_DIR=str(tmp_path / "state"), PYTHONUNBUFFERED="1")
    env.pop("MAGCOMP_CONFIG", None)
    argv = [sys.executable, str(script), "--master", f"udpin:127.0.0.1:{port}",
            "--out", f"udpout:127.0.0.1:{sock.getsockname()[1]}", "--daemon", "--no-state",
            "--default-modules", "", "--cmd", "module load magcomp"]  # fmt: skip
    proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, cwd=tmp_path, env=env, start_new_session=True)  # fmt: skip
    assert proc.stdout is not None
    out = LineReader(proc.stdout)
    try:

        def loaded() -> bool:
            return out.has("Loaded module magcomp") or out.has("Failed to load") or proc.poll() is not None

        wait_for(loaded, 60.0, "MAVProxy to load the magcomp module")
        assert out.has("Loaded module magcomp"), out.text()[-3000:]
        link = stream_to_link(result, f"udpout:127.0.0.1:{port}", speed=10.0)
        n_mag = int(result.samples.t_s.shape[0]) * int(result.samples.mag_mgauss.shape[0])

        quiet = _Quiet(lambda: sum(m.get_type() == "MAGCOMP_HEADING" for m in got), n_mag)
        wait_for(quiet, 120.0, "MAGCOMP_HEADING on MAVProxy's output")
    finally:
        _stop_group(proc)
        stop.set()
        rx.join(timeout=5)
        sock.close()
    text = out.text()
    assert "Failed to load" not in text and "Traceback" not in text, text[-3000:]

    headings = [m for m in got if m.get_type() == "MAGCOMP_HEADING"]
    assert {m.mag_index for m in headings} == {0, 1}
    assert len(headings) >= 0.5 * n_mag, (len(headings), n_mag)  # 10x real time on a loaded machine
    assert all(m.get_srcComponent() == 191 for m in headings)
    named = {m.name for m in got if m.get_type() == "NAMED_VALUE_FLOAT"}
    assert {"MC_HDG0", "MC_HDG1", "MC_THETA0", "MC_STAT0"} <= named, named
    assert link.received.get("MAGCOMP_HEADING", 0) > 0.5 * n_mag  # and back to the flight controller

    # physics: once the motor runs (the paper's pan, ramp and step), the corrected heading follows the truth
    h0 = [m for m in headings if m.mag_index == 0]
    t = np.array([m.time_boot_ms for m in h0], dtype=float) / 1000.0
    _, matched, idx, truth = truth_at(result, t)
    names = result.motion.segment_names
    moving = [i for i, nm in enumerate(names) if nm in ("pan", "ramp", "step")]
    sel = matched & np.isin(result.motion.segment[idx], moving)
    assert sel.sum() > 1000, sel.sum()
    err = _wrap(np.array([m.heading for m in h0])[sel] - truth[sel])
    err_raw = _wrap(np.array([m.heading_raw for m in h0])[sel] - truth[sel])
    rms, rms_raw = float(np.sqrt(np.mean(err**2))), float(np.sqrt(np.mean(err_raw**2)))
    print(f"MAVProxy: {len(headings)}/{n_mag} headings; motor on: {rms:.2f} deg rms, raw {rms_raw:.2f}")
    assert rms < 1.5, (rms, rms_raw)
    assert rms < 0.25 * rms_raw, (rms, rms_raw)
