"""Ordinary flight, no hand rotation (issue 9): simulated take-off, hover, yaw turns, climbs, forward flight,
landing, the autopilot's yaw fused from the disturbed compass, its own calibration slightly off, telemetry at
1, 10 and 50 Hz. Each run: simulate -> tlog -> ``replay`` (the product path, causal and two-pass) and an
oracle replay with the true calibration and theta (no learning), everything else identical.

Reported per rate (worst of the seeds): rms heading error against the simulated truth after the first 60 s
of flight, for magcomp causal / two-pass, uncorrected and oracle, the ratio to the oracle, and theta's
error in % of |theta| (causal, end of flight), and theta's Cramer-Rao bound at the end of the flight for the
same samples (``benchmarks/theta_crb.py``: rms |theta error| / |theta|, %) with the attitude trusted
(``CRB trusted``: the absolute form's, an external primary) and with its yaw trusted only within 2 s windows
(``CRB window``: the window-field rows' information with the autopilot's yaw) and with the raw gyro's yaw
over 10 s windows (``CRB gyro``: what the relative form uses for an internal compass).

Each run at theta's two sizes (``--theta-scales 1 6``): Table II's (the hard case: 17 mgauss at hover, 2-3 deg
of heading) and a realistic multirotor's (399 mgauss, 19-22 deg uncorrected; log171's internal compasses have
484 and 790 mgauss).

Also per run: the heading error's constant part (``offset``) and the rms of the rest (``offset-free``),
with the compass's true mounting rotation about body z beside it. For a compass that is the autopilot's yaw
reference (the relative form) that rotation is not observable (it looks like a declination error; no
yaw the compass does not steer is there to see it), so its part of the offset is the same with and without
learning; the oracle knows it (docs/inflight.md, tenth pass). ``--set ap_kp_yaw=0.05`` gives the
autopilot a real EKF's slow compass pull (log171: 0.01-0.02 /s; benchmarks/autopilot_yaw_follow.py).

    .venv/bin/python benchmarks/ordinary_flight.py [--rates 1 10 50] [--seeds 0 1 2] [--theta-scales 1 6]
        [--set KEY=VALUE ...] [--no-crb]
"""

from __future__ import annotations

import argparse
import itertools
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from magcomp.adapters.config import Config
from magcomp.core.rotations import so3_log
from magcomp.service.demo import errors_after_learning, offset_split, oracle_replay, rms_after_learning
from magcomp.service.replay import replay_log

try:
    from theta_crb import theta_bounds
except ImportError:  # run as a module from elsewhere
    from benchmarks.theta_crb import theta_bounds


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rates", type=float, nargs="+", default=[1.0, 10.0, 50.0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="simulator knob")
    ap.add_argument("--compass", type=int, default=0, help="compass to score (1 with external_compass0=on)")
    ap.add_argument("--theta-scales", type=float, nargs="+", default=[1.0, 6.0],
                    help="theta's size: 1 = Table II's (67 mgauss, the hard case), 6 = a realistic "
                         "multirotor's (399 mgauss; log171's internal compasses: 484 / 790)")  # fmt: skip
    ap.add_argument("--no-crb", action="store_true", help="skip the Cramer-Rao columns (faster)")

    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate
    from magcomp.sim.config import apply_settings

    cfg = Config()
    args = ap.parse_args()
    print("theta rate  seed  causal  two-pass  uncorrected  oracle  causal/oracle  theta err %  "
          "CRB trusted %  CRB window %  CRB gyro %  | offset causal / two-pass, mount yaw z  "
          "offset-free causal / two-pass / oracle  status")  # fmt: skip
    worst: dict[tuple[float, float], list[tuple[float, ...]]] = {}
    for scale, rate, seed in itertools.product(args.theta_scales, args.rates, args.seeds):
        sim_cfg = apply_settings(SimConfig(scenario="ordinary", seed=seed),
                                 [f"telemetry_hz={rate:g}", f"theta_scale={scale:g}", *args.set])  # fmt: skip
        result = simulate(sim_cfg)
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "ordinary.tlog"
            write_tlog(result, path)
            causal = replay_log(path, cfg, keep_estimates=True)
            two = replay_log(path, cfg, keep_estimates=True, two_pass=True)
            orc = oracle_replay(result, path, Path(tmp) / "oracle", cfg)
        j = args.compass
        c_rms, raw_rms = rms_after_learning(result, causal.estimates, j)
        t_rms, _ = rms_after_learning(result, two.estimates, j)
        o_rms, _ = rms_after_learning(result, orc.estimates, j)
        # the constant part: a compass mounted rotated about body z, not observable in the relative form
        c_off, c_sd = offset_split(errors_after_learning(result, causal.estimates, j)[0])
        t_off, t_sd = offset_split(errors_after_learning(result, two.estimates, j)[0])
        _, o_sd = offset_split(errors_after_learning(result, orc.estimates, j)[0])
        u, _, vt = np.linalg.svd(result.true_calibration(j)[0])
        mount_z = float(np.degrees(so3_log(u @ vt))[2])
        comp = causal.summary["compasses"][j]
        th = np.asarray(comp["theta_mgauss"], dtype=float)
        tt = np.asarray(result.compasses[j].theta_mgauss, dtype=float)
        th_err = 100.0 * float(np.linalg.norm(th - tt) / np.linalg.norm(tt))
        nan = float("nan")
        crb = ({"trusted": nan, "window_field": nan, "gyro_window": nan} if args.no_crb
               else {b.model: b.pct_end for b in theta_bounds(result, rate, j)})  # fmt: skip
        worst.setdefault((scale, rate), []).append(
            (c_rms, t_rms, raw_rms, o_rms, th_err, c_sd / o_sd, t_sd / o_sd)
        )
        print(f"x{scale:<3g} {rate:4g}  {seed:4d}  {c_rms:6.2f}  {t_rms:8.2f}  {raw_rms:11.2f}  "
              f"{o_rms:6.2f}  {c_rms / o_rms:13.2f}  {th_err:11.1f}  {crb['trusted']:13.1f}  "
              f"{crb['window_field']:12.1f}  {crb['gyro_window']:10.1f}  | {c_off:+6.2f} / {t_off:+6.2f}, "
              f"{mount_z:+5.2f}  {c_sd:5.2f} / {t_sd:5.2f} / {o_sd:5.2f}  "
              f"{comp['status']}: {comp['why']}")  # fmt: skip
    print()
    print("theta  rate Hz  worst causal  worst two-pass  uncorrected  oracle  worst causal/oracle  "
          "worst theta err %  worst offset-free causal/oracle  two-pass/oracle")  # fmt: skip
    for (scale, rate), rows in worst.items():
        a = np.array(rows)
        print(f"x{scale:<4g} {rate:7g}  {a[:, 0].max():12.2f}  {a[:, 1].max():14.2f}  {a[:, 2].min():11.2f}  "
              f"{a[:, 3].max():6.2f}  {np.max(a[:, 0] / a[:, 3]):19.2f}  {a[:, 4].max():17.1f}  "
              f"{a[:, 5].max():31.2f}  {a[:, 6].max():15.2f}")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
