"""`magcomp demo`: the simulator as a fake flight controller on loopback UDP, the daemon attached to it."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from magcomp.adapters.rerun_viz import add_rerun_argument

    parser.add_argument("--duration", type=float, default=90.0, metavar="S",
                        help="simulated seconds of the paper's experiment (default 90)")  # fmt: skip
    parser.add_argument("--speed", type=float, default=10.0, metavar="X",
                        help="play the simulated flight at X times real time (default 10)")  # fmt: skip
    parser.add_argument("--seed", type=int, default=0, help="simulator seed (default 0)")
    parser.add_argument("--config", metavar="FILE", help="TOML configuration for the daemon")
    parser.add_argument("--state-dir", metavar="DIR", help="keep state here (default: a fresh temporary one)")
    parser.add_argument("--json", metavar="SUMMARY.json", help="write the summary")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug log lines")
    add_rerun_argument(parser)


def execute(args: argparse.Namespace) -> int:
    import tempfile

    import numpy as np

    from magcomp.adapters.config import load_config
    from magcomp.adapters.rerun_viz import open_viz
    from magcomp.adapters.state_store import StateStore
    from magcomp.errors import InputError
    from magcomp.service.console import setup_logging, write_json
    from magcomp.service.demo import run_demo

    if not 60.0 <= args.duration <= 3600.0:
        raise InputError(
            f"--duration must be in [60, 3600] s (the hand rotation must last long enough to calibrate), "
            f"got {args.duration:g}"
        )
    if not 0.1 <= args.speed <= 50.0:
        raise InputError(f"--speed must be in [0.1, 50], got {args.speed}")
    setup_logging("demo", args.verbose)
    cfg = load_config(args.config)
    viz = open_viz(args.rerun, live=True, recording_name="magcomp demo")
    if viz.notice:
        print(viz.notice, flush=True)

    def on_sim(result: object) -> None:
        truth = [float(x) for x in result.compasses[0].theta_mgauss]  # type: ignore[attr-defined]
        viz.log_reference_theta(None, truth)

    with tempfile.TemporaryDirectory(prefix="magcomp-demo-") as tmp:
        store = StateStore(args.state_dir or tmp)
        print(f"demo: simulating {args.duration:g} s of the paper's experiment, played at {args.speed:g}x "
              "to the daemon over loopback UDP ...", flush=True)  # fmt: skip
        try:
            report, result, _ = run_demo(
                duration_s=args.duration, speed=args.speed, seed=args.seed, cfg=cfg, store=store,
                on_estimate=lambda e: viz.log_estimate(e) if e.mag_index == 0 else None,
                on_text=viz.log_text, on_sim=on_sim,
            )  # fmt: skip
            s = result.samples
            yaw = result.euler_rad[s.truth_index, 2]
            viz.log_truth_heading(s.t_s, (np.degrees(yaw) - result.declination_deg) % 360.0)
            viz.log_power(s.t_s, s.throttle_01, s.current_a, s.voltage_v)
            if 0 in report.clouds and len(report.clouds[0][0]):
                viz.log_calibration_cloud(*report.clouds[0])
        finally:
            if not viz.keeps_serving:
                viz.close()
    for line in report.lines():
        print(line)
    if args.json:
        doc = {
            "duration_s": report.duration_s,
            "speed": report.speed,
            "wall_s": report.wall_s,
            "sent": report.sent,
            "received_back": report.received_back,
            "estimates": report.estimates,
            "theta_mgauss": report.theta_mgauss,
            "theta_truth_mgauss": report.theta_truth_mgauss,
            "segments": [vars(x) for x in report.segments],
            "daemon": report.daemon.to_json(),
        }
        write_json(args.json, doc)
    if viz.keeps_serving:
        print(f"the viewer keeps serving at {viz.url}; press ^C to stop", flush=True)
        try:
            import time

            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass
        viz.close()
    return 0
