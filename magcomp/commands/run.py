"""`magcomp run`: attach to a live flight-controller link and publish corrected headings (MAGCOMP_HEADING)."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any

from magcomp.commands import options

if TYPE_CHECKING:
    from magcomp.adapters.rerun_viz import Viz
    from magcomp.adapters.state_store import StateStore
    from magcomp.service.daemon import Daemon, DaemonReport

MAX_DURATION_S = 1e8  # about three years; longer overflows the platform's timer


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from magcomp.adapters.rerun_viz import add_rerun_argument

    parser.add_argument(
        "--master",
        required=True,
        metavar="URL",
        help="the flight controller's link: udpin:0.0.0.0:14550 (MAGCOMP_HEADING goes back to the "
        "sender), udpout:HOST:PORT, tcp:HOST:PORT, tcpin:0.0.0.0:PORT, /dev/ttyACM0:115200 or "
        "serial:/dev/ttyUSB0:57600",
    )
    parser.add_argument(
        "--out", action="append", default=[], metavar="URL", help="also publish on this link (repeatable)"
    )
    options.add_config(parser)
    options.add_state_dir(
        parser, "calibration and theta per vehicle and compass (default: $XDG_STATE_HOME/magcomp)"
    )
    parser.add_argument(
        "--signing-key",
        metavar="FILE",
        help="MAVLink 2 signing: sign what is sent and read only frames signed with this key (32 bytes, "
        "64 hex digits or a passphrase)",
    )
    options.add_json(parser, "write a summary when the run ends")
    parser.add_argument(
        "--duration", type=float, metavar="S", help="stop after S seconds (default: run until ^C)"
    )
    options.add_verbose(parser)
    add_rerun_argument(parser)


def feed_hint(master: str) -> str | None:
    """For a master that listens (udpin:, tcpin:), one line on how to send it a vehicle's MAVLink; None for
    a master that connects out (it needs no feeding)."""
    text = master.strip()
    for prefix, proto, sim in (("udpin:", "udp", "udpout"), ("tcpin:", "tcp", "tcpout")):
        if text.startswith(prefix):
            host, _, port = text[len(prefix) :].rpartition(":")
            here = "127.0.0.1" if host in ("0.0.0.0", "", "::") else host
            return (
                f"waiting for MAVLink on {proto} port {port}. Send it a vehicle's stream: MAVProxy "
                f"`mavproxy.py --master /dev/ttyACM0 --out {proto}:{here}:{port}`, ArduPilot SITL "
                f"`sim_vehicle.py --out {proto}:{here}:{port}`, a ground station's MAVLink forwarding to "
                f"{here}:{port}; or, without hardware, `magcomp simulate --link {sim}:{here}:{port}`"
            )
    return None


def execute(args: argparse.Namespace) -> int:
    import signal
    import threading

    from magcomp.adapters.config import load_config
    from magcomp.adapters.rerun_viz import open_viz
    from magcomp.adapters.state_store import StateStore
    from magcomp.errors import InputError
    from magcomp.service.console import check_output_path, default_state_dir, setup_logging, write_json
    from magcomp.service.daemon import check_link_url

    if args.duration is not None and not 0 < args.duration <= MAX_DURATION_S:
        raise InputError(f"--duration must be in (0, {MAX_DURATION_S:.0f}] s, got {args.duration:g}")
    check_link_url(args.master, "--master")
    for url in args.out:
        check_link_url(url, "--out")
    check_output_path(args.json, "--json", (args.config,))
    setup_logging("run", args.verbose)
    cfg = load_config(args.config)
    store = StateStore(args.state_dir or default_state_dir())
    viz = open_viz(args.rerun, live=True, recording_name="magcomp run")
    if viz.notice:
        print(viz.notice, flush=True)
    hint = feed_hint(args.master)
    if hint is not None:
        print(hint, flush=True)
    daemon = _daemon(args, cfg, store, viz)

    def on_signal(signum: int, frame: object) -> None:
        daemon.request_stop()  # a flag only: a second signal during the first cannot deadlock

    # the handlers stay until the summary is written: a second ^C or SIGTERM while the state is saved
    # and the summary written changes nothing
    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    timer = threading.Timer(args.duration, daemon.stop) if args.duration else None
    if timer is not None:
        timer.daemon = True
        timer.start()
    try:
        try:
            report = daemon.run()
        finally:
            if timer is not None:
                timer.cancel()
            viz.close()
        _print_report(report)
        if args.json:
            write_json(args.json, report.to_json())
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    if report.connects == 0:
        raise InputError(f"never connected to {args.master}: {daemon.last_error or 'no link'}")
    return 0


def _daemon(args: argparse.Namespace, cfg: Any, store: StateStore, viz: Viz) -> Daemon:
    """The daemon of ``run``: the primary compass's estimates and battery 0's power to the viewer."""
    from magcomp.core.types import HeadingEstimate, PowerSample
    from magcomp.service.console import primary_compass
    from magcomp.service.daemon import Daemon

    primary = primary_compass(cfg.input.compasses)

    def show(est: HeadingEstimate) -> None:
        if est.mag_index == primary:
            viz.log_estimate(est)

    def power(s: PowerSample) -> None:
        if s.battery_index == 0:  # beside the throttle, which comes with the estimates
            viz.log_power(s.t_s, float("nan"), s.current_a, s.voltage_v)

    key = None
    if args.signing_key:
        from magcomp.adapters.signing import read_signing_key

        key = read_signing_key(args.signing_key)
    return Daemon(args.master, cfg, outs=args.out, store=store, on_estimate=show, on_text=viz.log_text,
                  on_power=power, signing_key=key)  # fmt: skip


def _print_report(report: DaemonReport) -> None:
    """The end of a run on the console: the summary, the Earth field, foreign datagrams and latency."""
    from magcomp.service.console import earth_field_line, summary_lines

    for line in summary_lines(report.summary):
        print(line)
    earth = earth_field_line(report.summary)
    if earth is not None:
        print(earth)
    foreign = report.source_counts.get("foreign_datagrams", 0)
    if foreign:
        print(f"ignored {foreign} datagrams from addresses other than the flight controller's")
    lat = report.latency_ms
    if lat:
        print(f"latency sample -> MAGCOMP_HEADING: p50 {lat['p50']:.2f} ms, p99 {lat['p99']:.2f} ms")
