"""How fast the autopilot's yaw follows its compass, measured from a log (magcomp.diagnosis.yaw_follow).

The gain k (1/s) of ``d psi_ap/dt = gyro + b + k (psi_compass - psi_ap)``, on the ground (motors off) and in
flight (throttle above 0.1), for the compass the autopilot fuses (``--compass``, default 0). With
``--simulate`` it runs on simulated ordinary flights instead, whose autopilot has a known gain
(``ap_kp_yaw``), to check the measurement.

    .venv/bin/python benchmarks/autopilot_yaw_follow.py [LOG ...] [--compass N] [--until S]
    .venv/bin/python benchmarks/autopilot_yaw_follow.py --simulate --kp 0.05 0.5 --seeds 0 1 2
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from magcomp.adapters.mavlink_source import load_log
from magcomp.core.types import LogData
from magcomp.diagnosis.yaw_follow import YawFollow, yaw_follow_gain

DEFAULT_LOG = (
    Path(__file__).resolve().parents[1].parent / "shared/data/measured/dronekit_log171_copter33_quad.bin"
)
FLYING_THROTTLE_01 = 0.1


def segments(log: LogData, compass: int, until_s: float) -> dict[str, YawFollow | None]:
    mag = log.mag[compass]
    att = log.attitude_rad
    thr = log.throttle_01
    t0 = float(att.t_s[0])
    fly_t = thr.t_s[thr.values > FLYING_THROTTLE_01] if len(thr) else np.zeros(0)
    out: dict[str, YawFollow | None] = {}
    args = (att.t_s, att.values, log.imu_t_s, log.gyro_rad_s, mag.t_s, mag.values)
    if fly_t.size:
        out["ground (before the motors start)"] = yaw_follow_gain(*args, t_end_s=float(fly_t[0]) - 1.0)
        out["flight (first to last throttle > 0.1)"] = yaw_follow_gain(
            *args, t_start_s=float(fly_t[0]) + 5.0, t_end_s=min(float(fly_t[-1]), t0 + until_s)
        )
    else:
        out["whole log (no throttle above 0.1)"] = yaw_follow_gain(*args, t_end_s=t0 + until_s)
    return out


def show(name: str, r: YawFollow | None) -> None:
    if r is None:
        print(f"  {name}: too little data")
        return
    tau = f"{1.0 / r.gain_per_s:.0f} s" if r.gain_per_s > 0 else "inf"
    spread = math.degrees(r.spread_rad)
    print(f"  {name}: k = {r.gain_per_s:.3f} +- {r.gain_sigma_per_s:.3f} /s (time constant {tau}), "
          f"{r.n_windows} windows ({r.n_left_out} left out as jumps), compass - autopilot yaw spread "
          f"{spread:.2f} deg")  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("logs", nargs="*")
    ap.add_argument("--compass", type=int, default=0)
    ap.add_argument("--until", type=float, default=226.0, help="s after the first attitude (log171 crashes)")
    ap.add_argument("--simulate", action="store_true")
    ap.add_argument("--kp", type=float, nargs="+", default=[0.05, 0.5])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    args = ap.parse_args()
    if args.simulate:
        from magcomp.adapters.mavlink_emit import write_tlog
        from magcomp.sim import SimConfig, simulate
        from magcomp.sim.config import apply_settings

        for kp in args.kp:
            for seed in args.seeds:
                res = simulate(
                    apply_settings(SimConfig(scenario="ordinary", seed=seed), [f"ap_kp_yaw={kp:g}"])
                )
                with tempfile.TemporaryDirectory() as tmp:
                    path = Path(tmp) / "o.tlog"
                    write_tlog(res, path)
                    log = load_log(path)
                print(f"simulated ordinary flight, ap_kp_yaw = {kp:g} /s, seed {seed}:")
                for name, r in segments(log, 0, math.inf).items():
                    show(name, r)
        return 0
    for p in args.logs or [str(DEFAULT_LOG)]:
        if not Path(p).exists():
            print(f"{p}: not found", file=sys.stderr)
            return 2
        log = load_log(p)
        if args.compass not in log.mag or len(log.attitude_rad) < 2 or log.imu_t_s.size < 2:
            print(f"{p}: no compass {args.compass}, attitude or gyro stream")
            continue
        print(f"{p} (compass {args.compass}):")
        for name, r in segments(log, args.compass, args.until).items():
            show(name, r)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
