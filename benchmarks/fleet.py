"""`magcomp fleet` throughput: the same logs on a local Dask cluster of 1 worker, then of 2, in one run.

Prints per run: wall time, logs per minute, CPU seconds per log (measured inside the worker, the whole
per-log analysis: identity scan + diagnose + two-pass replay + rows; split into replay, diagnose and the
rest from the rows' ``replay_cpu_s`` and ``diagnose_cpu_s``), logs per core-hour (3600 / CPU per log), peak
resident memory per worker; then the speed-up from 1 to 2 workers. The cluster's start-up (worker
processes importing magcomp) is timed apart from the analyses.

    .venv/bin/python benchmarks/fleet.py [PATH ...] [--sim N --sim-duration S] [--workers 1 2]

Without PATH: ``--sim N`` simulated ``ordinary`` flights of ``--sim-duration`` seconds (default 4 x 600 s).
"""

from __future__ import annotations

import os

# as magcomp's CLI does, before numpy loads: OpenBLAS threads on small solves only spin on a busy machine
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _simulate(folder: Path, n: int, duration: float) -> list[str]:
    from magcomp.cli import main

    paths = []
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        p = folder / f"sim{i:03d}.tlog"
        rc = main(["simulate", "--scenario", "ordinary", "--duration", str(duration), "--compasses", "2",
                   "--seed", str(100 + i), "--out", str(p)])  # fmt: skip
        assert rc == 0
        paths.append(str(p))
    return paths


def _startup_s(workers: int) -> float:
    from distributed import Client, LocalCluster

    t0 = time.perf_counter()
    with LocalCluster(n_workers=workers, threads_per_worker=1, dashboard_address=None) as c, Client(c) as cl:
        cl.run(lambda: __import__("magcomp.fleet.analyse"))  # what the first task imports
        return time.perf_counter() - t0


def cpu_split(out: Path) -> str:
    """CPU per log split into the two-pass replay, diagnose and the rest (identity scan, rows, the worker's
    own share), from the rows."""
    from magcomp.fleet import store

    rows = store.read_rows(out).to_pylist()
    per_log = {r["sha256"]: r for r in rows if r.get("status") == "ok"}
    if not per_log:
        return "no log analysed ok"
    n = len(per_log)
    cpu = sum(float(r["cpu_s"] or 0.0) for r in per_log.values()) / n
    diag = sum(float(r.get("diagnose_cpu_s") or 0.0) for r in per_log.values()) / n
    replay = sum(float(r.get("replay_cpu_s") or 0.0) for r in per_log.values()) / n
    return (
        f"CPU per log {cpu:.2f} s = replay {replay:.2f} s + diagnose {diag:.2f} s + identity, rows and the "
        f"rest {cpu - replay - diag:.2f} s"
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("paths", nargs="*", help="logs or folders (default: simulated flights)")
    ap.add_argument("--sim", type=int, default=4, help="simulated flights when no PATH (default 4)")
    ap.add_argument("--sim-duration", type=float, default=600.0, help="seconds each (default 600)")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--no-diagnose", action="store_true", help="the replay's rows only (fleet --no-diagnose)")
    args = ap.parse_args()

    from magcomp.fleet import engine
    from magcomp.fleet.discover import find_logs

    with tempfile.TemporaryDirectory(prefix="magcomp-fleet-bench-") as tmp:
        root = Path(tmp)
        if args.paths:
            logs = find_logs(args.paths)
        else:
            t0 = time.perf_counter()
            logs = [Path(p) for p in _simulate(root / "logs", args.sim, args.sim_duration)]
            took = time.perf_counter() - t0
            print(f"simulated {len(logs)} x {args.sim_duration:.0f} s flights in {took:.1f} s")
        size_mb = sum(p.stat().st_size for p in logs) / 1e6
        print(f"{len(logs)} logs, {size_mb:.1f} MB")
        walls: dict[int, float] = {}
        for w in args.workers:
            startup = _startup_s(w) if w > 0 else 0.0  # 0: in this process, no cluster
            out = root / f"out{w}"
            p = engine.plan(logs, out, diagnose=not args.no_diagnose)
            st = engine.run(p.tasks, out, workers=w, progress=False)
            cpu_per_log = st.cpu_s / max(st.analysed, 1)
            walls[w] = st.wall_s - startup
            rss = ", ".join(f"{v:.0f}" for v in st.peak_rss_mb.values())
            print(f"{w} worker(s): {st.analysed} logs ({st.failed} failed) in {st.wall_s:.1f} s wall "
                  f"(cluster start-up ~{startup:.1f} s of it): {60 * st.analysed / st.wall_s:.1f} logs/min; "
                  f"{cpu_per_log:.2f} s CPU per log = {3600 / cpu_per_log:.0f} logs per core-hour; "
                  f"peak RSS per worker {rss} MB")  # fmt: skip
            print("  " + cpu_split(out))
        if len(walls) >= 2:
            a, b = sorted(walls)[:2]
            print(f"speed-up {a} -> {b} workers (start-up excluded): {walls[a] / walls[b]:.2f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
