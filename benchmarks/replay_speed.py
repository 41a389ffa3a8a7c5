"""Replay speed: the whole pipeline over a long tlog vs pymavlink merely parsing the same file.

Baseline: ``mavutil.mavlink_connection(path)`` + ``recv_msg()`` until None (every message decoded,
nothing else done). Measured: ``magcomp.service.replay.replay_log`` (source -> alignment -> Mahony ->
calibration -> observer -> heading; two compasses), and the source alone. Wall times, min and median of
``--repeat`` runs, from one process on this machine.

    .venv/bin/python benchmarks/replay_speed.py [--duration 600] [--repeat 3] [--emit]
    .venv/bin/python benchmarks/replay_speed.py --process [--causal]   # whole `magcomp replay --emit`

``--process``: the acceptance measure of issue 13: ``magcomp replay LOG --emit OUT`` run as its own
process (interpreter start, imports, both passes unless ``--causal``, every MAGCOMP_HEADING written),
against pymavlink's parse-only loop both in this process and as a process of its own. Its CPU time counts
the first pass's child processes (the observers, service/observer_process.py; the in-flight stages,
service/inflight_process.py); the main process's own CPU time and its children's are printed beside it
(the wall time tends to the largest of them when the cores are free).
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
# as the magcomp command line does before numpy is loaded (magcomp/cli.py); pymavlink does not use BLAS
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from magcomp.adapters.config import Config
from magcomp.service.replay import replay_log


def timed(fn: object, repeat: int) -> list[float]:
    out = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()  # type: ignore[operator]
        out.append(time.perf_counter() - t0)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=600.0, help="simulated seconds")
    ap.add_argument("--scenario", default="paper", help="paper (hand rotation) or ordinary (in flight)")
    ap.add_argument("--two-pass", action="store_true", help="time the CLI's default two-pass replay")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--emit", action="store_true", help="also write every MAGCOMP_HEADING to a tlog")
    ap.add_argument(
        "--process",
        action="store_true",
        help="time the whole `magcomp replay --emit` process (two passes unless --causal)",
    )
    ap.add_argument("--causal", action="store_true", help="with --process: one pass (`replay --causal`)")
    args = ap.parse_args()

    from magcomp.adapters.dialect import ensure_dialect
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.adapters.mavlink_source import open_source
    from magcomp.sim import SimConfig, simulate

    ensure_dialect()
    from pymavlink import mavutil

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "long.tlog"
        sim_cfg = SimConfig(scenario=args.scenario, duration_s=args.duration, seed=0)
        n_msgs = write_tlog(simulate(sim_cfg), path)
        size_mb = path.stat().st_size / 1e6

        def parse_only() -> None:
            conn = mavutil.mavlink_connection(str(path), dialect="magcomp")
            while conn.recv_msg() is not None:
                pass
            conn.close()

        def source_only() -> None:
            with open_source(path) as src:
                for _ in src.samples():
                    pass

        if args.process:
            return _whole_process(path, n_msgs, size_mb, parse_only, args)
        emit = str(Path(tmp) / "out.tlog") if args.emit else None
        report: list[object] = []

        def replay() -> None:
            report.append(replay_log(path, Config(), emit=emit, two_pass=args.two_pass))

        # interleaved, so that load from other processes hits all three alike
        base: list[float] = []
        src: list[float] = []
        rep: list[float] = []
        for _ in range(args.repeat):
            base += timed(parse_only, 1)
            src += timed(source_only, 1)
            rep += timed(replay, 1)
    n_est = report[-1].n_estimates  # type: ignore[attr-defined]
    how = "two passes" if args.two_pass else "one pass"
    print(f"tlog: {args.scenario}, {args.duration:g} s simulated, {n_msgs} messages, {size_mb:.1f} MB; "
          f"{n_est} headings; replay {how}")  # fmt: skip
    for name, ts in (("mavutil parse only", base), ("magcomp source only", src), ("magcomp replay", rep)):
        med = statistics.median(ts)
        print(f"{name:<22} min {min(ts):6.2f} s  median {med:6.2f} s  "
              f"{n_msgs / med / 1e3:6.1f} k msgs/s  {args.duration / med:7.0f}x real time")  # fmt: skip
    ratio = statistics.median(rep) / statistics.median(base)
    src_ratio = statistics.median(src) / statistics.median(base)
    print(f"replay / parse-only wall time: median {ratio:.2f}, best {min(rep) / min(base):.2f} "
          f"(target <= 1.0); source alone: {src_ratio:.2f}")  # fmt: skip
    return 0


_REPLAY_SCRIPT = """
import resource, sys
from magcomp.cli import main
rc = main(sys.argv[2:])
r = resource.getrusage(resource.RUSAGE_SELF)
c = resource.getrusage(resource.RUSAGE_CHILDREN)
with open(sys.argv[1], "w") as f:
    f.write(f"{r.ru_utime + r.ru_stime!r} {c.ru_utime + c.ru_stime!r}")
sys.exit(rc)
"""

_PARSE_SCRIPT = """
import sys
from magcomp.adapters.dialect import ensure_dialect
ensure_dialect()
from pymavlink import mavutil
conn = mavutil.mavlink_connection(sys.argv[1], dialect="magcomp")
while conn.recv_msg() is not None:
    pass
"""


def _whole_process(
    path: Path, n_msgs: int, size_mb: float, parse_only: object, args: argparse.Namespace
) -> int:
    """``magcomp replay LOG --emit OUT [--causal]`` as a process vs pymavlink's parse-only loop."""
    root = Path(__file__).resolve().parents[1]
    # PYTHONDONTWRITEBYTECODE (set in some sandboxes) would recompile the generated 1 MB dialect module
    # in every process (0.6 s); an ordinary install caches its bytecode, so the benchmark does too
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env = {
        **env,
        "PYTHONPATH": os.pathsep.join(filter(None, (str(root), os.environ.get("PYTHONPATH")))),
    }
    out = path.with_name("out.tlog")
    self_cpu = path.with_name("self_cpu.txt")
    # `magcomp replay` (magcomp/cli.py main), then the CPU time of that process alone (without the observer
    # process of the first pass, service/observer_process.py): the critical path when a second core is free
    cmd = [sys.executable, "-c", _REPLAY_SCRIPT, str(self_cpu), "replay", str(path), "--emit", str(out)]
    if args.causal:
        cmd.append("--causal")
    parse_cmd = [sys.executable, "-c", _PARSE_SCRIPT, str(path)]

    def run(c: list[str]) -> float:
        """Wall time of the process; its CPU time (user + system, all threads and child processes) added
        to ``cpu``."""
        r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        subprocess.run(c, check=True, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        wall = time.perf_counter() - t0
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu[c is cmd].append(r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime)
        if c is cmd:
            own, kids = self_cpu.read_text().split()
            cpu_main.append(float(own))
            cpu_kids.append(float(kids))
        return wall

    def parse_in_process() -> float:
        c0, t0 = time.process_time(), time.perf_counter()
        parse_only()  # type: ignore[operator]
        cpu_base.append(time.process_time() - c0)
        return time.perf_counter() - t0

    cpu: dict[bool, list[float]] = {False: [], True: []}  # parse process, replay process
    cpu_main: list[float] = []  # the replay process alone
    cpu_kids: list[float] = []  # its child processes together (observers, in-flight stages)
    cpu_base: list[float] = []
    run(parse_cmd)  # once untimed: bytecode written, files in the page cache
    cpu[False].clear()
    base: list[float] = []
    base_proc: list[float] = []
    rep: list[float] = []
    for _ in range(args.repeat):  # interleaved, so that load from other processes hits all alike
        base.append(parse_in_process())
        base_proc.append(run(parse_cmd))
        rep.append(run(cmd))
    how = "one pass (--causal)" if args.causal else "two passes (default)"
    print(
        f"tlog: {args.scenario}, {args.duration:g} s simulated, {n_msgs} messages, {size_mb:.1f} MB; "
        f"magcomp replay --emit, {how}, whole process"
    )
    rows = (
        ("mavutil parse only", base, cpu_base),
        ("mavutil parse, process", base_proc, cpu[False]),
        ("magcomp replay --emit", rep, cpu[True]),
    )
    for name, ts, cs in rows:
        print(f"{name:<24} wall min {min(ts):6.2f} s  median {statistics.median(ts):6.2f} s; "
              f"CPU min {min(cs):6.2f} s  median {statistics.median(cs):6.2f} s")  # fmt: skip
    mmed = statistics.median(cpu_main)
    print(f"{'  its main process alone':<24} {'':<36}CPU min {min(cpu_main):6.2f} s  median {mmed:6.2f} s "
          f"(/ parse-only process {mmed / statistics.median(cpu[False]):.2f}, / in process "
          f"{mmed / statistics.median(cpu_base):.2f}: the critical path when a core is free for each child "
          "and they take less)")  # fmt: skip
    kmed = statistics.median(cpu_kids)
    print(f"{'  its child processes':<24} {'':<36}CPU min {min(cpu_kids):6.2f} s  median {kmed:6.2f} s "
          "(none: the replay runs in one process)")  # fmt: skip
    med, cmed = statistics.median(rep), statistics.median(cpu[True])
    print(
        f"replay --emit process / parse-only (in process): wall median {med / statistics.median(base):.2f}, "
        f"best {min(rep) / min(base):.2f}; CPU median {cmed / statistics.median(cpu_base):.2f}, best "
        f"{min(cpu[True]) / min(cpu_base):.2f}\n"
        f"replay --emit process / parse-only process: wall median {med / statistics.median(base_proc):.2f}, "
        f"best {min(rep) / min(base_proc):.2f}; CPU median {cmed / statistics.median(cpu[False]):.2f}, "
        f"best {min(cpu[True]) / min(cpu[False]):.2f} (target <= 1.0)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
