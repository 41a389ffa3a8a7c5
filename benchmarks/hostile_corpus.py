"""A generated hostile corpus through `replay`, `diagnose` and `fit` (issue 25's acceptance run).

Clean logs are simulated (tlog, DataFlash .bin, PX4 .ulg; a paper-like flight whose theta converges), then
damaged in seeded ways: flipped bits, zeroed or random blocks, cuts, zero tails, random FMT blocks,
NaN parameters, garbage attitudes, clipped magnetometer samples, NUL runs. Each damaged log is run by
each command in a subprocess with a wall-time and memory limit; a run passes when it ends without a
traceback, within the limits, with at most MAX_LINES lines of output. For the damaged-but-mostly-intact
cases (``mild``), `replay` must also keep >= 90 % of the clean run's headings with theta within 20 %
(of at least 25 mgauss) of the clean run's.

    .venv/bin/python benchmarks/hostile_corpus.py [--cases 200] [--seed 0] [--commands replay diagnose fit]
        [--timeout 60] [--memory-mib 1024] [--keep DIR] [--only 10 14 170] [--mild-only]

``--only`` runs just the listed cases and ``--mild-only`` just the mild ones (the damage of every case is
still drawn in order, so case k is the same log whichever cases run).

Prints one line per failing run and the counts: cases, runs, tracebacks, timeouts, over-memory, too many
lines, mild cases below the headings or theta bar.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

MAX_LINES = 100
Damage = Callable[[bytes, np.random.Generator], bytes]


def flip_bits(n: int) -> Damage:
    def damage(data: bytes, rng: np.random.Generator) -> bytes:
        b = bytearray(data)
        for p in rng.integers(min(2000, len(b) // 4), len(b), n):
            b[p] ^= 1 << int(rng.integers(0, 8))
        return bytes(b)

    return damage


def blocks(n: int, size: int, zero: bool) -> Damage:
    def damage(data: bytes, rng: np.random.Generator) -> bytes:
        b = bytearray(data)
        for p in rng.integers(min(2000, len(b) // 4), max(len(b) - size, 1), n):
            b[p : p + size] = bytes(size) if zero else rng.integers(0, 256, size, dtype=np.uint8).tobytes()
        return bytes(b)

    return damage


def cut(fraction: float) -> Damage:
    return lambda data, rng: data[: int(len(data) * fraction)]


def zero_tail(n_bytes: int) -> Damage:
    return lambda data, rng: data + bytes(n_bytes)


def random_fmt(n: int) -> Damage:
    def damage(data: bytes, rng: np.random.Generator) -> bytes:
        b = bytearray(data)
        for p in rng.integers(500, len(b) - 100, n):
            b[p : p + 89] = b"\xa3\x95\x80" + rng.integers(0, 256, 86, dtype=np.uint8).tobytes()
        return bytes(b)

    return damage


def nul_runs(n: int) -> Damage:
    return blocks(n, 50, zero=True)


#: (name, formats it applies to, damage, mild): mild cases must keep the clean run's results
DAMAGES: list[tuple[str, tuple[str, ...], Callable[[], Damage], bool]] = [
    ("flip10", ("tlog", "bin", "ulg"), lambda: flip_bits(10), True),
    ("flip100", ("tlog", "bin", "ulg"), lambda: flip_bits(100), False),
    ("flip1000", ("tlog", "bin", "ulg"), lambda: flip_bits(1000), False),
    ("zero-blocks", ("tlog", "bin", "ulg"), lambda: blocks(3, 512, zero=True), True),
    ("random-blocks", ("tlog", "bin", "ulg"), lambda: blocks(3, 512, zero=False), True),
    ("cut-half", ("tlog", "bin", "ulg"), lambda: cut(0.5), False),
    ("cut-tiny", ("tlog", "bin", "ulg"), lambda: cut(0.01), False),
    ("zero-tail", ("tlog", "bin", "ulg"), lambda: zero_tail(1 << 20), True),
    ("random-fmt", ("bin",), lambda: random_fmt(3), False),
    ("nul-runs", ("bin",), lambda: nul_runs(20), False),
]


def clean_logs(d: Path, seed: int) -> dict[str, Path]:
    from magcomp.adapters.dataflash_writer import write_sim_dataflash
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.adapters.ulog_writer import write_sim_ulog
    from magcomp.sim import SimConfig, simulate

    result = simulate(SimConfig(scenario="paper", duration_s=60.0, seed=seed))
    out = {"tlog": d / "clean.tlog", "bin": d / "clean.bin", "ulg": d / "clean.ulg"}
    write_tlog(result, out["tlog"])
    write_sim_dataflash(result, out["bin"])
    write_sim_ulog(result, out["ulg"])
    return out


def _limit(memory_mib: int) -> Callable[[], None]:
    def apply() -> None:
        limit = memory_mib << 20
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))

    return apply


def run(command: str, log: Path, timeout_s: float, memory_mib: int, js: Path) -> dict[str, Any]:
    """One command on one log: exit code, lines, traceback, timeout, over-memory, its JSON."""
    argv = [sys.executable, "-m", "magcomp", command, str(log), "--json", str(js)]
    if command == "fit":
        argv += ["--monte-carlo", "50"]
    t0 = time.monotonic()
    try:
        proc = subprocess.run(argv, capture_output=True, text=True, timeout=timeout_s, cwd=REPO,
                              preexec_fn=_limit(memory_mib), errors="replace")  # fmt: skip
    except subprocess.TimeoutExpired:
        return {"timeout": True, "wall_s": time.monotonic() - t0}
    text = proc.stdout + proc.stderr
    doc = None
    if js.is_file():
        try:
            doc = json.loads(js.read_text())
        except (OSError, ValueError):
            doc = None
    return {
        "rc": proc.returncode,
        "lines": len(text.splitlines()),
        "traceback": "Traceback" in proc.stderr,
        "memory": "MemoryError" in proc.stderr or proc.returncode == -9,
        "wall_s": time.monotonic() - t0,
        "json": doc,
        "last": (proc.stderr.strip().splitlines() or [""])[-1][:160],
    }


def _thetas(doc: Any) -> dict[int, np.ndarray]:
    comps = doc.get("compasses", []) if isinstance(doc, dict) else []
    return {int(c["index"]): np.asarray(c["theta_mgauss"], dtype=float) for c in comps
            if c.get("theta_mgauss") is not None}  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--commands", nargs="+", default=["replay", "diagnose", "fit"])
    ap.add_argument("--timeout", type=float, default=60.0)
    ap.add_argument("--memory-mib", type=int, default=1024)
    ap.add_argument("--keep", type=Path, help="keep the corpus in this directory")
    ap.add_argument("--only", type=int, nargs="+", metavar="CASE", help="run only these cases")
    ap.add_argument("--mild-only", action="store_true", help="run only the mild cases")
    args = ap.parse_args()

    work = args.keep or Path(tempfile.mkdtemp(prefix="magcomp-hostile-"))
    work.mkdir(parents=True, exist_ok=True)
    clean = clean_logs(work, args.seed)
    reference = {}
    for fmt, path in clean.items():
        reference[fmt] = run("replay", path, args.timeout, args.memory_mib, work / f"clean-{fmt}.json")
    cases = [(name, fmt, make, mild) for name, fmts, make, mild in DAMAGES for fmt in fmts]
    rng = np.random.default_rng(args.seed)
    tally: Counter[str] = Counter()
    for k in range(args.cases):
        name, fmt, make, mild = cases[k % len(cases)]
        data = make()(clean[fmt].read_bytes(), rng)
        if (args.only is not None and k not in args.only) or (args.mild_only and not mild):
            continue
        log = work / f"case{k:04d}-{name}.{fmt}"
        log.write_bytes(data)
        tally["cases"] += 1
        for command in args.commands:
            res = run(command, log, args.timeout, args.memory_mib, work / f"case{k:04d}-{command}.json")
            tally["runs"] += 1
            bad = []
            if res.get("timeout"):
                bad.append("timeout")
            if res.get("traceback"):
                bad.append("traceback")
            if res.get("memory"):
                bad.append("memory")
            if int(res.get("lines", 0)) > MAX_LINES:
                bad.append(f"{res['lines']} lines")
            if mild and command == "replay" and not bad:
                ref, got = reference[fmt].get("json"), res.get("json")
                n_ref = int((ref or {}).get("estimates", 0))
                n_got = int((got or {}).get("estimates", 0))
                if n_got < 0.9 * n_ref:
                    bad.append(f"headings {n_got}/{n_ref}")
                th_ref, th_got = _thetas(ref), _thetas(got)
                for idx, a in th_ref.items():
                    got_theta = th_got.get(idx)
                    tol = 0.2 * max(float(np.linalg.norm(a)), 25.0)
                    err = float(np.linalg.norm(got_theta - a)) if got_theta is not None else math.inf
                    if not err <= tol:
                        bad.append(f"theta {idx}")
            for why in bad:
                tally[why.split()[0] if why[0].isalpha() else "lines"] += 1
            if bad:
                tally["failed runs"] += 1
                said = ", ".join(bad)
                print(f"case {k} {name} .{fmt} {command}: {said} ({res.get('last', '')})", flush=True)
    print(" ".join(f"{k}={v}" for k, v in sorted(tally.items())))
    print(f"corpus in {work}")
    return 0 if tally["failed runs"] == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
