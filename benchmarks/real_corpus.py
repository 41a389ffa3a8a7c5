"""Real-flight corpus: magcomp's published heading against the heading the autopilot already had, per compass.

    python benchmarks/real_corpus.py DIR [--modes two-pass,causal,chained] [--json OUT]

Every log in DIR (tlog, DataFlash .bin/.log, ULog; the development logs of ../shared/data/real-corpus.md are
fetched there, never into the project) is replayed with no configuration, and each compass is scored on the
samples with the motors running (throttle above FLYING_THROTTLE_01) and |roll|, |pitch| < 60 deg:

* **att**: rms of (heading - the autopilot's yaw) with its circular mean removed;
* **gyro**: rms of (heading - the yaw integrated from the logged gyro with the autopilot's roll and pitch),
  each 10 s window's mean removed; where the gyro comes slower than 10 Hz, the autopilot's yaw on the same
  windows instead.

The baseline is the autopilot's own heading: the log's field as logged (its calibration and any onboard
motor compensation applied) tilt-compensated with the autopilot's roll and pitch (eq. (24)). magcomp's is
the published MAGCOMP_HEADING ``heading``. worse = att or gyro up by more than 10 % and 0.5 deg; better =
both down by 10 % or more. The metrics are :mod:`magcomp.core.selfcheck`'s, the ones the product's own
self-check uses.

Modes: ``two-pass`` (``magcomp replay``), ``causal`` (``replay --causal``: what the live daemon publishes on a
vehicle it has never seen) and ``chained``: the daemon as it is used, flight after flight: each vehicle's logs
(grouped and ordered as ``magcomp fleet`` does: the board's id, the log's date) replayed ``--causal`` with one
``--state-dir`` per vehicle, so that each flight starts from the state the previous one saved.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magcomp.adapters.config import load_config
from magcomp.adapters.mavlink_source import load_log
from magcomp.core import selfcheck as sc
from magcomp.core.heading import heading_from_trig_deg, wrap_deg_180
from magcomp.core.types import FLAG_CALIBRATED, LogData
from magcomp.errors import InputError
from magcomp.service.evaluate import FLYING_THROTTLE_01
from magcomp.service.persist import StateSink
from magcomp.service.replay import replay_log

SUFFIXES = {".tlog", ".bin", ".log", ".ulg"}
F64 = NDArray[np.float64]
MAX_TILT_RAD = math.radians(60.0)


@dataclass
class Reference:
    """What the scores are taken against, for one log."""

    att_t: np.ndarray
    roll: np.ndarray
    pitch: np.ndarray
    yaw_unwrapped: np.ndarray
    thr_t: np.ndarray
    thr: np.ndarray
    gyro_t: np.ndarray | None  # None: the gyro is slower than 10 Hz (the autopilot's yaw is the reference)
    gyro_yaw: np.ndarray
    gyro_seg: np.ndarray


def reference(data: LogData) -> Reference | None:
    att = data.attitude_rad
    if len(att) < 10 or len(data.throttle_01) < 2:
        return None
    roll, pitch, yaw = att.values[:, 0], att.values[:, 1], np.unwrap(att.values[:, 2])
    gt, g = data.imu_t_s, data.gyro_rad_s
    gyro_t: np.ndarray | None = None
    gyro_yaw = gyro_seg = np.zeros(0)
    if gt.size > 10 and float(np.median(np.diff(gt))) <= sc.MAX_GYRO_DT_S:
        r = np.interp(gt, att.t_s, roll)
        p = np.interp(gt, att.t_s, pitch)
        gyro_yaw, gyro_seg = sc.integrate_yaw_rad(gt, sc.euler_yaw_rate_rad_s(g, r, p))
        gyro_t = gt
    thr = data.throttle_01
    return Reference(att.t_s, roll, pitch, yaw, thr.t_s, thr.values, gyro_t, gyro_yaw, gyro_seg)


def score(ref: Reference, t: np.ndarray, heading_deg: np.ndarray) -> dict[str, float] | None:
    """att / gyro / att in the top throttle quartile (deg) of one heading series at times ``t``."""
    inside = (t >= ref.att_t[0]) & (t <= ref.att_t[-1])
    t, h = t[inside], np.radians(heading_deg[inside])
    if t.size < 20:
        return None
    roll = np.interp(t, ref.att_t, ref.roll)
    pitch = np.interp(t, ref.att_t, ref.pitch)
    thr = np.interp(t, ref.thr_t, ref.thr)
    keep = (thr > FLYING_THROTTLE_01) & (np.abs(roll) < MAX_TILT_RAD) & (np.abs(pitch) < MAX_TILT_RAD)
    if keep.sum() < 20:
        return None
    t, h, thr = t[keep], h[keep], thr[keep]
    yaw = np.interp(t, ref.att_t, ref.yaw_unwrapped)
    att = sc.offset_removed_rms_deg(h - yaw)
    top = thr >= np.quantile(thr, 0.75)
    att_top = sc.offset_removed_rms_deg(h[top] - yaw[top])
    if ref.gyro_t is not None:
        gy = np.interp(t, ref.gyro_t, ref.gyro_yaw)
        seg = np.interp(t, ref.gyro_t, ref.gyro_seg).round()
        gyro = sc.windowed_rms_deg(h - gy, sc.window_ids(t, seg))
    else:
        gyro = sc.windowed_rms_deg(h - yaw, sc.window_ids(t))
    # the constant att removes (deg): where the autopilot's yaw is independent of the compass (another
    # compass's, the absolute form) the published heading's constant can be compared with the two-pass's
    mean = math.degrees(sc.circular_mean_rad(h - yaw))
    return {"att": att, "gyro": gyro, "att_top": att_top, "n": float(t.size), "mean_deg": mean}


def verdict(base: dict[str, float], new: dict[str, float]) -> str:
    worse = any(new[k] > base[k] * 1.1 and new[k] > base[k] + 0.5 for k in ("att", "gyro"))
    better = all(new[k] <= 0.9 * base[k] for k in ("att", "gyro"))
    return "worse" if worse else "better" if better else "same"


def own_headings(data: LogData, ref: Reference) -> Iterator[tuple[int, F64, F64]]:
    """Per compass with 20 samples or more: its index, sample times (s) and the autopilot's own heading (deg):
    the field as logged, tilt-compensated (eq. (24)) with the autopilot's roll and pitch."""
    for idx, s in sorted(data.mag.items()):
        if len(s) < 20:
            continue
        r = np.interp(s.t_s, ref.att_t, ref.roll)
        p = np.interp(s.t_s, ref.att_t, ref.pitch)
        m = s.values
        h = heading_from_trig_deg(m[:, 0], m[:, 1], m[:, 2], np.cos(r), np.sin(r), np.cos(p), np.sin(p))
        yield idx, s.t_s, h


def baseline_scores(data: LogData, ref: Reference) -> dict[int, dict[str, float]]:
    out: dict[int, dict[str, float]] = {}
    for idx, t_s, h in own_headings(data, ref):
        got = score(ref, t_s, h)
        if got is not None:
            out[idx] = got
    return out


Scores = dict[int, dict[str, float]]

#: ``--config``: a configuration to replay with (default: none, as a new user runs it)
CONFIG_PATH: str | None = None


def magcomp_scores(
    path: Path, ref: Reference, causal: bool, store: StateSink | None = None
) -> tuple[Scores, dict[int, str], dict[int, float]]:
    """Scores of the published heading per compass (each with ``gyro_corrected``: the gyro metric on the
    samples published as corrected, FLAG_CALIBRATED, which is what the printed +-sigma describes: before a
    live correction switches on, the autopilot's own heading is published), what replay said, the sigma.
    ``store``: the vehicle's saved state (``chained``), loaded at the start and saved at the end."""
    rep = replay_log(path, load_config(CONFIG_PATH), keep_estimates=True, two_pass=not causal, store=store)
    by: dict[int, list[tuple[float, float, float]]] = {}
    for e in rep.estimates:
        by.setdefault(e.mag_index, []).append((e.t_s, e.heading_deg, float(e.flags & FLAG_CALIBRATED)))
    out: dict[int, dict[str, float]] = {}
    for idx, rows in by.items():
        a = np.asarray(rows)
        got = score(ref, a[:, 0], a[:, 1])
        if got is not None:
            on = a[:, 2] > 0
            cor = score(ref, a[on, 0], a[on, 1]) if on.any() else None
            got["gyro_corrected"] = math.nan if cor is None else cor["gyro"]
            out[idx] = got
    said = {int(c["index"]): f"{c['status']}: {c['why']}" for c in rep.summary.get("compasses", [])}
    sigma = {  # the heading uncertainty printed for a compass corrected in flight (deg, 1 sigma); none is
        # printed for theta against the autopilot's calibration (its summary still has the unapplied in-flight
        # estimate's, which does not describe the published heading)
        int(c["index"]): float(c["inflight"]["heading_sigma_deg"])
        for c in rep.summary.get("compasses", [])
        if c["status"] == "corrected" and (c.get("calibration") or {}).get("source") == "in-flight"
        and (c.get("inflight") or {}).get("heading_sigma_deg") is not None
    }
    return out, said, sigma


def vehicle_order(paths: list[Path]) -> list[tuple[Path, str]]:
    """The logs with their vehicle, each vehicle's in date order (what ``magcomp fleet`` groups by)."""
    from magcomp.fleet.identity import scan_identity

    keyed = []
    for path in paths:
        try:
            ident = scan_identity(path)
            vehicle = ident.vehicle_id(path)[0]
            date = ident.date_utc or ""
        except Exception:  # an unreadable log: its own vehicle (run() reports why)
            vehicle, date = path.name, ""
        keyed.append((vehicle, str(date), path.name, path))
    return [(p, v) for v, _, _, p in sorted(keyed, key=lambda k: k[:3])]


def run(paths: list[Path], modes: list[str]) -> list[dict[str, Any]]:
    import tempfile

    from magcomp.adapters.state_store import StateStore

    rows: list[dict[str, Any]] = []
    chained = "chained" in modes
    vehicle_of = dict(vehicle_order(paths)) if chained else {}
    if chained:  # each vehicle's flights in order
        paths = [p for p, _ in vehicle_order(paths)]
    state_root = Path(tempfile.mkdtemp(prefix="magcomp-corpus-state-")) if chained else None
    for path in paths:
        try:
            data = load_log(path, undo_motor_comp=False)  # the field as the autopilot had it
        except InputError as exc:
            print(f"{path.name}: {exc}", file=sys.stderr)
            continue
        ref = reference(data)
        if ref is None:
            print(f"{path.name}: no attitude or throttle to score against", file=sys.stderr)
            continue
        base = baseline_scores(data, ref)
        store = StateStore(state_root / _safe(vehicle_of[path])) if state_root is not None else None
        per_mode = {
            m: magcomp_scores(path, ref, m != "two-pass", store if m == "chained" else None) for m in modes
        }
        for idx, b in base.items():
            row: dict[str, Any] = {"log": path.name, "compass": idx, "autopilot": b}
            if chained:
                row["vehicle"] = vehicle_of[path]
            for m, (scores, said, sigma) in per_mode.items():
                got = scores.get(idx)
                row[m] = got
                row[m + "_sigma"] = sigma.get(idx)
                row[m + "_verdict"] = verdict(b, got) if got is not None else "missing"
                row[m + "_said"] = said.get(idx, "")
            rows.append(row)
            print(line(row, modes), flush=True)
    return rows


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)[:80] or "vehicle"


def _fmt(s: dict[str, float] | None) -> str:
    return "-" if s is None else f"{s['att']:.1f} / {s['gyro']:.1f}"


def line(row: dict[str, Any], modes: list[str]) -> str:
    parts = [f"{row['log'][:58]:58s} {row['compass']}", f"{_fmt(row['autopilot']):>11s}"]
    for m in modes:
        parts.append(f"{_fmt(row[m]):>11s} {row[m + '_verdict']:7s}")
    parts.append(row[modes[0] + "_said"][:70])
    return "  ".join(parts)


def constant_line(rows: list[dict[str, Any]], mode: str) -> list[str]:
    """What att cannot see: the published heading's constant. Where the two-pass replay learned the
    compass in the absolute form (the autopilot's yaw from another compass: the constant is observable) and
    its heading is better than the autopilot's own, the median |constant - the two-pass one| of the heading
    published in ``mode`` and of the autopilot's own heading (deg)."""
    if mode == "two-pass":
        return []
    got = [(r[mode]["mean_deg"], r["autopilot"]["mean_deg"], r["two-pass"]["mean_deg"]) for r in rows
           if "absolute form" in r.get("two-pass_said", "") and r.get(mode) and r.get("two-pass")
           and r["two-pass_verdict"] == "better"]  # fmt: skip
    if not got:
        return []
    a = np.asarray(got)
    pub = np.abs(wrap_deg_180(a[:, 0] - a[:, 2]))
    own = np.abs(wrap_deg_180(a[:, 1] - a[:, 2]))
    return [f"{mode}: constant vs the two-pass replay's where it is observable (absolute form, {len(a)} "
            f"compasses): median |difference| {np.median(pub):.1f} deg (the autopilot's own heading's "
            f"{np.median(own):.1f})"]  # fmt: skip


def summary(rows: list[dict[str, Any]], modes: list[str]) -> list[str]:
    out = []
    for m in modes:
        v = [r[m + "_verdict"] for r in rows]
        big = [r for r in rows if r["autopilot"]["att"] >= 8.0 and r[m] is not None]
        ratios = [r[m]["att"] / r["autopilot"]["att"] for r in big]
        better_big = sum(r[m + "_verdict"] == "better" for r in big)
        med = statistics.median(ratios) if ratios else math.nan
        g_ratios = [r[m]["gyro"] / r["autopilot"]["gyro"] for r in big if r["autopilot"]["gyro"] > 0]
        g_med = statistics.median(g_ratios) if g_ratios else math.nan
        for key, what in (("gyro", "all samples"), ("gyro_corrected", "the samples published corrected")):
            cov = [(r[m][key], r[m + "_sigma"]) for r in rows
                   if r[m] is not None and r.get(m + "_sigma") and r[m].get(key, math.nan) == r[m].get(key)]
            in1 = sum(g <= s for g, s in cov)
            in2 = sum(g <= 2 * s for g, s in cov)
            out.append(
                f"{m}: printed +-sigma of {len(cov)} corrected compasses vs their realised error (gyro, "
                f"{what}): within 1 sigma {in1}/{len(cov)}, within 2 sigma {in2}/{len(cov)}"
            )  # fmt: skip
        out += constant_line(rows, m)
        out.append(
            f"{m}: {len(rows)} compasses: worse {v.count('worse')}, better {v.count('better')}, "
            f"same {v.count('same')}, missing {v.count('missing')}; own heading >= 8 deg att: "
            f"{better_big}/{len(big)} better, median att ratio {med:.2f} (gyro ratio {g_med:.2f})"
        )
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("paths", nargs="+", help="log files or directories")
    ap.add_argument("--modes", default="two-pass,causal,chained")
    ap.add_argument("--json", help="write the rows here")
    ap.add_argument("--config", help="replay with this configuration (default: none)")
    args = ap.parse_args()
    global CONFIG_PATH
    CONFIG_PATH = args.config
    files: list[Path] = []
    for p in map(Path, args.paths):
        files += sorted(f for f in p.rglob("*") if f.suffix.lower() in SUFFIXES) if p.is_dir() else [p]
    modes = args.modes.split(",")
    head = "  ".join(f"{m:>19s}" for m in modes)
    print(f"{'log':58s} c  {'autopilot':>11s}  {head}  what replay said")
    rows = run(files, modes)
    for s in summary(rows, modes):
        print(s)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
