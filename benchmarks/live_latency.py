"""Live latency and throughput of `magcomp run` over loopback UDP.

A fake flight controller (this process) plays a simulated flight (the paper scenario, one compass,
RAW_IMU at 50 Hz plus the usual ArduPilot stream) to `magcomp run --master udpin:...` (a separate
process), paced at ``speed`` x real time, so the magnetometer input rate is 50 x speed samples/s; a
receiver thread decodes the MAGCOMP_HEADING the daemon publishes on ``--out``. Latency = time the
MAGCOMP_HEADING was received - time its RAW_IMU was sent (both loopback hops included), matched on
time_boot_ms; the daemon's own figure (sample parsed -> written to every sink) comes from its --json.

    .venv/bin/python benchmarks/live_latency.py [--speeds 1 20 100 200 400]
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def receiver(port: int, out_path: str, ready: Any, stop: Any) -> None:
    """A separate process (no GIL shared with the sender): time of arrival of each MAGCOMP_HEADING."""
    from magcomp.adapters.dialect import ensure_dialect

    mod = ensure_dialect()
    mav = mod.MAVLink(None)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    sock.bind(("127.0.0.1", port))
    sock.settimeout(0.05)
    gc.collect()
    gc.freeze()  # a full collection over pymavlink's dialect would stall this receiver ~40 ms
    ready.set()
    rx: dict[int, float] = {}
    while not stop.is_set():
        try:
            data = sock.recv(65536)
        except TimeoutError:
            continue
        now = time.monotonic()
        for m in mav.parse_buffer(data) or []:
            if m.get_type() == "MAGCOMP_HEADING":
                rx.setdefault(m.time_boot_ms, now)
    sock.close()
    Path(out_path).write_text(json.dumps(rx))


def run_once(packets: list[tuple[float, bytes, int | None]], speed: float, tmp: Path) -> dict[str, float]:
    import multiprocessing as mp

    master, out = free_port(), free_port()
    ctx = mp.get_context("spawn")
    ready, stop = ctx.Event(), ctx.Event()
    rx_file = tmp / f"rx-{speed:g}.json"
    rx = ctx.Process(target=receiver, args=(out, str(rx_file), ready, stop))
    rx.start()
    summary = tmp / f"run-{speed:g}.json"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "magcomp", "run", "--master", f"udpin:127.0.0.1:{master}", "--out",
         f"udpout:127.0.0.1:{out}", "--state-dir", str(tmp / f"state-{speed:g}"), "--json", str(summary)],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env, cwd=REPO,
    )  # fmt: skip
    ready.wait(30)
    time.sleep(2.0)  # interpreter start, imports, socket bound
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx_times: dict[int, float] = {}
    gc.collect()
    gc.freeze()
    t0_msg = packets[0][0]
    wall0 = time.monotonic()
    for t_msg, pkt, mag_ms in packets:
        due = wall0 + (t_msg - t0_msg) / speed
        while True:
            now = time.monotonic()
            if now >= due:
                break
            if due - now > 0.002:
                time.sleep(due - now - 0.001)
        # stamped before the send: after it, a sender descheduled between the two made latencies near 0 on a
        # loaded machine (1 kHz p50 0.01 ms)
        t_tx = time.monotonic()
        tx.sendto(pkt, ("127.0.0.1", master))
        if mag_ms is not None:
            tx_times[mag_ms] = t_tx
    send_s = time.monotonic() - wall0
    time.sleep(3.0)  # let the daemon drain what it has queued
    proc.terminate()
    proc.wait(timeout=20)
    stop.set()
    rx.join(timeout=20)
    tx.close()
    rx_times = {int(k): v for k, v in json.loads(rx_file.read_text()).items()}
    lat = np.array([rx_times[k] - tx_times[k] for k in tx_times if k in rx_times]) * 1e3
    inner = json.loads(summary.read_text()).get("latency_ms", {}) if summary.exists() else {}
    return {
        "rate": len(tx_times) / send_s,
        "sent": float(len(tx_times)),
        "received": float(sum(1 for k in tx_times if k in rx_times)),
        "p50": float(np.percentile(lat, 50)) if lat.size else float("nan"),
        "p99": float(np.percentile(lat, 99)) if lat.size else float("nan"),
        "inner_p50": float(inner.get("p50", float("nan"))),
        "inner_p99": float(inner.get("p99", float("nan"))),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--speeds", type=float, nargs="+", default=[1.0, 20.0, 100.0, 200.0, 400.0])
    ap.add_argument("--duration", type=float, default=133.0)
    args = ap.parse_args()

    from magcomp.adapters.dialect import ensure_dialect
    from magcomp.adapters.mavlink_emit import encode_stream
    from magcomp.sim import SimConfig, simulate

    mod = ensure_dialect()
    result = simulate(SimConfig(scenario="paper", duration_s=args.duration, seed=0, n_compasses=1))
    mav = mod.MAVLink(None)
    packets: list[tuple[float, bytes, int | None]] = []
    for t, pkt in encode_stream(result):
        m = mav.decode(bytearray(pkt))
        mag_ms = round(m.time_usec / 1000) if m.get_type() == "RAW_IMU" else None
        packets.append((t, pkt, mag_ms))
    print(f"stream: {len(packets)} packets over {args.duration:g} s, "
          f"{sum(p[2] is not None for p in packets)} magnetometer samples (RAW_IMU, 50 Hz)")  # fmt: skip
    print("input mag/s   sent  received  loss   latency p50 / p99 ms (end to end)   daemon p50 / p99 ms")
    with tempfile.TemporaryDirectory() as tmp:
        for speed in args.speeds:
            # at real time, play only the first 30 s: the latency does not change with the scenario
            pk = packets if speed > 1 else [p for p in packets if p[0] - packets[0][0] <= 30.0]
            r = run_once(pk, speed, Path(tmp))
            loss = 1.0 - r["received"] / r["sent"]
            print(f"{r['rate']:9.0f}  {r['sent']:6.0f}  {r['received']:8.0f}  {100 * loss:4.1f}%   "
                  f"{r['p50']:7.2f} / {r['p99']:7.2f}                     "
                  f"{r['inner_p50']:5.2f} / {r['inner_p99']:5.2f}")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
