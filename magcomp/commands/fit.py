"""`magcomp fit LOG`: offline least squares of theta on the log's stationary throttle sweep (Table II).

Finds (or takes from --start/--end) the window where the vehicle is at rest while the throttle moves,
interpolates the throttle onto the magnetometer times, fits eq. (12) per axis with eqs. (14)-(15), and
prints a table like the paper's Table II (in mgauss, in the magnetometer's own frame). ``--json OUT``
writes the same numbers.
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from magcomp.errors import InputError, MagcompError

if TYPE_CHECKING:
    import numpy as np

    from magcomp.core.bias_fit import OfflineFit
    from magcomp.core.types import LogData

MAX_THROTTLE_GAP_S = 1.0  # a magnetometer sample farther than this from any throttle sample is dropped


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", metavar="LOG", help="tlog, DataFlash .bin/.log or PX4 .ulg")
    parser.add_argument("--json", metavar="OUT", help="also write the results as JSON to OUT")
    parser.add_argument("--start", type=float, metavar="S", help="window start, s on the log's clock")
    parser.add_argument("--end", type=float, metavar="S", help="window end, s on the log's clock")
    parser.add_argument("--mag", type=int, metavar="N", help="compass index (default: the lowest in the log)")
    parser.add_argument(
        "--throttle-source",
        default="auto",
        metavar="SRC",
        help="auto (default), motors, servo:N, rc:N, vfr_hud or ctun",
    )
    parser.add_argument(
        "--monte-carlo", type=int, default=1000, metavar="N", help="refits for the benchmark R^2 (1000)"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the Monte-Carlo benchmark (default 0)")
    from magcomp.service.handover import add_save_state_arguments

    add_save_state_arguments(parser)
    parser.epilog = (
        "Without --start/--end the window is found automatically: smoothed gyro below 0.05 rad/s, attitude "
        "within 3 deg, throttle spanning at least 0.3 for at least 5 s."
    )


@dataclass(frozen=True)
class FitReport:
    """What `magcomp fit` prints and writes: the fit plus where it came from."""

    fit: OfflineFit
    t_start_s: float
    t_end_s: float
    mag_index: int
    throttle_source: str
    source: str


def _pick_mag(log: LogData, mag_index: int | None) -> int:
    present = sorted(i for i, s in log.mag.items() if len(s) > 0)
    if not present and mag_index is not None:
        raise InputError(f"{log.source}: no compass {mag_index} in the log")
    if not present:
        raise InputError(f"{log.source}: no magnetometer samples in the log")
    if mag_index is None:
        return present[0]
    if mag_index not in present:
        raise InputError(f"{log.source}: no compass {mag_index} in the log (have {present})")
    return mag_index


MAX_MONTE_CARLO = 100_000


def fit_log(
    log: LogData,
    mag_index: int | None = None,
    start_s: float | None = None,
    end_s: float | None = None,
    n_monte_carlo: int = 1000,
    rng: np.random.Generator | None = None,
) -> FitReport:
    """Select the window, align throttle to the magnetometer and run :func:`fit_bias_offline`."""
    import numpy as np

    from magcomp.core.bias_fit import fit_bias_offline
    from magcomp.core.segments import SegmentParams, find_sweep_in_log

    idx = _pick_mag(log, mag_index)
    mag = log.mag[idx]
    thr = log.throttle_01
    finite = np.isfinite(thr.values)
    thr_t, thr_v = thr.t_s[finite], thr.values[finite]
    if thr_t.shape[0] < 2 and log.throttle_source and (start_s is not None or end_s is not None):
        # a window cut while reading (load_log(window=...)) that holds no throttle: the whole log's messages
        first = [float(a[0]) for a in (mag.t_s, thr_t) if a.size]
        last = [float(a[-1]) for a in (mag.t_s, thr_t) if a.size]
        t0 = start_s if start_s is not None else max(first, default=-math.inf)
        t1 = end_s if end_s is not None else min(last, default=math.inf)
        if not t1 > t0:
            raise InputError(f"empty window: --start {t0:.6g} s is not before --end {t1:.6g} s")
        raise MagcompError(f"{log.source}: only 0 magnetometer samples with throttle in {t0:.2f}-{t1:.2f} s")
    if thr_t.shape[0] < 2:
        raise MagcompError(
            f"{log.source}: no throttle data (source {log.throttle_source or 'auto'}); try --throttle-source"
        )
    if start_s is None and end_s is None:
        found = find_sweep_in_log(log)
        if found is None:
            p = SegmentParams()
            raise MagcompError(
                f"{log.source}: no stationary throttle sweep found (needs the vehicle at rest, gyro below "
                f"{p.max_rate_rad_s} rad/s and attitude within "
                f"{math.degrees(p.max_attitude_change_rad):.0f} deg, "
                f"while the throttle spans >= {p.min_throttle_span} for >= {p.min_duration_s:.0f} s); "
                "pass --start/--end to choose a window"
            )
        t0, t1 = found
    else:
        t0 = start_s if start_s is not None else max(float(mag.t_s[0]), float(thr_t[0]))
        t1 = end_s if end_s is not None else min(float(mag.t_s[-1]), float(thr_t[-1]))
        if not t1 > t0:
            raise InputError(f"empty window: --start {t0:.6g} s is not before --end {t1:.6g} s")
    sel = (mag.t_s >= t0) & (mag.t_s <= t1) & (mag.t_s >= thr_t[0]) & (mag.t_s <= thr_t[-1])
    t_mag = mag.t_s[sel]
    # drop magnetometer samples that fall in a hole of the throttle stream
    k = np.clip(np.searchsorted(thr_t, t_mag), 1, len(thr_t) - 1)
    near = np.minimum(np.abs(thr_t[k] - t_mag), np.abs(t_mag - thr_t[k - 1]))
    ok = near <= MAX_THROTTLE_GAP_S
    t_mag = t_mag[ok]
    field = mag.values[sel][ok]
    if t_mag.shape[0] < 10:
        raise MagcompError(
            f"{log.source}: only {t_mag.shape[0]} magnetometer samples with throttle in {t0:.2f}-{t1:.2f} s"
        )
    throttle_at_mag = np.interp(t_mag, thr_t, thr_v)
    fit = fit_bias_offline(
        throttle_at_mag, field, rng=rng or np.random.default_rng(0), n_monte_carlo=n_monte_carlo
    )
    return FitReport(fit, float(t0), float(t1), idx, log.throttle_source, log.source)


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def report_json(rep: FitReport) -> dict[str, Any]:
    """The JSON document: per-axis lists of 3 (mgauss, magnetometer frame) plus n and the window."""
    f = rep.fit
    return {
        "theta": [_num(v) for v in f.theta_mgauss],
        "theta_std": [_num(v) for v in f.theta_std_mgauss],
        "sigma": [_num(v) for v in f.sigma_mgauss],
        "r2": [_num(v) for v in f.r2],
        "snr_db": [_num(v) for v in f.snr_db],
        "benchmark_r2": [
            [_num(m), _num(s)] for m, s in zip(f.benchmark_r2_mean, f.benchmark_r2_two_sd, strict=True)
        ],
        "n": int(f.n),
        "t_start_s": rep.t_start_s,
        "t_end_s": rep.t_end_s,
    }


def format_table(rep: FitReport) -> str:
    """Table II layout, in mgauss."""
    f = rep.fit
    lines = [
        f"{rep.source}: compass {rep.mag_index}, throttle {rep.throttle_source or '?'}, "
        f"window {rep.t_start_s:.2f}-{rep.t_end_s:.2f} s, n = {f.n}",
        f"{'axis':<5}{'theta [mG]':>12}{'+-1sd':>8}{'sigma [mG]':>12}{'R^2':>8}{'SNR [dB]':>10}"
        f"{'benchmark R^2':>20}",
    ]
    for i, axis in enumerate("xyz"):
        bench = f"{f.benchmark_r2_mean[i]:.3f} +- {f.benchmark_r2_two_sd[i]:.3f}"
        lines.append(
            f"{axis:<5}{f.theta_mgauss[i]:>12.2f}{f.theta_std_mgauss[i]:>8.2f}{f.sigma_mgauss[i]:>12.2f}"
            f"{f.r2[i]:>8.3f}{f.snr_db[i]:>10.1f}{bench:>20}"
        )
    lines.append("theta: bias at full throttle (eq. (11)); benchmark: Monte-Carlo mean +- 2 sd (Table II)")
    return "\n".join(lines)


def execute(args: argparse.Namespace) -> int:
    import numpy as np

    from magcomp.adapters.columns import Window
    from magcomp.adapters.mavlink_source import load_log
    from magcomp.service.console import check_output_path

    if not 0 <= args.monte_carlo <= MAX_MONTE_CARLO:
        raise InputError(f"--monte-carlo must be in [0, {MAX_MONTE_CARLO}], got {args.monte_carlo}")
    if args.seed < 0:
        raise InputError(f"--seed must be >= 0, got {args.seed}")
    if args.mag is not None and args.mag < 0:
        raise InputError(f"--mag must be a compass index >= 0, got {args.mag}")
    for name, value in (("--start", args.start), ("--end", args.end)):
        if value is not None and not math.isfinite(value):
            raise InputError(f"{name} must be a finite time in s on the log's clock, got {value}")
    path = Path(args.log)
    if not str(args.log).strip():
        raise InputError("LOG: the path is empty")
    if not path.exists():
        raise InputError(f"{path}: no such file")
    check_output_path(args.json, "--json", (args.log, args.config))
    from magcomp.service.console import Busy, reading_progress

    if args.save_state:
        from magcomp.adapters.state_store import StateStore
        from magcomp.service.handover import handover_config, save_learned_state

        cfg = handover_config(args.config, args.throttle_source)
        for line in save_learned_state(path, cfg, StateStore(args.save_state)):
            print(line, flush=True)
    # --start/--end: only the window is kept while reading (plus MAX_THROTTLE_GAP_S and one sample each side,
    # so that the throttle interpolated at the window's edges is the one the whole log gives)
    window = Window.around(args.start, args.end, MAX_THROTTLE_GAP_S)
    with reading_progress(f"fit: reading {path.name}", path) as on_progress:
        log = load_log(path, throttle_source=args.throttle_source, mag_index=args.mag, window=window,
                       on_progress=on_progress)  # fmt: skip
    from magcomp.adapters.config import load_config
    from magcomp.service.align import gate_log_inputs

    # the pipeline's magnetometer gates: a clipped (saturated) or corrupt (jump) sample is not a field
    dropped = gate_log_inputs(log, load_config(args.config).input.saturation_mgauss)
    try:
        with Busy(f"fit: least squares and {args.monte_carlo} Monte-Carlo refits"):
            rep = fit_log(
                log,
                mag_index=args.mag,
                start_s=args.start,
                end_s=args.end,
                n_monte_carlo=args.monte_carlo,
                rng=np.random.default_rng(args.seed),
            )
    except MagcompError as exc:
        if not args.save_state or args.json or isinstance(exc, InputError):
            raise
        # an ordinary flight has no bench sweep: the state saved above is what was asked for
        print(f"note: no offline fit (Table II): {exc}")
        return 0
    print(format_table(rep))
    if any(dropped.values()):
        said = ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in dropped.items() if v)
        print(f"dropped before the fit: {said}")
    if args.json:
        from magcomp.adapters.files import write_file

        doc = {**report_json(rep), "dropped": dropped}
        write_file(args.json, (json.dumps(doc, indent=2) + "\n").encode())
    return 0
