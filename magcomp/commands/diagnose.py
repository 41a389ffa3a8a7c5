"""`magcomp diagnose LOG`: compare the model with a measured log, name what it misses, extend it,
measure the gain.

Reads a tlog, an ArduPilot DataFlash .bin/.log or a PX4 .ulg; writes a JSON document (``--json``) and a
Markdown report with PNG plots (``--report``); prints a short summary. A simulated log's truth
(``LOG.truth.npz`` beside it, or ``--truth``) gives the heading reference.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", metavar="LOG", help=".tlog, ArduPilot DataFlash .bin/.log, or PX4 .ulg")
    parser.add_argument("--json", metavar="OUT.json", help="write the diagnosis as JSON")
    parser.add_argument("--report", metavar="OUT.md", help="write a Markdown report with PNG plots beside it")
    parser.add_argument("--mag-index", type=int, default=None, help="primary compass (default: the first)")
    parser.add_argument(
        "--throttle-source",
        default="auto",
        help="servo:N, motors, rc:N, vfr_hud, ctun or auto (default auto)",
    )
    parser.add_argument(
        "--truth",
        metavar="FILE.truth.npz",
        help="heading reference from a simulation's truth (default: LOG.truth.npz if present)",
    )
    parser.add_argument(
        "--rerun",
        metavar="MODE",
        nargs="?",
        const="auto",
        default=None,
        help="show the primary compass in Rerun: spawn, serve, connect[=URL], save=PATH.rrd, auto",
    )


def _truth_reference(args: argparse.Namespace) -> tuple[Any, Any] | None:
    import numpy as np

    from magcomp.errors import InputError

    path = Path(args.truth) if args.truth else None
    if path is None:
        p = Path(args.log)
        cand = p.with_name((p.stem if p.suffix else p.name) + ".truth.npz")
        path = cand if cand.is_file() else None
    if path is None:
        return None
    try:
        with np.load(path) as z:
            return np.asarray(z["t_s"], dtype=float), np.asarray(z["euler_rad"], dtype=float)[:, 2]
    except (OSError, KeyError, ValueError) as exc:
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
        if isinstance(exc, ValueError) and "pickle" in str(exc):
            why = "not a NumPy .npz file"
        elif isinstance(exc, KeyError):
            why = f"no array {exc} in it (not a magcomp simulate truth file)"
        raise InputError(f"cannot read the truth {path}: {why}") from exc


def log_events(path: str) -> list[tuple[float, str]]:
    """Timestamped events of a log (messages, mode changes, arming, parameter sets), for the step report."""
    suffix = Path(path).suffix.lower()
    if suffix not in (".bin", ".log", ".tlog"):
        return []
    import contextlib
    import io

    from pymavlink import mavutil

    rows: list[tuple[float | None, float, str]] = []  # (boot time or None, reader timestamp, text)
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            m = mavutil.mavlink_connection(path)
    except Exception:  # events are a nicety; a reader hiccup must not stop the diagnosis
        return []
    try:
        t_first_param: float | None = None
        types = ["MSG", "EV", "MODE", "ERR", "PARM", "ARM", "STATUSTEXT"]
        while True:
            msg = m.recv_match(type=types)
            if msg is None:
                break
            d = msg.to_dict()
            stamp = float(getattr(msg, "_timestamp", 0.0))
            boot: float | None = None
            if "TimeUS" in d:
                boot = d["TimeUS"] * 1e-6
            elif "TimeMS" in d:
                boot = d["TimeMS"] * 1e-3
            elif "time_boot_ms" in d:
                boot = d["time_boot_ms"] * 1e-3
            kind = msg.get_type()
            if kind == "PARM":
                ref = boot if boot is not None else stamp
                t_first_param = ref if t_first_param is None else t_first_param
                if ref - t_first_param < 1.0:
                    continue  # the start-up parameter dump is not an event
                text = f"PARM {d.get('Name')}={d.get('Value')}"
            elif kind in ("MSG", "STATUSTEXT"):
                text = f"{kind} {d.get('Message', d.get('text', ''))}".strip()
            else:
                skip = ("mavpackettype", "TimeUS", "TimeMS")
                text = kind + " " + " ".join(f"{k}={v}" for k, v in d.items() if k not in skip)
            rows.append((boot, stamp, text))
    except Exception:  # events are a nicety; a reader hiccup must not stop the diagnosis
        pass
    finally:
        m.close()
    # messages without their own boot time (old MSG/EV) get it from the reader's clock offset
    offsets = [stamp - boot for boot, stamp, _ in rows if boot is not None]
    off = sorted(offsets)[len(offsets) // 2] if offsets else None
    out = []
    for boot, stamp, text in rows:
        if boot is None and off is None:
            continue
        out.append((boot if boot is not None else stamp - (off or 0.0), text))
    return out


def _summary(j: dict[str, Any]) -> list[str]:
    lines = []
    for c in j["compasses"]:
        names = (
            ", ".join(
                f"{f['effect']} "
                + " ".join(f"{k}={v}" for k, v in f["params"].items() if not isinstance(v, list))
                for f in c["findings"]
            )
            or "no finding"
        )
        lines.append(
            f"compass {c['index']}: theta {c['theta']} mgauss; residual {c['residual_rms_baseline']} -> "
            f"{c['residual_rms_extended']} mgauss; {names}"
        )
        if c["suspects"]:
            s = c["suspects"][0]
            lines.append(
                f"  the remaining residual follows {s['signal']} best "
                f"(lag {s['lag_s']} s, {100 * (s['r2'] or 0.0):.1f} % of its variance)"
            )
    g = j["gain"]
    if "heading_error_rms_deg" in g:
        h = g["heading_error_rms_deg"]
        lines.append(
            f"heading error rms vs {g['heading_reference']}: uncompensated {h['uncompensated']} deg, "
            f"paper {h['paper']} deg, extended {h['extended']} deg"
        )
    return lines


def _show_in_rerun(mode: str, d: Any, reference: tuple[Any, Any] | None) -> None:
    import numpy as np

    from magcomp.adapters.rerun_viz import open_viz, serve_until_interrupt
    from magcomp.core.types import FLAG_CALIBRATED, HeadingEstimate
    from magcomp.diagnosis.engine import compass_yaw_rad
    from magcomp.diagnosis.report import _earth_part

    c = d.compass(d.primary)
    data = c.data
    viz = open_viz(mode, live=False, recording_name=f"magcomp diagnose {d.log_source}")
    if viz.notice:
        print(viz.notice, flush=True)
    yaw_e = np.degrees(compass_yaw_rad(data, c.extended)) % 360.0
    yaw_r = np.degrees(compass_yaw_rad(data, c.baseline, remove_bias=False)) % 360.0
    bias = c.bias_mgauss(c.extended)
    thr = data.throttle_01
    theta = c.extended.theta_mgauss
    ests = [
        HeadingEstimate(
            float(data.t_s[i]),
            c.index,
            float(yaw_e[i]),
            float(yaw_r[i]),
            theta,
            bias[i],
            float(thr[i]),
            FLAG_CALIBRATED,
            data.field_mgauss[i],
            data.field_mgauss[i] - bias[i],
            float(np.linalg.norm(c.extended.residual_mgauss[i])),
        )
        for i in range(data.n)
    ]
    viz.log_estimates(ests)
    viz.log_reference_theta(c.baseline.theta_mgauss, None)
    meas_bias = data.field_mgauss - _earth_part(c, c.extended)
    viz.log_bias_fit(thr**2, meas_bias, theta)
    if reference is not None:
        viz.log_truth_heading(reference[0], np.degrees(reference[1]) % 360.0)
    for f in c.findings:
        viz.log_text(float(data.t_s[0]), f"finding: {f.effect} {f.params}")
    serve_until_interrupt(viz, lambda m: print(m, flush=True))
    viz.close()


def execute(args: argparse.Namespace) -> int:
    from magcomp.adapters.mavlink_source import load_log
    from magcomp.diagnosis.engine import diagnose
    from magcomp.errors import InputError
    from magcomp.service.console import check_distinct_outputs, check_output_path

    if not str(args.log).strip():
        raise InputError("LOG: the path is empty")
    if Path(args.log).is_dir():
        raise InputError(f"{args.log}: is a directory, not a log file")
    if not Path(args.log).is_file():
        raise InputError(f"{args.log}: no such file")
    if args.mag_index is not None and args.mag_index < 0:
        raise InputError(f"--mag-index must be a compass index >= 0, got {args.mag_index}")
    inputs = (args.log, args.truth)
    check_output_path(args.json, "--json", inputs)
    check_output_path(args.report, "--report", inputs, makes_parents=True)
    if args.report:
        import importlib.util

        if importlib.util.find_spec("matplotlib") is None:  # a core dependency, unless removed by hand
            raise InputError("--report needs matplotlib for its plots: pip install matplotlib")
    check_distinct_outputs(json=args.json, report=args.report)
    if args.rerun:
        from magcomp.adapters.rerun_viz import parse_mode

        parse_mode(args.rerun)  # a bad --rerun fails now, not after the diagnosis
    reference = _truth_reference(args)
    from magcomp.service.console import Busy

    with Busy(f"diagnose: reading {Path(args.log).name}"):
        log = load_log(args.log, throttle_source=args.throttle_source)
    with Busy("diagnose: fitting the models"):
        d = diagnose(log, primary=args.mag_index, heading_reference=reference, events=log_events(args.log))
    j = d.to_json()
    print(f"{args.log}: {len(d.compasses)} compass(es), primary {d.primary}")
    for line in _summary(j):
        print(line)
    for note in d.notes:
        print(f"note: {note}")
    if args.json:
        try:
            Path(args.json).write_text(json.dumps(j, indent=1, allow_nan=False) + "\n", encoding="utf-8")
        except OSError as exc:
            raise InputError(f"cannot write {args.json}: {exc.strerror or exc}") from exc
        print(f"wrote {args.json}")
    if args.report:
        from magcomp.diagnosis.report import write_report

        try:
            written = write_report(d, Path(args.report))
        except OSError as exc:
            raise InputError(f"cannot write {args.report}: {exc.strerror or exc}") from exc
        print(f"wrote {written[0]} and {len(written) - 1} plot(s)")
    if args.rerun:
        try:
            import magcomp.adapters.rerun_viz  # noqa: F401
        except ImportError:
            print("the Rerun view is not available yet (magcomp.adapters.rerun_viz missing)", file=sys.stderr)
        else:
            _show_in_rerun(args.rerun, d, reference)
    if not math.isfinite(float(j["residual_rms_extended"] or 0.0)):
        return 1
    return 0
