"""False-alarm rate and detection power of `magcomp diagnose` on deliberately varied simulations.

Every log is simulated fresh (simulate -> tlog -> load_log -> diagnose) and then varied so that the
diagnosis cannot lean on the simulator's habits:

* simulator: scenario (paper experiment or a flight), vehicle (fixed-wing throttle or quad motor outputs),
  duration 60-133 s, place and date (latitude -60..60, any longitude, 2025-2030: Earth field 250-650 mgauss,
  inclination -75..75 deg), IMU rate 25-200 Hz, attitude / servo / battery message rates, |theta| 0.5-3x
  Table II in a random direction; the simulated autopilot's yaw is fused from the disturbed compass;
* applied to the loaded log here: magnetometer rate 1-100 Hz (below 5 Hz the IMU is thinned with it, as in a
  telemetry log), coloured noise (AR(1), rho 0-0.95, 0-4 mgauss), quantisation (0-3 mgauss LSB), a residual
  scale error of the compass (+-10 % per axis), attitude errors (roll/pitch bias sd 1 deg and noise sd
  0.5 deg), a gyro bias (sd 0.005 rad/s).

The Earth reference is the WMM at the simulated place and date, as `diagnose` takes it from a log's GPS.

Reported: on clean logs, the share with any named finding on an observable compass (false alarms), the share
with "unexplained structure", the share the gate declares not observable; per hidden effect and size, the
share where the effect is named (alone or in a set of indistinguishable causes), and the smallest size found
at least 90 % of the time (at that size and every larger one).

    .venv/bin/python benchmarks/diagnosis_false_alarm.py [--clean 60] [--per-size 8] [--workers 2]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from dataclasses import replace
from multiprocessing import Pool
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

THETA_PAPER = np.array([-61.0, 26.4, -1.2])

#: effect -> sizes tried (the simulator's VALUE; exponent as given, the others from zero)
SIZES: dict[str, list[float]] = {
    "throttle_offset": [0.03, 0.06, 0.1, 0.15, 0.25],
    "throttle_exponent": [2.15, 2.3, 2.5, 2.8, 3.2],
    "current_lag": [0.05, 0.1, 0.2, 0.4, 0.8],
    "time_skew": [0.03, 0.06, 0.1, 0.2, 0.4],
    "voltage_sag": [0.1, 0.2, 0.4, 0.7, 1.0],
    "temperature_drift": [0.25, 0.5, 1.0, 2.0, 4.0],
    "per_motor": [0.1, 0.2, 0.4, 0.8, 1.6],
}


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def varied_log(seed: int, effect: str, value: float) -> tuple[Any, Any, dict[str, Any]]:
    """(LogData, EarthReference, what was varied) of one deliberately varied simulation."""
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.adapters.mavlink_source import load_log
    from magcomp.core.types import Series
    from magcomp.diagnosis.gate import EarthReference
    from magcomp.geomag import earth_field_ned_mgauss
    from magcomp.sim import SimConfig, simulate
    from magcomp.sim.config import Location, Rates

    rng = np.random.default_rng(seed)
    scenario = str(rng.choice(["paper", "flight"]))
    vehicle = "multirotor" if effect == "per_motor" else str(rng.choice(["fixedwing", "multirotor"]))
    imu_hz = float(rng.choice([25.0, 50.0, 100.0, 200.0]))
    rates = Rates(
        imu_hz=imu_hz,
        attitude_hz=min(imu_hz, float(rng.choice([5.0, 10.0, 25.0, 50.0]))),
        servo_hz=min(imu_hz, float(rng.choice([5.0, 10.0, 25.0, 50.0]))),
        power_hz=min(imu_hz, float(rng.choice([1.0, 5.0, 10.0]))),
        rc_hz=min(imu_hz, 10.0),
        vfr_hud_hz=min(imu_hz, 10.0),
    )
    loc = Location(
        lat_deg=float(rng.uniform(-60.0, 60.0)),
        lon_deg=float(rng.uniform(-180.0, 180.0)),
        alt_m=float(rng.uniform(0.0, 2000.0)),
        decimal_year=float(rng.uniform(2025.0, 2029.9)),
    )
    theta = _random_rotation(rng) @ THETA_PAPER * float(rng.uniform(0.5, 3.0))
    cfg = SimConfig(
        scenario=scenario,
        duration_s=float(rng.uniform(60.0, 133.0)),
        seed=seed,
        effects={effect: value} if effect else {},
        vehicle=vehicle,
        location=loc,
        rates=rates,
        n_compasses=1,
        theta_mgauss=(float(theta[0]), float(theta[1]), float(theta[2])),
    )
    res = simulate(cfg)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "v.tlog"
        write_tlog(res, path)
        log = load_log(path)
    # --- variation applied to the loaded log
    mag_hz = float(rng.choice([1.0, 2.0, 5.0, 10.0, 25.0, 50.0, 100.0]))
    mag_hz = min(mag_hz, imu_hz)
    s = log.mag[0]
    every = max(1, round(imu_hz / mag_hz))
    t, v = s.t_s[::every], s.values[::every].astype(float)
    rho = float(rng.uniform(0.0, 0.95))
    sd = float(rng.uniform(0.0, 4.0))
    e = rng.normal(0.0, sd * math.sqrt(1.0 - rho**2), v.shape)
    for k in range(1, e.shape[0]):
        e[k] += rho * e[k - 1]
    v = v @ np.diag(1.0 + rng.uniform(-0.1, 0.1, 3)) + e
    lsb = float(rng.choice([0.0, 1.0, 2.0, 3.0]))
    if lsb > 0:
        v = np.round(v / lsb) * lsb
    att = log.attitude_rad
    av = att.values.copy()
    av[:, :2] += np.radians(rng.normal(0.0, 1.0, 2)) + np.radians(rng.normal(0.0, 0.5, (av.shape[0], 2)))
    gyro = log.gyro_rad_s + rng.normal(0.0, 0.005, 3)
    imu_t, acc = log.imu_t_s, log.accel_m_s2
    if mag_hz < 5.0:  # a telemetry log: RAW_IMU carries the gyro at the compass rate
        imu_t, gyro, acc = imu_t[::every], gyro[::every], acc[::every]
    log = replace(
        log,
        mag={0: Series(t, v)},
        attitude_rad=Series(att.t_s, av),
        gyro_rad_s=gyro,
        imu_t_s=imu_t,
        accel_m_s2=acc,
    )
    earth = EarthReference(
        earth_field_ned_mgauss(loc.lat_deg, loc.lon_deg, loc.alt_m, loc.decimal_year), "simulated place"
    )
    varied = {"scenario": scenario, "vehicle": vehicle, "mag_hz": mag_hz, "imu_hz": imu_hz}
    return log, earth, varied


def run_one(job: tuple[int, str, float]) -> dict[str, Any]:
    """Simulate, vary, diagnose one log. job = (seed, effect or "", value)."""
    from magcomp.diagnosis.engine import diagnose

    seed, effect, value = job
    log, earth, varied = varied_log(seed, effect, value)
    t0 = time.perf_counter()
    try:
        j = diagnose(log, earth=earth).to_json()
    except Exception as exc:  # a crash is a result too: report it
        return {"seed": seed, "effect": effect, "value": value, "error": repr(exc)}
    c = j["compasses"][0]
    names: list[str] = []
    for f in c["findings"]:
        names += f.get("candidates", [f["effect"]])
    return {
        "seed": seed,
        "effect": effect,
        "value": value,
        **varied,
        "attitude_source": c["attitude"]["source"],
        "observable": c["observable"],
        "why": c["unobservable_why"],
        "findings": names,
        "top": c["findings"][0]["effect"] if c["findings"] else None,
        "structure": [u["kind"] for u in c["unexplained_structure"]],
        "seconds": round(time.perf_counter() - t0, 2),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clean", type=int, default=60, help="clean logs (default 60)")
    ap.add_argument("--per-size", type=int, default=8, help="logs per effect and size (default 8)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--effects", nargs="*", default=list(SIZES))
    ap.add_argument("--jsonl", default=None, help="append every run's record here as it finishes")
    ap.add_argument("--summarise", default=None, help="only summarise the records of an earlier --jsonl")
    args = ap.parse_args()

    jobs: list[tuple[int, str, float]] = [(10_000 + i, "", 0.0) for i in range(args.clean)]
    for k, eff in enumerate(args.effects):
        for m, size in enumerate(SIZES[eff]):
            for r in range(args.per_size):
                jobs.append((20_000 + 1000 * k + 100 * m + r, eff, size))
    t0 = time.perf_counter()
    out: list[dict[str, Any]] = []
    if args.summarise:
        for line in Path(args.summarise).read_text(encoding="utf-8").splitlines():
            out.append(json.loads(line))
    else:
        # clean logs first, then effects interleaved, so a partial run still covers every effect
        jobs.sort(key=lambda j: (j[1] != "", j[0] % 100, j[0]))
        sink = open(args.jsonl, "w", encoding="utf-8") if args.jsonl else None  # noqa: SIM115
        with Pool(args.workers) as pool:
            for rec in pool.imap_unordered(run_one, jobs, chunksize=1):
                out.append(rec)
                if sink is not None:
                    sink.write(json.dumps(rec) + "\n")
                    sink.flush()
        if sink is not None:
            sink.close()
    wall = time.perf_counter() - t0
    summarise(out, args.effects, wall, args.workers)
    return 0


def summarise(out: list[dict[str, Any]], effects: list[str], wall: float, workers: int) -> None:
    errors = [o for o in out if "error" in o]
    ok = [o for o in out if "error" not in o]
    clean = [o for o in ok if not o["effect"]]
    obs = [o for o in clean if o["observable"]]
    fa = [o for o in obs if o["findings"]]
    st = [o for o in obs if o["structure"]]
    print(f"{len(out)} logs in {wall:.0f} s ({workers} workers); {len(errors)} errors")
    print(
        f"clean logs: {len(clean)}; not observable (gate): {len(clean) - len(obs)}; "
        f"named finding on an observable compass: {len(fa)}/{len(obs)} = "
        f"{100 * len(fa) / max(len(obs), 1):.1f} %; "
        f"unexplained structure: {len(st)}/{len(obs)} = {100 * len(st) / max(len(obs), 1):.1f} %"
    )
    for o in fa:
        print(f"  false alarm seed {o['seed']}: {o['findings']} (mag {o['mag_hz']} Hz, {o['scenario']})")
    why: dict[str, int] = {}
    for o in clean:
        if not o["observable"]:
            key = o["why"].split(":")[0][:60]
            why[key] = why.get(key, 0) + 1
    for k, n in sorted(why.items(), key=lambda kv: -kv[1]):
        print(f"  not observable x{n}: {k}")
    print(
        "\neffect | size: found / observable (all mag rates) | found at >= 5 Hz | 90 % size (all / >= 5 Hz)"
    )
    for eff in effects:
        cells, cells5 = [], []
        rates, rates5 = [], []
        for size in SIZES[eff]:
            runs = [o for o in ok if o["effect"] == eff and o["value"] == size and o["observable"]]
            fast = [o for o in runs if o["mag_hz"] >= 5.0]
            hit = sum(eff in o["findings"] for o in runs)
            hit5 = sum(eff in o["findings"] for o in fast)
            rates.append(hit / len(runs) if runs else 0.0)
            rates5.append(hit5 / len(fast) if fast else 0.0)
            cells.append(f"{size}: {hit}/{len(runs)}")
            cells5.append(f"{hit5}/{len(fast)}")

        def size90(r: list[float], eff: str = eff) -> str:
            for i in range(len(r)):
                if all(x >= 0.9 for x in r[i:]):
                    return str(SIZES[eff][i])
            return "not reached"

        print(f"{eff} | {', '.join(cells)} | {', '.join(cells5)} | {size90(rates)} / {size90(rates5)}")


if __name__ == "__main__":
    raise SystemExit(main())
