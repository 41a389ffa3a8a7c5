"""Peak memory (resident set size) of the commands on a long simulated log (issue 12: bounded memory).

Writes a simulated flight of ``--hours`` (default 1; the issue's figures were for 4 h) as a tlog, then runs
each command in its own process and reads that process's peak RSS (``ru_maxrss`` of a wrapper's only
child). Not a test: run by hand, numbers go into docs/README.

    .venv/bin/python benchmarks/memory.py [--hours 1] [--keep DIR] [--log TLOG] [--only NAME]

Measured 2026-11-23 on a 2-core machine shared with other jobs (so wall times are long and noisy; peak RSS
is not), the 4 h log being the 1 h flight 4 times (119 MiB tlog); before = the previous checkout (fa0ad10),
after = streamed reading (1 MiB chunks) + columnar ``load_log`` (adapters/columns.py) + windows cut while
reading:

    peak RSS, MiB             10 min      1 h before -> after      4 h before -> after
    replay                        51           181 -> 51              164 -> 51
    replay --rerun save=         159           255 -> 167             ~344 -> 183
    fit --start/--end (1 h)      120           457 -> 172            1697 -> 171
    diagnose                     157           522 -> 260             1764 -> 601

replay is flat in the log's length (4 h = 10 min). What is left in diagnose grows with the log through the
diagnosis itself: the full-rate gyro integrated for the attitude and the 100 Hz drive grid of each compass
(diagnosis/engine.py), not the loading. The 4 h "replay --rerun save=" before figure is an earlier session's
(that run was stopped here to save time; it had reached 238 MiB). ``--log`` reuses a log written with
``--keep``; ``--only NAME`` (repeatable) runs only the commands whose name starts with NAME.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

_WRAPPER = """
import resource, subprocess, sys, json
rc = subprocess.run(sys.argv[1:], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL).returncode
print(json.dumps({"rc": rc, "peak_kib": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss}))
"""


def peak_mib(cmd: list[str]) -> tuple[float, float, int]:
    """(peak RSS MiB, wall s, exit code) of one command in a fresh process."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", _WRAPPER, *cmd], capture_output=True, text=True, env=env,
                         check=True).stdout  # fmt: skip
    wall = time.perf_counter() - t0
    doc = json.loads(out.strip().splitlines()[-1])
    return doc["peak_kib"] / 1024.0, wall, int(doc["rc"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=1.0)
    ap.add_argument("--keep", metavar="DIR", help="write the log (and outputs) here instead of a temp dir")
    ap.add_argument("--log", metavar="TLOG", help="reuse this log (from an earlier --keep run) for --hours")
    ap.add_argument("--only", metavar="NAME", action="append", help="only the commands starting with NAME")
    args = ap.parse_args()
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate

    d = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="magcomp-mem-"))
    d.mkdir(parents=True, exist_ok=True)
    log = Path(args.log) if args.log else d / "long.tlog"
    t0 = time.perf_counter()
    # the simulator goes up to 1 h: longer logs are that hour repeated (each copy a reboot of the autopilot)
    one_h = min(args.hours, 1.0)
    if not args.log:
        write_tlog(simulate(SimConfig(scenario="flight", duration_s=one_h * 3600.0, seed=1)), log)
        copies = max(1, round(args.hours / one_h))
        if copies > 1:
            data = log.read_bytes()
            with log.open("ab") as f:
                for _ in range(copies - 1):
                    f.write(data)
    print(f"{log}: {log.stat().st_size / 2**20:.0f} MiB, {args.hours:g} h simulated in "
          f"{time.perf_counter() - t0:.0f} s")  # fmt: skip
    py = [sys.executable, "-m", "magcomp"]
    cases = {
        "replay": [*py, "replay", str(log)],
        "replay --rerun save=": [*py, "replay", str(log), "--rerun", f"save={d / 'r.rrd'}"],
        # a 1 h window (the case: 200 Monte-Carlo refits of it held 3.4 GiB)
        "fit --start/--end": [*py, "fit", str(log), "--monte-carlo", "200", "--start", "0",
                              "--end", str(one_h * 3600.0 + 60.0)],
        "diagnose": [*py, "diagnose", str(log)],
    }
    for name, cmd in cases.items():
        if args.only and not any(name.startswith(o) for o in args.only):
            continue
        mib, wall, rc = peak_mib(cmd)
        print(f"{name:22s} peak RSS {mib:7.0f} MiB   wall {wall:6.1f} s   exit {rc}")


if __name__ == "__main__":
    main()
