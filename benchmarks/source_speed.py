"""Source speed: ``open_source(tlog).samples()`` alone vs pymavlink merely parsing the same file.

Baseline: ``mavutil.mavlink_connection(path)`` + ``recv_msg()`` until None (every message decoded, nothing
else done). Measured: the magcomp source (frame walk, CRC, decode of the needed ids, unit conversion,
throttle selection) streaming every sample. Wall times of ``--repeat`` interleaved runs in one process;
msgs/s are file messages (all ids) per second of wall time.

    .venv/bin/python benchmarks/source_speed.py [--duration 600] [--repeat 5] [--profile]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def timed(fn: Callable[[], object]) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--duration", type=float, default=600.0, help="simulated seconds (paper scenario)")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--profile", action="store_true", help="print a cProfile of one source pass")
    args = ap.parse_args()

    from magcomp.adapters.dialect import ensure_dialect
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.adapters.mavlink_source import open_source
    from magcomp.sim import SimConfig, simulate

    ensure_dialect()
    from pymavlink import mavutil

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "long.tlog"
        n_msgs = write_tlog(simulate(SimConfig(scenario="paper", duration_s=args.duration, seed=0)), path)
        size_mb = path.stat().st_size / 1e6
        n_samples = [0]

        def parse_only() -> None:
            conn = mavutil.mavlink_connection(str(path), dialect="magcomp")
            while conn.recv_msg() is not None:
                pass
            conn.close()

        def source_only() -> None:
            n = 0
            with open_source(path) as src:
                for _ in src.samples():
                    n += 1
            n_samples[0] = n

        if args.profile:
            import cProfile
            import pstats

            prof = cProfile.Profile()
            prof.runcall(source_only)
            pstats.Stats(prof).sort_stats("tottime").print_stats(15)

        base: list[float] = []
        src: list[float] = []
        for _ in range(args.repeat):  # interleaved, so that load from other processes hits both alike
            base.append(timed(parse_only))
            src.append(timed(source_only))
    print(f"tlog: {args.duration:g} s simulated, {n_msgs} messages, {size_mb:.1f} MB; {n_samples[0]} samples")
    for name, ts in (("mavutil parse only", base), ("magcomp source only", src)):
        med = statistics.median(ts)
        print(f"{name:<21} min {min(ts):6.3f} s  median {med:6.3f} s  {n_msgs / med / 1e3:7.1f} k msgs/s")
    print(f"source / parse-only wall time: median {statistics.median(src) / statistics.median(base):.3f}, "
          f"best {min(src) / min(base):.3f}")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
