"""`magcomp replay`: run the whole pipeline over a tlog, DataFlash log or ULog as fast as the machine goes."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

from magcomp.commands import options

if TYPE_CHECKING:
    from magcomp.adapters.config import Config
    from magcomp.service.replay import ReplayReport


#: estimates handed to the viewer at once during a replay
VIEWER_BLOCK = 20_000


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from magcomp.adapters.rerun_viz import add_rerun_argument

    parser.add_argument(
        "log", metavar="LOG", help=".tlog, raw MAVLink, ArduPilot DataFlash .bin/.log, or PX4 .ulg"
    )
    parser.add_argument("--emit", metavar="OUT.tlog", help="write every published MAGCOMP_HEADING to a tlog")
    options.add_json(parser, "write a JSON summary: counts, theta")
    options.add_config(parser)
    options.add_state_dir(
        parser, "load and save calibration and theta here (default: none; a replay starts fresh)"
    )
    parser.add_argument(
        "--causal",
        action="store_true",
        help="one pass, exactly what the live daemon would have published (default without --state-dir: "
        "learn from the whole log first, then replay from the state it ends with)",
    )
    options.add_verbose(parser)
    add_rerun_argument(parser)


class _ViewerBlocks:
    """The viewer gets the primary compass's estimates in blocks while the replay runs (a 4 h log held
    every estimate: 1.9 GiB); the estimates are not kept."""

    def __init__(self, viz: Any, primary: int) -> None:
        self.viz = viz
        self.primary = primary
        self.block: list[Any] = []

    def add(self, est: Any) -> None:
        if est.mag_index == self.primary:
            self.block.append(est)
            if len(self.block) >= VIEWER_BLOCK:
                self.flush()

    def flush(self) -> None:
        if self.block:
            self.viz.log_estimates(self.block)
        self.block.clear()


def execute(args: argparse.Namespace) -> int:
    import signal

    from magcomp.adapters.config import load_config
    from magcomp.adapters.log_span import interruptible_scans
    from magcomp.adapters.rerun_viz import discard_viz, open_viz, serve_until_interrupt
    from magcomp.adapters.state_store import StateStore
    from magcomp.adapters.tlog_split import several_vehicles
    from magcomp.errors import InputError
    from magcomp.service.console import (
        check_distinct_outputs,
        check_output_path,
        primary_compass,
        setup_logging,
    )

    setup_logging("replay", args.verbose)
    inputs = (args.log, args.config)
    check_output_path(args.emit, "--emit", inputs)
    if args.emit and Path(args.emit).suffix.lower() in (".ulg", ".bin", ".log"):
        # a reader would take the file for that format by its name; only a tlog is written
        raise InputError(f"--emit {args.emit}: writes a MAVLink telemetry log; name it .tlog")
    check_output_path(args.json, "--json", inputs)
    check_distinct_outputs(emit=args.emit, json=args.json)
    cfg = load_config(args.config)
    store = StateStore(args.state_dir) if args.state_dir else None
    viz = None
    if args.rerun:
        viz = open_viz(args.rerun, live=False, recording_name=f"magcomp replay {args.log}")
    if viz is not None and viz.notice:
        print(viz.notice, flush=True)
    # ^C and SIGTERM only set a flag (a handler that did more could deadlock on a second signal); the
    # replay stops at its next batch and everything below (summary, --json, state) still happens
    stop_signals: list[int] = []

    def on_signal(signum: int, frame: object) -> None:
        stop_signals.append(signum)

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    viewer = _ViewerBlocks(viz, primary_compass(cfg.input.compasses)) if viz is not None else None
    try:
        with interruptible_scans(lambda: bool(stop_signals)):  # a repair's search through GiB stops too
            vehicles = several_vehicles(args.log)
            if vehicles:
                reports = _run_vehicles(args, cfg, store, viewer, lambda: bool(stop_signals), vehicles)
            else:
                reports = [_run(args, cfg, store, viewer, lambda: bool(stop_signals))]
    except BaseException:
        if viz is not None:
            discard_viz(viz)  # the log could not be read: no recording of nothing left behind
        raise
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    no_mag = not any(r.summary["counts"].get("mag") for r in reports)
    interrupted = any(r.interrupted for r in reports)
    if viz is not None and no_mag and not interrupted:
        discard_viz(viz)
        viz = None
    if viz is not None and not interrupted:
        serve_until_interrupt(viz, lambda m: print(m, flush=True))
    if viz is not None:
        viz.close()
    if interrupted:
        if stop_signals and stop_signals[0] == signal.SIGTERM:
            return 128 + signal.SIGTERM  # asked to stop: partial results written, the usual exit code
        raise KeyboardInterrupt  # the CLI's one line and exit code 130, after the partial results
    if no_mag:  # (the tlog writer leaves an --emit path as it was when nothing was written)
        raise InputError(f"{args.log}: no magnetometer messages in the log, nothing to correct")
    return 0


def _run(args: argparse.Namespace, cfg: Config, store: Any, viewer: _ViewerBlocks | None,
         should_stop: Any, shown: tuple[str, str | None] | None = None) -> ReplayReport:  # fmt: skip
    """The replay with a progress bar, then the summary (printed, --json, the viewer's extras). ``shown``:
    the log and --emit names printed (default: args.log and args.emit)."""
    from magcomp.service.console import Progress
    from magcomp.service.replay import replay_log

    texts: list[tuple[float, str]] = []
    t_first: list[float] = []

    def on_progress(t_s: float) -> None:  # message time reached, as seconds of log over both passes
        if not t_first:
            t_first.extend((t_s, t_s, 0.0))  # first time, latest time, seconds of earlier passes
        elif t_s < t_first[1] - 1.0:  # the second pass starts again at the log's beginning
            t_first[0], t_first[2] = t_s, t_first[2] + t_first[1] - t_first[0]
        t_first[1] = t_s
        bar.goto(t_first[2] + t_s - t_first[0])

    from magcomp.adapters.log_span import estimate_span_s

    span = estimate_span_s(args.log)
    passes = 1 if args.causal or store is not None else 2
    total = span * passes if span is not None else None
    with Progress(f"replay {Path(args.log).name}", total=total, unit="s of log") as bar:
        report = replay_log(args.log, cfg, store=store, emit=args.emit, keep_clouds=viewer is not None,
                            on_estimate=viewer.add if viewer is not None else None,
                            on_text=lambda t, m: texts.append((t, m)),
                            should_stop=should_stop, on_progress=on_progress,
                            two_pass=not args.causal and store is None)  # fmt: skip
    if viewer is not None:
        viewer.flush()
    log_name, emit_name = shown if shown is not None else (args.log, args.emit)
    return _finish(args, report, cfg, viewer.viz if viewer is not None else None, texts, log_name, emit_name)


def _finish(args: argparse.Namespace, report: ReplayReport, cfg: Config, viz: Any,
            texts: list[tuple[float, str]], log_name: str, emit_name: str | None,
            ) -> ReplayReport:  # fmt: skip
    """Print the summary and write --json; hand the estimates to the viewer."""
    from magcomp.service.console import (
        SKIP_KEYS,
        earth_field_line,
        format_counts,
        primary_compass,
        summary_lines,
        write_json,
    )

    counts = report.counts
    passes = report.summary.get("passes", 1)
    how = "two passes: learned from the whole log, then replayed" if passes == 2 else "one pass, causal"
    print(f"{log_name}: {report.n_estimates} headings in {report.wall_s:.2f} s ({how})")
    for line in summary_lines(report.summary):
        print(line)
    earth = earth_field_line(report.summary)
    if earth is not None:
        print(earth)
    print(f"skipped or absorbed: {format_counts(counts, SKIP_KEYS)}")
    for w in report.summary["warnings"]:
        print(f"warning: {w}")
    if report.interrupted:
        if math.isfinite(report.t_last_s):
            print(f"interrupted: the summary covers the log up to {report.t_last_s:.1f} s", flush=True)
        else:  # stopped in the first pass (it reads the whole log before any heading) or before any sample
            print("interrupted before the first heading: nothing to report", flush=True)
    if emit_name and report.emitted == 0:  # (the tlog writer leaves the path as it was)
        print(f"nothing written to {emit_name}")
    elif emit_name:
        print(f"wrote {report.emitted} MAGCOMP_HEADING to {emit_name}")
    if args.json:
        write_json(args.json, report.to_json())
    if viz is not None:
        primary = primary_compass(cfg.input.compasses)
        if primary in report.clouds and len(report.clouds[primary][0]):
            viz.log_calibration_cloud(*report.clouds[primary])
        for t, m in texts:
            viz.log_text(t, m)
    return report


def _run_vehicles(args: argparse.Namespace, cfg: Config, store: Any, viewer: _ViewerBlocks | None,
                  should_stop: Any, vehicles: list[tuple[int, int]]) -> list[ReplayReport]:  # fmt: skip
    """A log of several vehicles: each sender's frames replayed on their own, as ``run`` follows each one
    live (:mod:`magcomp.adapters.tlog_split`), with the state of each in the state directory. --emit gets
    every vehicle's MAGCOMP_HEADING merged in time order, --json one summary per vehicle, the viewer the
    first vehicle's estimates."""
    import tempfile

    from magcomp.adapters.tlog_split import merge_tlogs, split_by_vehicle
    from magcomp.service.console import write_json

    names = ", ".join(f"system {s} component {c}" for s, c in vehicles)
    print(f"{args.log}: {len(vehicles)} vehicles ({names}), each replayed on its own", flush=True)
    reports: list[ReplayReport] = []
    emits: list[Path] = []
    docs: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="magcomp-vehicles-") as tmp:
        for (system, component), part in split_by_vehicle(args.log, tmp, vehicles).items():
            one = argparse.Namespace(**vars(args))
            one.log, one.json = str(part), None
            one.emit = str(Path(tmp) / f"emit.sys{system}.comp{component}.tlog") if args.emit else None
            label = f"{args.log} (system {system} component {component})"
            report = _run(one, cfg, store, viewer if not reports else None, should_stop, (label, None))
            reports.append(report)
            docs.append({**report.to_json(), "log": args.log, "system_id": system, "component_id": component})
            if one.emit is not None and Path(one.emit).exists():
                emits.append(Path(one.emit))
            if report.interrupted:
                break
        if args.emit:
            n = sum(r.emitted for r in reports)
            if merge_tlogs(emits, Path(args.emit)):
                print(f"wrote {n} MAGCOMP_HEADING of {len(reports)} vehicles to {args.emit}")
            else:
                print(f"nothing written to {args.emit}")
    if args.json:
        write_json(args.json, {"log": args.log, "vehicles": docs})
    return reports

