"""Issue 25's stop measure: `magcomp run` against a TCP flight controller that serves one client at a
time and drops the link four times in quick succession, then ^C (SIGINT) or SIGTERM, alternately; N runs
(default 50). Per run: the exit code, the time from the signal to the exit, the summary written, the
state saved, the connections the server served. Prints the counts and the stop times (the bound is 3 s).

    .venv/bin/python benchmarks/stop_under_drops.py [--runs 50]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

BOUND_S = 3.0


def main() -> int:
    from tests.tcp_drops import SIGNALS, stop_after_drops

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=50)
    ap.add_argument("--kill-after", type=float, default=30.0, help="kill a run not stopped after this (s)")
    args = ap.parse_args()
    times, ok = [], 0
    for i in range(args.runs):
        with tempfile.TemporaryDirectory() as d:
            sig = SIGNALS[i % 2]
            try:
                r = stop_after_drops(Path(d), sig, args.kill_after)
            except AssertionError as exc:  # the run did not reach the stop (no connection, no calibration)
                print(f"run {i + 1}: did not reach the stop: {exc}", flush=True)
                continue
            good = (r.code == 0 and r.summary is not None and r.state_saved and "Traceback" not in r.stderr
                    and r.stop_s <= BOUND_S)  # fmt: skip
            ok += good
            times.append(r.stop_s)
            print(f"run {i + 1} ({sig.name}): exit {r.code} after {r.stop_s:.2f} s, summary "
                  f"{'written' if r.summary is not None else 'MISSING'}, state "
                  f"{'saved' if r.state_saved else 'MISSING'}, connections {r.served}",
                  flush=True)  # fmt: skip
    if times:
        q = sorted(times)
        print(f"{ok}/{args.runs} runs exited 0 within {BOUND_S:.0f} s with the summary and the state saved; "
              f"stop time median {statistics.median(q):.2f} s, max {q[-1]:.2f} s")  # fmt: skip
    return 0 if ok == args.runs else 1


if __name__ == "__main__":
    raise SystemExit(main())
