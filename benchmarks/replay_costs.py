"""Where a replay's fixed and per-sample costs go (issue 13): imports and the observer step's two halves.

* start-up: CPU time (user + system) of a fresh interpreter importing what ``magcomp replay`` imports, module
  group by module group, against the bare interpreter and against the imports of pymavlink's parse-only loop
  (and scipy.optimize, which a replay no longer imports);
* the observer: the whole :func:`~magcomp.core.observer.observer_step` against its theta-independent half
  (rotation increment, regressor, eq. (21) excitation, the sec. II-D low-pass on the regression), which
  depends on the inputs alone and so could be computed over a block of samples in a learn-only pass;
* ``--inflight``: the in-flight calibration's layers on a simulated 10 min flight (the ordinary scenario,
  calibration and theta learned in flight): a two-pass replay (one process), in fresh processes, with one
  layer more switched on in each: no ``feed`` at all, ``feed``'s bookkeeping without window rows, the rows
  built but not added to the estimators, everything. Each difference is that layer's CPU, also per call
  (the calls counted in the same run). Beside them the budget that issue 24's 1.5x leaves the stage (1.5
  times the parse-only process, less the replay without ``feed``).

    .venv/bin/python benchmarks/replay_costs.py [--repeat 5] [--inflight]
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import statistics
import subprocess
import sys
import timeit
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

#: what each line imports, cumulatively (each after the previous ones)
IMPORTS: tuple[tuple[str, str], ...] = (
    ("bare interpreter", "pass"),
    (
        "pymavlink parse-only imports",
        "from magcomp.adapters.dialect import ensure_dialect; ensure_dialect(); "
        "from pymavlink import mavutil",
    ),
    ("+ numpy", "import numpy"),
    ("+ magcomp replay modules", "import magcomp.cli, magcomp.commands.replay, magcomp.service.replay"),
    # not imported by a replay since the refined eq. (3) fit runs on core/dpi.py's own Levenberg-Marquardt;
    # kept as the measure of what that saved
    ("+ scipy.optimize (no longer on a replay's path)", "import scipy.optimize"),
)


def _cpu_of(code: str, repeat: int) -> float:
    """Median CPU time of ``python -c code`` as a process of its own."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, (str(ROOT), os.environ.get("PYTHONPATH"))))
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    subprocess.run([sys.executable, "-c", code], check=True, env=env)  # bytecode written, pages cached
    out = []
    for _ in range(repeat):
        r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        subprocess.run([sys.executable, "-c", code], check=True, env=env)
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        out.append(r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime)
    return statistics.median(out)


def startup(repeat: int) -> None:
    code, prev = "", None
    print("start-up, CPU median of a fresh process:")
    for name, stmt in IMPORTS:
        code = f"{code}; {stmt}" if code else stmt
        t = _cpu_of(code, repeat)
        step = "" if prev is None else f"  (+{t - prev:.3f} s)"
        print(f"  {name:<48} {t:6.3f} s{step}")
        prev = t


def observer_split(repeat: int) -> None:
    from magcomp.core import observer as ob
    from magcomp.core.linalg3 import gram, minus_matvec
    from magcomp.core.rotations import dcm_from_rotvec

    p, dt = ob.ObserverParams(), 0.02

    def inputs(i: int) -> tuple[tuple[float, float, float], tuple[float, float, float], float]:
        t = i * dt  # a hand rotation about all three axes at half throttle
        w = (math.sin(t), 0.7 * math.cos(1.3 * t), 0.4 * math.sin(0.7 * t))
        v = (200.0 + 50.0 * math.sin(t), 100.0 * math.cos(t), 400.0 + 10.0 * math.sin(2.0 * t))
        return w, v, 0.5 + 0.2 * math.sin(0.3 * t)

    st = ob.observer_init(p)
    for i in range(600):
        w, v, d = inputs(i)
        st = ob.observer_step(st, w, v, d, dt, p).state
    w, v, d = inputs(601)
    k = p.step_constants(dt)

    def independent() -> None:
        ph = ob.rotation_increment(
            st.omega_prev2_rad_s, st.omega_prev_rad_s, w, st.dt_prev_s, dt, p.rate_interp
        )
        a_k = dcm_from_rotvec((-ph[0], -ph[1], -ph[2]))
        phi_k = ob.regressor(a_k, st.d2_prev, d * d, p.variant)
        y_k = minus_matvec(v, a_k, st.field_prev_mgauss)
        ob._excitation_update(st, phi_k, dt, k, p)
        ob._prefilter_regression(st.lp, y_k, phi_k, k.lowpass, p)

    def non_recursive() -> None:  # what does not carry state from sample to sample
        ph = ob.rotation_increment(
            st.omega_prev2_rad_s, st.omega_prev_rad_s, w, st.dt_prev_s, dt, p.rate_interp
        )
        a_k = dcm_from_rotvec((-ph[0], -ph[1], -ph[2]))
        phi_k = ob.regressor(a_k, st.d2_prev, d * d, p.variant)
        minus_matvec(v, a_k, st.field_prev_mgauss)
        gram(phi_k)

    n = 20_000
    flat = min(timeit.repeat(non_recursive, number=n, repeat=repeat)) / n
    full = min(timeit.repeat(lambda: ob.observer_step(st, w, v, d, dt, p), number=n, repeat=repeat)) / n
    half = min(timeit.repeat(independent, number=n, repeat=repeat)) / n
    print(f"observer_step {full * 1e6:.2f} us; its theta-independent half {half * 1e6:.2f} us "
          f"({half / full:.0%}; x 58,787 steps of a 10 min log: {half * 58_787:.2f} s), of which "
        f"{flat * 1e6:.2f} us carry no state from sample to sample ({flat * 58_787:.2f} s)")  # fmt: skip


def block_estimate(repeat: int, n: int = 58_787) -> None:
    """What the theta-independent half costs over a block of ``n`` samples at one dt: the core's own float
    functions fed numpy rows where they are plain arithmetic (rotation increment, regressor, y, Gram), scipy
    for A_k (``Rotation.from_rotvec``) and for the two recursions (``lfilter``: the eq. (21) window and the
    sec. II-D biquad with the coefficients of ``step_constants``). An estimate of lever 1 of issue 13, not a
    path of magcomp (no checks, no re-anchoring, no interval changes inside the block)."""
    import time

    import numpy as np
    from scipy.signal import lfilter
    from scipy.spatial.transform import Rotation

    from magcomp.core import observer as ob
    from magcomp.core.linalg3 import gram, minus_matvec

    p, dt = ob.ObserverParams(), 0.02
    t = np.arange(n + 2) * dt
    w = np.array((np.sin(t), 0.7 * np.cos(1.3 * t), 0.4 * np.sin(0.7 * t)))
    v = np.array((200.0 + 50.0 * np.sin(t), 100.0 * np.cos(t), 400.0 + 10.0 * np.sin(2.0 * t)))
    d2 = (0.5 + 0.2 * np.sin(0.3 * t)) ** 2
    k = p.step_constants(dt)
    c = k.lowpass

    def block() -> None:
        ph = ob.rotation_increment(w[:, :-2], w[:, 1:-1], w[:, 2:], dt, dt, p.rate_interp)  # type: ignore[arg-type]
        a_k = Rotation.from_rotvec(-np.array(ph).T).as_matrix().reshape(-1, 9).T
        phi = ob.regressor(a_k, d2[1:-1], d2[2:], p.variant)
        y = minus_matvec(v[:, 2:], a_k, v[:, 1:-1])
        q = np.array(gram(phi)) / dt
        gs = lfilter([1.0], [1.0, -k.lam_excitation], q, axis=1)
        gw = lfilter([dt], [1.0, -k.lam_excitation], np.ones(n))
        g = gs / gw
        a, b, cc, e, f, i = g
        det = a * (e * i - f * f) - b * (b * i - f * cc) + cc * (b * f - e * cc)  # per-axis 1 / [G^-1]_ii
        _ = (det / (e * i - f * f), det / (a * i - cc * cc), det / (a * e - b * b))
        lfilter([c.b0, c.b1, c.b2], [1.0, c.a1, c.a2], np.vstack((y, phi)), axis=1)

    best = math.inf
    for _ in range(repeat):
        t0 = time.process_time()
        block()
        best = min(best, time.process_time() - t0)
    print(
        f"theta-independent half over a block of {n} samples: {best:.3f} s ({best / n * 1e6:.2f} us a sample)"
    )


#: the in-flight layers: switched off by replacing one method for the run (a measurement, not a mode of
#: magcomp: the replay's results are not used)
_LAYER_SCRIPT = """
import resource, sys, time
from magcomp.adapters.config import Config
import magcomp.service.replay as rp
from magcomp.core import inflight as inf
from magcomp.service import inflight_stage as ist
layer, path = sys.argv[1], sys.argv[2]
calls = {"feed": 0, "rows": 0, "add": 0}
feed, row, add = ist.InflightStage.feed, ist.InflightStage._window_row, inf.InflightEstimator.add
def _feed(self, *a, **k):
    calls["feed"] += 1
    return None if layer == "none" else feed(self, *a, **k)
def _row(self, *a, **k):
    calls["rows"] += 1
    return None if layer == "feed" else row(self, *a, **k)
def _add(self, *a, **k):
    calls["add"] += 1
    if layer == "rows":  # not added: the estimator stays empty, nothing to solve
        return 0.0
    return add(self, *a, **k)
if layer != "all":  # the counting wrappers only where a layer is switched off (their own cost: ~0.1 us)
    ist.InflightStage.feed, ist.InflightStage._window_row, inf.InflightEstimator.add = _feed, _row, _add
rp.replay_log(path, Config(), emit=None, two_pass=True)
own = resource.getrusage(resource.RUSAGE_SELF)
print(own.ru_utime + own.ru_stime, calls["feed"], calls["rows"], calls["add"])
"""

_PARSE_ONLY_SCRIPT = """
import sys
from magcomp.adapters.dialect import ensure_dialect
ensure_dialect()
from pymavlink import mavutil
conn = mavutil.mavlink_connection(sys.argv[1], dialect="magcomp")
while conn.recv_msg() is not None:
    pass
"""


def _process_cpu(args: list[str], env: dict[str, str]) -> tuple[float, list[int]]:
    """CPU of ``python -c ...`` (its own, as it printed it, else as measured here) and the call counts it
    printed after it."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    out = subprocess.run([sys.executable, "-c", *args], check=True, env=env, capture_output=True, text=True)
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    total = r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime
    if not out.stdout.strip():
        return total, []
    own, *counts = out.stdout.split()
    return float(own), [int(c) for c in counts]


def inflight_layers(repeat: int, duration_s: float = 600.0) -> None:
    """The in-flight stage's layers (module docstring), medians of ``repeat`` fresh processes."""
    import tempfile

    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate

    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, (str(ROOT), os.environ.get("PYTHONPATH"))))
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    layers = ("none", "feed", "rows", "all")
    with tempfile.TemporaryDirectory() as tmp:
        path = str(Path(tmp) / "flight.tlog")
        write_tlog(simulate(SimConfig(scenario="ordinary", duration_s=duration_s, seed=0)), Path(path))
        _process_cpu([_PARSE_ONLY_SCRIPT, path], env)  # bytecode written, the file in the page cache
        runs: dict[str, list[tuple[float, list[int]]]] = {k: [] for k in ("parse", *layers)}
        for _ in range(repeat):  # interleaved, so that load from other processes hits all alike
            runs["parse"].append(_process_cpu([_PARSE_ONLY_SCRIPT, path], env))
            for layer in layers:
                runs[layer].append(_process_cpu([_LAYER_SCRIPT, layer, path], env))
    med = {k: statistics.median(o for o, _ in v) for k, v in runs.items()}
    n_feed, n_rows, n_add = runs["none"][0][1][0], runs["feed"][0][1][1], runs["rows"][0][1][2]
    print(f"in-flight stage, {duration_s:g} s ordinary flight, two-pass replay (one process), CPU medians of "
          f"{repeat}; {n_feed} feed calls, {n_rows} window rows, {n_add} estimator rows:")  # fmt: skip
    steps = (
        ("pymavlink parse-only process", "parse", None, 0),
        ("replay, no in-flight feed", "none", None, 0),
        ("+ feed's bookkeeping (no window rows)", "feed", "none", n_feed),
        ("+ window rows built, not added (nothing to solve)", "rows", "feed", n_rows),
        ("+ added: gate, accumulation, solves (all)", "all", "rows", n_add),
    )
    for name, key, prev, n in steps:
        d = med[key] - med[prev] if prev is not None else 0.0
        added = "" if prev is None else f"  (+{d:.2f} s, {d / max(n, 1) * 1e6:.1f} us a call)"
        print(f"  {name:<52} {med[key]:6.2f} s{added}")
    stage = med["all"] - med["none"]
    budget = 1.5 * med["parse"] - med["none"]
    print(f"  the stage costs {stage:.2f} s ({stage / med['all']:.0%} of the replay); issue 24's 1.5x "
          f"leaves it {budget:.2f} s ({stage / max(budget, 1e-9):.1f}x over)")  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--no-startup", action="store_true", help="skip the start-up processes")
    ap.add_argument("--inflight", action="store_true", help="only the in-flight stage's layers")
    args = ap.parse_args()
    if args.inflight:
        inflight_layers(args.repeat)
        return 0
    if not args.no_startup:
        startup(args.repeat)
    observer_split(args.repeat)
    block_estimate(args.repeat)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
