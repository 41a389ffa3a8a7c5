"""Replay speed (issue 24's acceptance): whole-process CPU of ``magcomp replay LOG --emit OUT`` against
pymavlink's parse-only process on the same file, side by side in one run.

For each scenario (default: a simulated 10 min ordinary flight, calibration and theta learned in flight, and
the paper log, a hand rotation then flight), three processes on the same tlog, interleaved ``--repeat``
times so that load from other processes hits all alike:

* pymavlink parse-only: ``mavutil.mavlink_connection(path)`` + ``recv_msg()`` until None (every message
  decoded, nothing else done);
* ``magcomp replay LOG --emit OUT`` (two passes, the default: interpreter start, imports, both passes, every
  MAGCOMP_HEADING written);
* ``magcomp replay LOG --emit OUT --causal`` (one pass, what the live daemon would have published).

CPU is user + system time of the process and of any process it started (RUSAGE_CHILDREN around it); the
replay reports its own CPU and its children's apart, and the table shows the children's (0: one process,
no forks). Printed: CPU medians, the ratios to the parse-only process and the targets (two passes <= 1.5x on
the ordinary flight and <= 1.0x on the paper log, ``--causal`` <= 2.0x), and wall medians; below the table,
each kind's CPU from its fastest to its slowest run (the scatter a median is taken over).

``--compare ROOT``: the replays of another checkout of magcomp (e.g. ``/work/main``, or a commit exported with
``git archive``) run in the same interleaving, their ratios printed beside: the load of other processes
moves a ratio by several percent between runs minutes apart (it slows this process's caches and cores, not
only its wall time), so a change is measured against its base side by side.

    .venv/bin/python benchmarks/replay_speed.py [--duration 600] [--repeat 3] [--scenario ordinary paper]
        [--compare ROOT]
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

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

#: issue 24's targets: (two passes, --causal) CPU / the parse-only process's, per scenario
TARGETS = {"ordinary": (1.5, 2.0), "paper": (1.0, 2.0)}
#: the kinds of the compared checkout's replays end in this
COMPARED = " (compare)"

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


def _env(root: Path = ROOT) -> dict[str, str]:
    # PYTHONDONTWRITEBYTECODE (set in some sandboxes) would recompile the generated 1 MB dialect module in
    # every process (0.6 s); an ordinary install caches its bytecode, so the benchmark does too. One BLAS
    # thread, as the magcomp command line sets before numpy loads (magcomp/cli.py).
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, (str(root), os.environ.get("PYTHONPATH"))))
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    return env


def _replays(tmp: Path, path: Path, tag: str = "") -> dict[str, list[str]]:
    """The two replay commands (two passes, ``--causal``) of ``path``, their kinds suffixed by ``tag``."""
    out = {}
    for kind, extra in (("two-pass", []), ("causal", ["--causal"])):
        k = kind + tag
        out[k] = [sys.executable, "-c", _REPLAY_SCRIPT, str(tmp / f"{k}.cpu"), "replay", str(path),
                  "--emit", str(tmp / f"{k}.tlog"), *extra]  # fmt: skip
    return out


def _run(cmd: list[str], env: dict[str, str], root: Path = ROOT) -> tuple[float, float]:
    """(CPU of the process and its children, wall) of one run, in checkout ``root``: ``python -c`` puts the
    working directory first on sys.path, so a process started elsewhere in a checkout would import that
    checkout's magcomp, not PYTHONPATH's."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, env=env, cwd=root, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime, wall


def measure(
    scenario: str, duration_s: float, repeat: int, tmp: Path, compare: Path | None = None
) -> dict[str, object]:
    """The three processes on one simulated tlog (with ``compare``, that checkout's two replays too, kinds
    ending in " (compare)"), interleaved; CPU and wall per kind, the replays' own children's CPU."""
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate

    path = tmp / f"{scenario}.tlog"
    n_msgs = write_tlog(simulate(SimConfig(scenario=scenario, duration_s=duration_s, seed=0)), path)
    parse = [sys.executable, "-c", _PARSE_SCRIPT, str(path)]
    kinds = {"parse": parse, **_replays(tmp, path)}
    envs = dict.fromkeys(kinds, _env())
    roots = dict.fromkeys(kinds, ROOT)
    if compare is not None:
        other = _replays(tmp, path, COMPARED)
        kinds.update(other)
        envs.update(dict.fromkeys(other, _env(compare)))
        roots.update(dict.fromkeys(other, compare))
    _run(parse, envs["parse"])  # once untimed: bytecode written, the file in the page cache
    if compare is not None:
        _run(parse, _env(compare), compare)  # the other checkout's generated dialect module too
    cpu: dict[str, list[float]] = {k: [] for k in kinds}
    wall: dict[str, list[float]] = {k: [] for k in kinds}
    kids: dict[str, list[float]] = {k: [] for k in kinds if k != "parse"}
    for _ in range(repeat):
        for kind, cmd in kinds.items():
            c, w = _run(cmd, envs[kind], roots[kind])
            cpu[kind].append(c)
            wall[kind].append(w)
            if kind in kids:
                kids[kind].append(float((tmp / f"{kind}.cpu").read_text().split()[1]))
    return {"messages": n_msgs, "cpu": cpu, "wall": wall, "kids": kids}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=600.0, help="simulated seconds")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--scenario", nargs="+", default=["ordinary", "paper"], choices=sorted(TARGETS))
    ap.add_argument("--compare", type=Path, default=None, metavar="ROOT",
                    help="another checkout whose replays run interleaved with these (its ratios beside)")
    args = ap.parse_args()
    if args.compare is not None:
        args.compare = args.compare.resolve()
    if args.compare is not None and not (args.compare / "magcomp" / "__init__.py").is_file():
        ap.error(f"--compare {args.compare}: not a checkout of magcomp (no magcomp/__init__.py)")
    med = statistics.median
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for scenario in args.scenario:
            rows.append((scenario, measure(scenario, args.duration, args.repeat, Path(tmp), args.compare)))
    print(f"magcomp replay --emit, whole process, {args.duration:g} s simulated; CPU = user + system of the "
          f"process and its children, median of {args.repeat} (wall median in brackets)")  # fmt: skip
    if args.compare is not None:
        print(f"{COMPARED.strip()}: the replays of {args.compare}, interleaved with these")
    w = 9 + (len(COMPARED) if args.compare is not None else 0)
    print(f"{'scenario':<{w}} {'messages':>8}  {'parse-only':>15}  {'replay (two passes)':>26}  "
          f"{'replay --causal':>26}  {'forks':>5}")  # fmt: skip
    for scenario, m in rows:
        cpu, wall, kids = m["cpu"], m["wall"], m["kids"]
        assert isinstance(cpu, dict) and isinstance(wall, dict) and isinstance(kids, dict)
        base = med(cpu["parse"])
        for tag in ("", COMPARED) if args.compare is not None else ("",):
            cells = [f"{base:5.2f} s [{med(wall['parse']):5.2f}]"]
            for kind, target in zip(("two-pass", "causal"), TARGETS[scenario], strict=True):
                c = med(cpu[kind + tag])
                cells.append(f"{c:5.2f} s {c / base:4.2f}x (<= {target:.1f}) [{med(wall[kind + tag]):5.2f}]")
            forked = max(max(v) for k, v in kids.items() if k.endswith(COMPARED) == bool(tag))
            name = scenario + tag
            print(f"{name:<{w}} {m['messages']:>8}  {cells[0]:>15}  {cells[1]:>26}  {cells[2]:>26}  "
                  f"{'none' if forked == 0.0 else f'{forked:.2f} s':>5}")  # fmt: skip
    print("CPU of each run, fastest to slowest (s):")
    for scenario, m in rows:
        cpu = m["cpu"]
        assert isinstance(cpu, dict)
        spread = ", ".join(f"{k} {min(v):.2f}-{max(v):.2f}" for k, v in cpu.items())
        print(f"  {scenario}: {spread}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
