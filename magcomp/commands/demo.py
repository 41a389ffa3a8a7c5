"""`magcomp demo`: the simulator as a fake flight controller on loopback UDP, the daemon attached to it."""

from __future__ import annotations

import argparse
import math
from typing import Any

from magcomp.commands import options


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from magcomp.adapters.rerun_viz import add_rerun_argument

    parser.add_argument("--duration", type=float, default=90.0, metavar="S",
                        help="simulated seconds of the paper's experiment (default 90)")  # fmt: skip
    parser.add_argument("--speed", type=float, default=10.0, metavar="X",
                        help="play the simulated flight at X times real time (default 10)")  # fmt: skip
    parser.add_argument("--seed", type=int, default=0, help="simulator seed (default 0)")
    options.add_config(parser, "TOML configuration for the daemon")
    options.add_state_dir(parser, "keep state here (default: a fresh temporary one)")
    options.add_json(parser, "write the summary")
    options.add_verbose(parser)
    add_rerun_argument(parser)


def execute(args: argparse.Namespace) -> int:
    import tempfile

    import numpy as np

    from magcomp.adapters.config import load_config
    from magcomp.adapters.rerun_viz import open_viz, serve_until_interrupt
    from magcomp.adapters.state_store import StateStore
    from magcomp.service.console import check_output_path, setup_logging, write_json
    from magcomp.service.demo import run_demo

    _check_arguments(args)
    check_output_path(args.json, "--json", (args.config,))
    setup_logging("demo", args.verbose)
    cfg = load_config(args.config)
    viz = open_viz(args.rerun, live=True, recording_name="magcomp demo")
    if viz.notice:
        print(viz.notice, flush=True)
    feed = _TruthFeed(viz)
    with tempfile.TemporaryDirectory(prefix="magcomp-demo-") as tmp:
        store = StateStore(args.state_dir or tmp)
        print(f"demo: simulating {args.duration:g} s of the paper's experiment, played at {args.speed:g}x "
              "to the daemon over loopback UDP ...", flush=True)  # fmt: skip
        try:
            report, result, _ = run_demo(
                duration_s=args.duration, speed=args.speed, seed=args.seed, cfg=cfg, store=store,
                on_estimate=feed.on_estimate, on_text=viz.log_text, on_sim=feed.on_sim,
            )  # fmt: skip
            feed.send(np.inf)
            if 0 in report.clouds and len(report.clouds[0][0]):
                viz.log_calibration_cloud(*report.clouds[0])
            # Fig. 7: the simulator's true current-induced bias against throttle^2 (the demo has no stationary
            # throttle sweep to measure it), with the line of the daemon's final theta-hat (eq. (11))
            thr = np.asarray(result.samples.throttle_01, dtype=float)
            viz.log_bias_fit(
                thr**2, result.truth_at_samples(result.bias_mgauss)[0], report.theta_mgauss.get(0)
            )
        finally:
            if not viz.keeps_serving:
                viz.close()
    for line in report.lines():
        print(line)
    if args.json:
        write_json(args.json, _summary(report))
    if viz.keeps_serving:
        message = f"the viewer keeps serving at {viz.url}; press ^C to stop"
        serve_until_interrupt(viz, lambda m: print(m, flush=True), message)
        viz.close()
    return 0


def _check_arguments(args: argparse.Namespace) -> None:
    from magcomp.errors import InputError

    if not 60.0 <= args.duration <= 3600.0:
        raise InputError(
            f"--duration must be in [60, 3600] s (the hand rotation must last long enough to calibrate), "
            f"got {args.duration:g}"
        )
    if not 0.1 <= args.speed <= 50.0:
        raise InputError(f"--speed must be in [0.1, 50], got {args.speed}")
    if args.seed < 0:
        raise InputError(f"--seed must be >= 0, got {args.seed}")


class _TruthFeed:
    """The simulated truth, fed to the viewer as the run goes: the errors against truth show live."""

    def __init__(self, viz: Any) -> None:
        self.viz = viz
        self.until = -math.inf
        self.samples: Any = None
        self.heading: Any = None
        self.sent = 0

    def on_sim(self, result: Any) -> None:
        import numpy as np

        self.viz.log_reference_theta(None, [float(x) for x in result.compasses[0].theta_mgauss])
        s = result.samples
        yaw = result.euler_rad[s.truth_index, 2]
        self.samples, self.heading, self.sent = s, (np.degrees(yaw) - result.declination_deg) % 360.0, 0

    def send(self, until_s: float) -> None:
        """Truth heading and power up to ``until_s`` (message time)."""
        import numpy as np

        self.until = until_s
        if self.samples is None:
            return
        s, i = self.samples, self.sent
        end = int(np.searchsorted(s.t_s, until_s, side="right"))
        if end > i:
            self.viz.log_truth_heading(s.t_s[i:end], self.heading[i:end])
            self.viz.log_power(s.t_s[i:end], s.throttle_01[i:end], s.current_a[i:end], s.voltage_v[i:end])
            self.sent = end

    def on_estimate(self, est: Any) -> None:
        if est.mag_index == 0:
            if est.t_s > self.until - 0.5:
                self.send(est.t_s + 1.0)
            self.viz.log_estimate(est)


def _summary(report: Any) -> dict[str, Any]:
    """The ``--json`` summary of a demo run."""
    return {
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
