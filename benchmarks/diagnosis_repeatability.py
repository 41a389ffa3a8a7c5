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


def segment_thetas(data: object, k: int, effects: tuple[str, ...] = ()) -> list[str]:
    """Lines of the report for one compass (``CompassData``) and K segments; ``effects``: extensions of the
    model (e.g. per_motor), fitted jointly with the segment thetas."""
    from magcomp.diagnosis.effects import ExtensionParams, drive_columns
    from magcomp.diagnosis.engine import inlier_mask, subset
    from magcomp.diagnosis.intervals import column_halfwidth
    from magcomp.diagnosis.model import CompassData, fit_model, initial_fit

    assert isinstance(data, CompassData)
    base = fit_model(data, (), start=initial_fit(data))
    keep = inlier_mask(data.t_s, base.residual_mgauss)
    if keep is not None:  # the diagnosis's own outlier rule (glitches, hardest manoeuvres)
        data = subset(data, keep)
    ext = ExtensionParams(per_motor="per_motor" in effects, temperature="temperature_drift" in effects)
    col = drive_columns(data.drive, ext)[0][:, 0]
    flying = data.t_s[data.throttle_01 > 0.05]
    edges = np.linspace(float(flying[0]), float(flying[-1]), k + 1)
    seg = np.clip(np.searchsorted(edges, data.t_s, side="right") - 1, 0, k - 1)
    extra = np.column_stack([col * (seg == j) for j in range(1, k)])
    names = tuple(f"seg{j + 1}" for j in range(1, k))
    d2 = replace(data, drive=replace(data.drive, extra=extra, extra_names=names))
    fit = fit_model(d2, effects, start=base)
    th1 = fit.coefs[0]
    hw1 = column_halfwidth(d2, fit, {"throttle": 1.0})
    lines = [
        f"  segment 1 t = {edges[0]:.0f}-{edges[1]:.0f} s: theta {_v(th1)} +- {_v(hw1)}",
    ]
    agree = True
    worst = 0.0
    for j, name in enumerate(names, start=1):
        i = list(fit.columns).index(name)
        diff = fit.coefs[i]
        hw_d = column_halfwidth(d2, fit, {name: 1.0})
        th = th1 + diff
        hw = column_halfwidth(d2, fit, {"throttle": 1.0, name: 1.0})
        ratio = float(np.max(np.abs(diff) / np.maximum(hw_d, 1e-9)))
        worst = max(worst, ratio)
        agree &= ratio <= 1.0
        rel = float(np.linalg.norm(diff)) / max(float(np.linalg.norm(th1)), 1e-9)
        cos = float(th @ th1) / max(float(np.linalg.norm(th) * np.linalg.norm(th1)), 1e-9)
        lines.append(
            f"  segment {j + 1} t = {edges[j]:.0f}-{edges[j + 1]:.0f} s: theta {_v(th)} +- {_v(hw)}; "
            f"minus segment 1: {_v(diff)} +- {_v(hw_d)} ({ratio:.2f}x); "
            f"|difference| / |theta_1| {rel:.2f}, cosine {cos:.3f}"
        )
    lines.append(
        f"  -> {'agree' if agree else 'DISAGREE'}: largest |difference| / 95 % half-width {worst:.2f}; "
        f"residual {fit.rms_mgauss:.1f} mgauss (one theta: {base.rms_mgauss:.1f})"
    )
    return lines


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
    for idx in sorted(log.mag):
        data = compass_data(log, idx)
        for k in args.segments:
            print(f"compass {idx}, {k} segments of the flying time:")
            print("\n".join(segment_thetas(data, k, tuple(args.effects))))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
