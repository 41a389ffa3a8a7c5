"""Whose slow error: per compass, the autopilot's own heading and the autopilot's yaw against the gyro.

    python benchmarks/reference_check.py DIR [--glob PATTERN] [--replay [--causal]]

The att metric of ``benchmarks/real_corpus.py`` charges every slow difference between a heading and the
autopilot's yaw to the heading. This prints, per compass, beside att, the rms over
30 s windows (each window's offset and gyro-drift ramp removed, :mod:`magcomp.core.yaw_reference`) of
(heading - gyro yaw) and of (autopilot yaw - gyro yaw): where the second is the larger, the slow error is the
autopilot's yaw's, and no correction of the compass can lower att. On PX4 ULogs the estimator's logged yaw
resets (``vehicle_attitude.delta_q_reset``) are listed. ``--replay``: the same for magcomp's two-pass heading
(``--causal``: replay --causal's).
The gyro is integrated at whatever rate the log has (3-4 Hz RAW_IMU in telemetry: slow turns only).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import real_corpus as rc

from magcomp.adapters.mavlink_source import load_log
from magcomp.core import selfcheck as sc
from magcomp.core.yaw_reference import slow_error_owner
from magcomp.errors import InputError
from magcomp.service.evaluate import FLYING_THROTTLE_01

#: a gap in the gyro longer than this restarts its integral (telemetry's RAW_IMU comes at 3-4 Hz)
GYRO_GAP_S = 2.0


def ulog_yaw_resets(path: Path) -> list[tuple[float, float]]:
    """(time s, yaw change deg) of each attitude reset the PX4 estimator logged."""
    from pyulog import ULog

    try:
        u = ULog(str(path), ["vehicle_attitude"])
    except Exception:  # an unreadable ULog: no resets to list (load_log reports the file)
        return []
    out = []
    for d in u.data_list:
        cols = d.data
        if "quat_reset_counter" not in cols:
            continue
        t = cols["timestamp"] / 1e6
        for i in np.nonzero(np.diff(cols["quat_reset_counter"]))[0] + 1:
            w, x, y, z = (float(cols[f"delta_q_reset[{k}]"][i]) for k in range(4))
            out.append((float(t[i]), math.degrees(math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))))
    return out


def heading_rows(data, ref, t, h_deg):  # type: ignore[no-untyped-def]
    """(t, heading rad, autopilot yaw rad, gyro yaw rad, segment) over the scored samples."""
    roll = np.interp(t, ref.att_t, ref.roll)
    pitch = np.interp(t, ref.att_t, ref.pitch)
    thr = np.interp(t, ref.thr_t, ref.thr)
    gt = data.imu_t_s
    keep = (thr > FLYING_THROTTLE_01) & (np.abs(roll) < rc.MAX_TILT_RAD) & (np.abs(pitch) < rc.MAX_TILT_RAD)
    keep &= (t >= max(ref.att_t[0], gt[0])) & (t <= min(ref.att_t[-1], gt[-1]))
    r = np.interp(gt, ref.att_t, ref.roll)
    p = np.interp(gt, ref.att_t, ref.pitch)
    gy, seg = sc.integrate_yaw_rad(gt, sc.euler_yaw_rate_rad_s(data.gyro_rad_s, r, p), max_gap_s=GYRO_GAP_S)
    t = t[keep]
    return (t, np.radians(h_deg[keep]), np.interp(t, ref.att_t, ref.yaw_unwrapped), np.interp(t, gt, gy),
            np.interp(t, gt, seg).round())


def line(label: str, rows) -> str:  # type: ignore[no-untyped-def]
    t, h, y, g, seg = rows
    own = slow_error_owner(t, h, y, g, seg)
    whose = "autopilot's yaw" if own.autopilot_yaw_limited else "compass"
    return (
        f"{label}: att {sc.offset_removed_rms_deg(h - y):5.1f}; 30 s, drift removed: heading-gyro "
        f"{own.compass_vs_gyro_deg:5.1f}, autopilot yaw-gyro {own.autopilot_vs_gyro_deg:5.1f}, "
        f"heading-yaw {own.compass_vs_autopilot_deg:5.1f} ({own.n_windows} windows): "
        f"slow error is the {whose}'s"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dir", type=Path)
    ap.add_argument("--glob", default="*")
    ap.add_argument("--replay", action="store_true", help="also magcomp's published heading")
    ap.add_argument("--causal", action="store_true", help="with --replay: replay --causal, not two-pass")
    a = ap.parse_args()
    for path in sorted(p for p in a.dir.glob(a.glob) if p.suffix.lower() in rc.SUFFIXES):
        try:
            data = load_log(path, undo_motor_comp=False)
        except InputError as exc:
            print(f"{path.name}: {exc}", file=sys.stderr)
            continue
        ref = rc.reference(data)
        if ref is None or data.imu_t_s.size < 10:
            continue
        rate = 1.0 / float(np.median(np.diff(data.imu_t_s)))
        resets = ulog_yaw_resets(path) if path.suffix.lower() == ".ulg" else []
        print(f"{path.name}  (gyro {rate:.0f} Hz)" + "".join(f"; yaw reset {dy:+.1f} deg at {tr:.1f} s"
                                                          for tr, dy in resets))
        published: dict[int, list[tuple[float, float]]] = {}
        if a.replay:
            from magcomp.adapters.config import load_config
            from magcomp.service.replay import replay_log

            rep = replay_log(path, load_config(None), keep_estimates=True, two_pass=not a.causal)
            for e in rep.estimates:
                published.setdefault(e.mag_index, []).append((e.t_s, e.heading_deg))
        for idx, t_s, h in rc.own_headings(data, ref):
            rows = heading_rows(data, ref, t_s, h)
            if rows[0].size < 20:
                continue
            print("  " + line(f"compass {idx} own     ", rows))
            if idx in published:
                pa = np.asarray(published[idx])
                print("  " + line(f"compass {idx} magcomp ", heading_rows(data, ref, pa[:, 0], pa[:, 1])))


if __name__ == "__main__":
    main()
