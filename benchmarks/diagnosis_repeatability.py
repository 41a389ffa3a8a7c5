"""Does theta repeat between disjoint segments of one real flight? (issue 10, repeatability on real data)

The only multi-compass real log with a clear current effect is log171 (``../shared/data/measured/``, see
SOURCES.md there): one flight, so the check is between disjoint segments of it. The flying time (throttle
above 5 %) is cut into K contiguous segments of equal duration (halves, thirds); the paper's model (eq. (11))
is fitted once with one calibration, Earth field and heading drift for the whole log but a theta per segment:
the drive column throttle^2 is split into K columns, throttle^2 x [t in segment k]. Sharing the calibration
is what makes a segment's theta observable even when the segment alone turns through too little heading
for the gate (the second half of log171 covers 44 deg).

Reported per compass and segment: theta_k +- its 95 % half-width (linear-model interval with the residual's
AR(1) inflation, :mod:`magcomp.diagnosis.intervals`), and the difference theta_k - theta_1 against its own
95 % half-width (the interval of the difference, from the same fit: it accounts for the correlation of the
two estimates). "Agrees" means every axis of every difference lies inside its interval.

    PYTHONPATH=. .venv/bin/python benchmarks/diagnosis_repeatability.py [LOG] [--segments 2 3]
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

DEFAULT_LOG = Path(__file__).resolve().parents[2] / "shared/data/measured/dronekit_log171_copter33_quad.bin"


def segment_thetas(data: object, k: int, effects: tuple[str, ...] = (), yaw_ref: object = None) -> list[str]:
    """Lines of the report for one compass (``CompassData``) and K segments; ``effects``: extensions of the
    model (e.g. per_motor), fitted jointly with the segment thetas (:func:`magcomp.diagnosis.consistency.
    segment_thetas`). Per segment also: the sd of the drive throttle^2 over its flying samples, the
    model-error bound (structured residual / that sd, :func:`magcomp.diagnosis.consistency.
    model_error_bound`), and, with ``yaw_ref`` = (t_s, yaw_rad) of an independent yaw, how far the
    compass-free heading wanders from it around the fitted linear drift (mean and sd, deg)."""
    from magcomp.diagnosis.consistency import model_error_bound
    from magcomp.diagnosis.consistency import segment_thetas as seg_fit
    from magcomp.diagnosis.engine import inlier_mask, subset
    from magcomp.diagnosis.model import CompassData, fit_model, initial_fit

    assert isinstance(data, CompassData)
    base = fit_model(data, (), start=initial_fit(data))
    keep = inlier_mask(data.t_s, base.residual_mgauss)
    if keep is not None:  # the diagnosis's own outlier rule (glitches, hardest manoeuvres)
        data = subset(data, keep)
    fit = fit_model(data, effects, start=base)
    segs = seg_fit(data, fit, k)
    if segs is None:
        return ["  too few flying samples per segment"]
    wander = None
    if yaw_ref is not None:
        t_ref, yaw = yaw_ref  # type: ignore[misc]
        r = data.r_nb
        gyro_yaw = np.unwrap(np.arctan2(r[:, 1, 0], r[:, 0, 0])) + fit.drift_rad_s * (
            data.t_s - 0.5 * (data.t_s[0] + data.t_s[-1])
        )
        dy = np.degrees(gyro_yaw - np.interp(data.t_s, t_ref, np.unwrap(yaw)))
        wander = dy - np.polyval(np.polyfit(data.t_s, dy, 1), data.t_s)
    lines = []
    worst = 0.0
    for j, sg in enumerate(segs):
        m = (data.t_s >= sg.t_from_s) & (data.t_s <= sg.t_to_s) & (data.throttle_01 > 0.05)
        sub = subset(data, m)
        part = replace(fit, residual_mgauss=fit.residual_mgauss[m], rms_mgauss=_rms(fit.residual_mgauss[m]))
        bound, structured, sd_d = model_error_bound(sub, part)
        line = (
            f"  segment {j + 1} t = {sg.t_from_s:.0f}-{sg.t_to_s:.0f} s: theta {_v(sg.theta_mgauss)} +- "
            f"{_v(sg.halfwidth_mgauss)}; sd(throttle^2) {sd_d:.3f}, structured residual {structured:.1f}, "
            f"bound {bound:.0f} mgauss"
        )
        if j:
            line += f"; differs from segment 1 by {sg.ratio:.2f}x its 95 % interval"
        if wander is not None:
            line += f"; heading wander {float(np.mean(wander[m])):+.1f} +- {float(np.std(wander[m])):.1f} deg"
        lines.append(line)
        worst = max(worst, sg.ratio)
    lines.append(
        f"  -> {'agree' if worst <= 1.0 else 'DISAGREE'}: largest |difference| / 95 % half-width {worst:.2f}"
    )
    return lines


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(x**2)))


def _v(x: np.ndarray) -> str:
    return "[" + ", ".join(f"{float(v):.0f}" for v in x) + "]"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log", nargs="?", default=str(DEFAULT_LOG))
    ap.add_argument("--segments", type=int, nargs="*", default=[2, 3])
    ap.add_argument(
        "--effects", nargs="*", default=[], help="linear extensions: per_motor, temperature_drift"
    )
    args = ap.parse_args()
    path = Path(args.log)
    if not path.is_file():
        print(f"{path}: not found (the shared logs are not part of the repository)")
        return 1
    from magcomp.adapters.mavlink_source import load_log
    from magcomp.diagnosis.engine import compass_data

    log = load_log(path)
    att = log.attitude_rad
    yaw_ref = (att.t_s, att.values[:, 2]) if len(att) >= 2 else None  # the autopilot's (external compass 0)
    for idx in sorted(log.mag):
        data = compass_data(log, idx)
        for k in args.segments:
            print(f"compass {idx}, {k} segments of the flying time:")
            print("\n".join(segment_thetas(data, k, tuple(args.effects), yaw_ref)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
