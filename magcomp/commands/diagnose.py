"""`magcomp diagnose LOG`: compare the model with a measured log, name what it misses, extend it,
measure the gain.

Reads a tlog, an ArduPilot DataFlash .bin/.log or a PX4 .ulg; writes a JSON document (``--json``) and a
Markdown report with PNG plots (``--report``); prints a short summary. A simulated log's truth
(``LOG.truth.npz`` beside it, or ``--truth``) gives the heading reference.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

#: the dates the bundled WMM releases cover (as the configuration's [location] decimal_year)
YEAR_RANGE = (2010.0, 2030.0)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", metavar="LOG", help=".tlog, ArduPilot DataFlash .bin/.log, or PX4 .ulg")
    parser.add_argument("--json", metavar="OUT.json", help="write the diagnosis as JSON")
    parser.add_argument("--report", metavar="OUT.md", help="write a Markdown report with PNG plots beside it")
    parser.add_argument(
        "--params-out",
        metavar="FILE",
        help="write the compensation parameters for the log's autopilot (PX4 CAL_MAGn_*COMP or ArduPilot "
        "COMPASS_MOT*): FILE.params for QGroundControl, FILE.param for Mission Planner",
    )
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
        "--location",
        metavar="LAT,LON[,ALT]",
        default=None,
        help="where the log was recorded (deg, deg, m), for the WMM check when the log has no GPS fix",
    )
    parser.add_argument(
        "--year",
        type=float,
        default=None,
        help="decimal year of the log, for the WMM check when the log has no GPS time",
    )
    parser.add_argument(
        "--rerun",
        metavar="MODE",
        nargs="?",
        const="auto",
        default=None,
        help="show the primary compass in Rerun: spawn, serve, connect[=URL], save=PATH.rrd, auto",
    )
    from magcomp.service.handover import add_save_state_arguments

    add_save_state_arguments(parser)


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


def gps_from_file(path: str) -> tuple[float, float, float, float] | None:
    """(lat deg, lon deg, alt m, decimal year or NaN) of the first 3D GPS fix of a DataFlash log or tlog.

    Used only while the log readers do not fill ``LogData.position`` themselves. GPS week/ms gives the date
    of a DataFlash fix; a tlog's date comes from SYSTEM_TIME.
    """
    if Path(path).suffix.lower() not in (".bin", ".log", ".tlog"):
        return None
    with _raw_log(path) as m:
        if m is None:  # a position is a nicety; the diagnosis runs without it
            return None
        return _read_fix(m)


def _read_fix(m: Any) -> tuple[float, float, float, float] | None:
    """The first 3D fix and the date of an open reader (see :func:`gps_from_file`)."""
    import datetime as dt

    from magcomp.geomag import decimal_year

    gps_epoch = dt.datetime(1980, 1, 6)
    fix: tuple[float, float, float] | None = None
    year = float("nan")
    try:
        while fix is None or not math.isfinite(year):
            msg = quiet_recv(m, ["GPS", "GPS_RAW_INT", "SYSTEM_TIME"])
            if msg is None:
                break
            d = msg.to_dict()
            kind = msg.get_type()
            if kind == "GPS" and int(d.get("Status", 0)) >= 3 and fix is None:
                fix = (float(d["Lat"]), float(d["Lng"]), float(d.get("Alt", 0.0)))
                week = d.get("Week", d.get("GWk"))
                ms = d.get("TimeMS", d.get("GMS"))
                if week and ms:
                    when = gps_epoch + dt.timedelta(weeks=int(week), milliseconds=float(ms))
                    year = decimal_year(when)
            elif kind == "GPS_RAW_INT" and int(d.get("fix_type", 0)) >= 3 and fix is None:
                fix = (d["lat"] * 1e-7, d["lon"] * 1e-7, d["alt"] * 1e-3)
            elif kind == "SYSTEM_TIME" and d.get("time_unix_usec", 0) > 1e15:
                year = decimal_year(dt.datetime.fromtimestamp(d["time_unix_usec"] * 1e-6, dt.UTC))
    except Exception:  # a reader hiccup: use what was read
        pass
    if fix is None or not all(math.isfinite(v) for v in fix) or (fix[0] == 0.0 and fix[1] == 0.0):
        return None
    return fix[0], fix[1], fix[2], year


def earth_reference(path: str, log: Any, location: str | None = None, year_arg: float | None = None) -> Any:
    """The WMM field at the log's position and date (see :mod:`magcomp.diagnosis.gate`); ``location`` and
    ``year_arg``: ``--location`` and ``--year`` as given."""
    import numpy as np

    from magcomp.diagnosis.gate import NO_POSITION, EarthReference
    from magcomp.errors import InputError
    from magcomp.geomag import earth_field_ned_mgauss

    pos: tuple[float, float, float, float] | None = None
    where = ""
    if len(log.position) > 0:
        lat, lon, alt = (float(v) for v in np.median(log.position.values, axis=0))
        pos, where = (lat, lon, alt, float(log.decimal_year)), "the log's GPS position"
    else:
        g = gps_from_file(path)
        if g is not None:
            pos, where = g, "the log's first 3D GPS fix"
    if location:
        try:
            parts = [float(x) for x in str(location).split(",")]
        except ValueError:
            parts = []
        if len(parts) not in (2, 3):
            raise InputError(f"--location must be LAT,LON[,ALT], got {location!r}")
        alt = parts[2] if len(parts) == 3 else 0.0
        pos, where = (parts[0], parts[1], alt, float("nan")), "--location"
    if pos is None:
        return NO_POSITION
    lat, lon, alt, year = pos
    when = "the log's date"
    if year_arg is not None:
        year, when = float(year_arg), "--year"
    if not math.isfinite(year):
        year, when = 2025.5, "no date in the log, 2025.5 assumed"
    from magcomp.geomag import wmm_release

    epoch, inside = wmm_release(year)
    ned = earth_field_ned_mgauss(lat, lon, alt, year, allow_outside_lifespan=True)
    src = f"WMM-{epoch} at {where} ({lat:.4f}, {lon:.4f}, {alt:.0f} m), {year:.2f} ({when})"
    if not inside and year >= 2030.0:
        src += f"; the date is past WMM-{epoch}'s span, so its secular variation is extrapolated"
    elif year < 2010.0:
        src += "; the date is before WMM-2010, so its secular variation is extrapolated back"
    return EarthReference(ned, src)


def log_events(path: str) -> list[tuple[float, str]]:
    """Timestamped events of a log (messages, mode changes, arming, parameter sets), for the step report."""
    suffix = Path(path).suffix.lower()
    if suffix not in (".bin", ".log"):
        # a tlog's only event message, STATUSTEXT, carries no boot time, and without one message that does
        # there is no clock offset to place it by (below): reading the file (a second pass through pymavlink,
        # ~0.1-0.4 s for a 10 min flight) could only end in no event
        return []
    rows: list[tuple[float | None, float, str]] = []  # (boot time or None, reader timestamp, text)
    with _raw_log(path) as m:
        if m is None:  # events are a nicety; a reader hiccup must not stop the diagnosis
            return []
        _read_events(m, rows)
    # messages without their own boot time (old MSG/EV) get it from the reader's clock offset
    offsets = [stamp - boot for boot, stamp, _ in rows if boot is not None]
    off = sorted(offsets)[len(offsets) // 2] if offsets else None
    out = []
    for boot, stamp, text in rows:
        if boot is None and off is None:
            continue
        out.append((boot if boot is not None else stamp - (off or 0.0), text))
    return out


@contextlib.contextmanager
def _raw_log(path: str) -> Iterator[Any]:
    """pymavlink's own reader of ``path`` (None when it cannot open it), for the events and the GPS
    fallback. A damaged .bin is read through the same repair as the samples (its intact messages only);
    the reader, which writes a "bad header" line per byte it cannot frame straight to the C streams (two
    million lines for 1 MiB of zero padding), is silenced; its messages are read through
    :func:`quiet_recv`."""
    from pymavlink import mavutil

    from magcomp.adapters.mavlink_source import Counts as _Counts
    from magcomp.adapters.mavlink_source import dataflash_repaired as _dataflash_repaired
    from magcomp.adapters.mavlink_source import quiet as _quiet
    from magcomp.adapters.mavlink_source import quiet_c_streams as _quiet_c_streams

    repaired = _dataflash_repaired(Path(path), _Counts()) if Path(path).suffix.lower() == ".bin" else None
    try:
        try:
            with _quiet(), _quiet_c_streams():
                m = mavutil.mavlink_connection(str(repaired or path))
        except Exception:
            m = None
        try:
            yield m
        finally:
            if m is not None:
                with contextlib.suppress(Exception):
                    m.close()
    finally:
        if repaired is not None:
            with contextlib.suppress(OSError):
                repaired.unlink()


def quiet_recv(m: Any, types: list[str]) -> Any:
    """``m.recv_match(type=types)`` with pymavlink's prints kept off the terminal."""
    from magcomp.adapters.mavlink_source import quiet as _quiet

    with _quiet():
        return m.recv_match(type=types)


def _read_events(m: Any, rows: list[tuple[float | None, float, str]]) -> None:
    """The events of an open reader into ``rows`` (what was read before a reader hiccup is kept)."""
    try:
        t_first_param: float | None = None
        types = ["MSG", "EV", "MODE", "ERR", "PARM", "ARM", "STATUSTEXT"]
        while True:
            msg = quiet_recv(m, types)
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


def _g3(v: float | None) -> str:
    """A number for the console: three significant digits (the JSON keeps more)."""
    return "?" if v is None else f"{float(v):.3g}"


def _vec1(v: list[float] | None, ci95: list[float] | None) -> str:
    """(x, y, z) to 0.1, with the 95 % half-widths when known."""
    if v is None:
        return "?"
    txt = "(" + ", ".join(f"{float(x):.1f}" for x in v) + ")"
    if ci95 is not None and all(x is not None for x in ci95):
        txt += " +- (" + ", ".join(f"{float(x):.1f}" for x in ci95) + ")"
    return txt


def _summary(j: dict[str, Any]) -> list[str]:
    from magcomp.diagnosis.export import finding_text
    from magcomp.service.console import bias_at_flown_text

    lines = []
    for c in j["compasses"]:
        if not c["observable"]:
            lines.append(f"compass {c['index']}: not observable: {c['unobservable_why']}")
            pt = c.get("theta_given_prior")
            if pt:  # the calibration is refused, theta is not (diagnosis.partial)
                theta = _vec1(pt["theta"], pt["theta_ci95_halfwidth"])
                bias = bias_at_flown_text(pt["theta"], c.get("throttle2_flown"))
                lines.append(
                    f"  theta {theta} mgauss with the autopilot's calibration as prior{bias}; {pt['note']}"
                )
            continue
        names = ", ".join(finding_text(f) for f in c["findings"]) or "no finding"
        theta = _vec1(c["theta"], c.get("theta_ci95_halfwidth"))
        bias = bias_at_flown_text(c["theta"], c.get("throttle2_flown"))
        lines.append(
            f"compass {c['index']}: theta {theta} mgauss{bias}; residual "
            f"{_g3(c['residual_rms_baseline'])} -> {_g3(c['residual_rms_extended'])} mgauss; {names}"
        )
        why = (c.get("gate") or {}).get("theta_consistency_why")
        if why:  # theta's interval is a lower bound here (diagnosis.consistency): say so beside it
            lines.append(f"  theta caveat: {why}")
        for f in c["findings"]:  # a parameter the data cannot give says why in words
            for k, v in f["params"].items():
                if isinstance(v, str):
                    lines.append(f"  {f['effect']} {k}: {v}")
        for u in c.get("unexplained_structure", []):
            when = f" at t = {u['t_s']} s" if "t_s" in u else ""
            lines.append(
                f"  unexplained structure: {u['kind']}{when}, size {u['size_mgauss']} mgauss, "
                f"{u['rms_reduction_pct']} % of the residual rms"
            )
        if c["suspects"]:
            s = c["suspects"][0]
            lines.append(
                f"  the remaining residual follows {s['signal']} best "
                f"(lag {s['lag_s']} s, {100 * (s['r2'] or 0.0):.1f} % of its variance)"
            )
    g = j["gain"]
    for c in j["compasses"]:
        h = c.get("heading_vs_gyro")
        if h:
            verdict = "helps" if h["helps"] else f"{h['result']}: {h['verdict']}"
            lines.append(
                f"compass {c['index']}: heading vs gyro, the field as logged -> with this theta removed: "
                f"{h['baseline_gyro_deg']:.1f} -> {h['model_gyro_deg']:.1f} deg over {h['windows']} windows "
                f"of 10 s with the motors running; {verdict}"
            )
        m = c.get("heading_vs_gyro_model")
        if m and m["helps"] and not (h and h["helps"]):  # the gain is the calibration's, not theta's
            lines.append(
                f"  with the diagnosis's calibration as well: {m['baseline_gyro_deg']:.1f} -> "
                f"{m['model_gyro_deg']:.1f} deg: the autopilot's calibration of this compass is off; "
                "calibrate it again (`magcomp replay` learns one in flight)"
            )
    if "heading_error_rms_deg" in g and "paper" in g["heading_error_rms_deg"]:
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
    from magcomp.diagnosis.report import earth_part

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
    meas_bias = data.field_mgauss - earth_part(c, c.extended)
    viz.log_bias_fit(thr**2, meas_bias, theta)
    if reference is not None:
        viz.log_truth_heading(reference[0], np.degrees(reference[1]) % 360.0)
    for f in c.findings:
        viz.log_text(float(data.t_s[0]), f"finding: {f.label} {f.params}")
    serve_until_interrupt(viz, lambda m: print(m, flush=True))
    viz.close()


def _write_params(path: str, d: Any, autopilot: int, unhelpful: dict[int, str]) -> None:
    """The compensation parameters of the compasses whose theta does not make the heading worse against the
    gyro (diagnosis/gyro_check.py); ``unhelpful``: compass -> why its theta does (noted, left out)."""
    from magcomp.adapters.param_files import MAV_AUTOPILOT_PX4, compensation_params, write_param_file

    for idx, why in sorted(unhelpful.items()):
        print(f"note: compass {idx}: no compensation parameters: its theta makes the heading worse on this "
              f"log ({why})")  # fmt: skip
    kept = [(c.index, c.autopilot) for c in d.compasses if c.index not in unhelpful]
    params, notes = compensation_params(kept, d.primary, autopilot)
    px4 = autopilot == MAV_AUTOPILOT_PX4
    for note in notes:
        print(f"note: {note}")
    if not params:
        print(f"note: no compensation parameters to write to {path}")
        return
    kind = write_param_file(path, params, stack="PX4 Pro" if px4 else "ArduPilot")
    print(f"wrote {path}: {len(params)} {'PX4' if px4 else 'ArduPilot'} parameters for {kind}")


def _check_args(args: argparse.Namespace) -> None:
    """A clear one-line error for a bad argument, before anything is computed."""
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
    if args.year is not None and not YEAR_RANGE[0] <= args.year < YEAR_RANGE[1]:  # NaN fails too
        raise InputError(
            f"--year {args.year:g} is outside [{YEAR_RANGE[0]:g}, {YEAR_RANGE[1]:g}) "
            "(the life spans of the bundled WMM 2010-2025 releases)"
        )
    inputs = (args.log, args.truth, args.config)
    check_output_path(args.json, "--json", inputs)
    check_output_path(args.report, "--report", inputs, makes_parents=True)
    check_output_path(args.params_out, "--params-out", inputs)
    check_distinct_outputs(json=args.json, report=args.report, params_out=args.params_out)
    if args.params_out and Path(args.params_out).suffix.lower() not in (".params", ".param"):
        raise InputError(
            f"--params-out {args.params_out}: use .params (QGroundControl) or .param (Mission Planner)"
        )
    if args.report:
        import importlib.util

        if importlib.util.find_spec("matplotlib") is None:  # a core dependency, unless removed by hand
            raise InputError("--report needs matplotlib for its plots: pip install matplotlib")
    if args.rerun:
        from magcomp.adapters.rerun_viz import parse_mode

        parse_mode(args.rerun)  # a bad --rerun fails now, not after the diagnosis


def _write_outputs(
    args: argparse.Namespace, d: Any, j: dict[str, Any], autopilot: int, reference: tuple[Any, Any] | None
) -> None:
    """The JSON, the autopilot parameters, the report and the Rerun view that were asked for."""
    from magcomp.errors import InputError
    from magcomp.service.console import json_safe

    if args.json:
        try:
            text = json.dumps(json_safe(j), indent=1, allow_nan=False)  # a damaged log's NaN: null
            Path(args.json).write_text(text + "\n", encoding="utf-8")
        except OSError as exc:
            raise InputError(f"cannot write {args.json}: {exc.strerror or exc}") from exc
        print(f"wrote {args.json}")
    if args.params_out:
        unhelpful = {int(c["index"]): c["heading_vs_gyro"]["verdict"] for c in j["compasses"]
                     if c.get("heading_vs_gyro") and c["heading_vs_gyro"]["worse"]}  # fmt: skip
        _write_params(args.params_out, d, autopilot, unhelpful)
    if args.report:
        from magcomp.diagnosis.report import write_report

        try:
            checks = {int(c["index"]): c.get("heading_vs_gyro") for c in j["compasses"]}
            written = write_report(d, Path(args.report), checks=checks)
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


def read_gated_log(
    path: str, throttle_source: str = "auto", config: str | None = None, on_progress: Any = None
) -> Any:
    """The log as diagnose reads it (LogData), its magnetometer samples through the pipeline's gates: a
    clipped (saturated) or corrupt (jump) sample is not a field."""
    from magcomp.adapters.config import load_config
    from magcomp.adapters.mavlink_source import load_log
    from magcomp.service.align import gate_log_inputs

    log = load_log(path, throttle_source=throttle_source, on_progress=on_progress)
    saturation = load_config(config).input.saturation_mgauss
    for key, n in gate_log_inputs(log, saturation).items():
        log.counts[key] = log.counts.get(key, 0) + n
    return log


def note_skipped(d: Any, log: Any) -> dict[str, int]:
    """What reading the log dropped or absorbed, as a note of ``d`` (counted, never silent)."""
    from magcomp.service.console import SKIP_KEYS, format_counts

    skipped = {k: int(log.counts[k]) for k in SKIP_KEYS if log.counts.get(k)}
    if skipped:
        d.notes.append(f"skipped or absorbed while reading the log: {format_counts(skipped, SKIP_KEYS)}")
    return skipped


def add_heading_checks(j: dict[str, Any], d: Any, log: Any) -> None:
    """Per compass of the JSON ``j``: the self-check against the gyro of the heading with the diagnosis's
    theta removed (diagnosis/gyro_check.py) as ``heading_vs_gyro``, and of the heading its whole model gives
    (its calibration too) as ``heading_vs_gyro_model`` (null where there is nothing to judge)."""
    from magcomp.diagnosis.gyro_check import heading_check, model_check, references

    refs = references(log, d.yaw_follow)  # once per log
    for cj, c in zip(j["compasses"], d.compasses, strict=True):
        cj["heading_vs_gyro"] = None if refs is None else _check_json(heading_check(c, refs))
        cj["heading_vs_gyro_model"] = None if refs is None else _check_json(model_check(c, refs))


def _check_json(chk: Any) -> dict[str, Any] | None:
    """A check's figures and its verdict (diagnosis/gyro_check.py ``verdict``) as JSON values."""
    from magcomp.diagnosis.gyro_check import verdict

    if chk is None:
        return None
    what, why = verdict(chk)
    return {
        "baseline_gyro_deg": chk.baseline_gyro_deg, "model_gyro_deg": chk.candidate_gyro_deg,
        "baseline_att_deg": chk.baseline_att_deg, "model_att_deg": chk.candidate_att_deg,
        "windows": chk.n_windows, "z": chk.z, "helps": what == "helps", "worse": chk.worse,
        "result": what, "verdict": why,
    }  # fmt: skip


def diagnose_file(path: str, throttle_source: str = "auto", config: str | None = None) -> tuple[Any, Any]:
    """(Diagnosis, LogData) of one log with no option set: what ``magcomp diagnose LOG`` computes (the fleet
    calls this per log)."""
    from magcomp.diagnosis.engine import diagnose

    log = read_gated_log(path, throttle_source, config)
    d = diagnose(log, events=log_events(path), earth=earth_reference(path, log))
    note_skipped(d, log)
    return d, log


def execute(args: argparse.Namespace) -> int:
    from magcomp.diagnosis.engine import diagnose

    _check_args(args)
    reference = _truth_reference(args)
    if args.save_state:
        from magcomp.adapters.state_store import StateStore
        from magcomp.service.handover import handover_config, save_learned_state

        cfg = handover_config(args.config, args.throttle_source)
        for line in save_learned_state(args.log, cfg, StateStore(args.save_state)):
            print(line, flush=True)
    from magcomp.service.console import Busy, reading_progress

    with reading_progress(f"diagnose: reading {Path(args.log).name}", args.log) as on_progress:
        log = read_gated_log(args.log, args.throttle_source, args.config, on_progress)
    with Busy("diagnose: fitting the models"):
        d = diagnose(
            log,
            primary=args.mag_index,
            heading_reference=reference,
            events=log_events(args.log),
            earth=earth_reference(args.log, log, args.location, args.year),
        )
    skipped = note_skipped(d, log)
    j = d.to_json()
    j["counts"] = skipped
    add_heading_checks(j, d, log)
    print(f"{args.log}: {len(d.compasses)} compass(es), primary {d.primary}")
    for line in _summary(j):
        print(line)
    for note in d.notes:
        print(f"note: {note}")
    _write_outputs(args, d, j, log.autopilot, reference)
    if not math.isfinite(float(j["residual_rms_extended"] or 0.0)):
        return 1
    return 0
