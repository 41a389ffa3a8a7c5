"""Real-flight accuracy: plain ``magcomp replay`` (no configuration) on a measured log with an external compass.

The heading of every other compass is compared with compass 0's (the external one, furthest from the power
wires), both as magcomp publishes them (MAGCOMP_HEADING ``heading``, corrected; ``heading_raw``, the
autopilot's calibration only). Reported: rms of the difference (deg) with its constant part removed (a
mounting offset between two compasses is not a heading error), over (a) every sample with tilt below 45 deg
before the crash (the metric ``diagnose`` uses) and (b) only the samples with the motors running.

    python benchmarks/real_flight.py [LOG] [--config FILE]

Default LOG: ../shared/data/measured/dronekit_log171_copter33_quad.bin (crash at 226 s after the first
sample: samples from there on are left out).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from magcomp.adapters.config import load_config
from magcomp.service.replay import replay_log

DEFAULT_LOG = Path(__file__).resolve().parents[1].parent / "shared/data/measured/dronekit_log171_copter33_quad.bin"
CRASH_AFTER_S = 226.0
TILT_MAX_RAD = math.radians(45.0)


def _rms_deg(err_rad: np.ndarray) -> float:
    if err_rad.size == 0:
        return float("nan")
    e = np.angle(np.exp(1j * err_rad))
    e = np.angle(np.exp(1j * (e - np.angle(np.mean(np.exp(1j * e))))))
    return math.degrees(float(np.sqrt(np.mean(e**2))))


def heading_errors(estimates: list, ref_index: int = 0) -> dict[str, dict[str, float]]:
    """Per compass other than ``ref_index``: rms heading difference (deg), raw and corrected."""
    by: dict[int, dict[str, list[float]]] = {}
    for e in estimates:
        d = by.setdefault(e.mag_index, {"t": [], "h": [], "r": [], "thr": []})
        d["t"].append(e.t_s)
        d["h"].append(math.radians(e.heading_deg))
        d["r"].append(math.radians(e.heading_raw_deg))
        d["thr"].append(e.throttle_01)
    if ref_index not in by:
        raise SystemExit(f"no compass {ref_index} in the log")
    ref = {k: np.asarray(v) for k, v in by[ref_index].items()}
    t0 = ref["t"][0]
    out: dict[str, dict[str, float]] = {}
    for idx, d in sorted(by.items()):
        if idx == ref_index:
            continue
        t = np.asarray(d["t"])
        keep = t - t0 < CRASH_AFTER_S
        flying = keep & (np.asarray(d["thr"]) > 0.05)
        ref_h = np.interp(t, ref["t"], np.unwrap(ref["h"]))
        ref_r = np.interp(t, ref["t"], np.unwrap(ref["r"]))
        h, r = np.asarray(d["h"]), np.asarray(d["r"])
        out[f"compass {idx}"] = {
            "corrected_all_deg": _rms_deg((h - ref_h)[keep]),
            "uncorrected_all_deg": _rms_deg((r - ref_r)[keep]),
            "corrected_flying_deg": _rms_deg((h - ref_h)[flying]),
            "uncorrected_flying_deg": _rms_deg((r - ref_r)[flying]),
        }
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log", nargs="?", default=str(DEFAULT_LOG))
    ap.add_argument("--config")
    ap.add_argument("--causal", action="store_true", help="one pass, as the live daemon")
    args = ap.parse_args()
    if not Path(args.log).exists():
        print(f"{args.log}: not found (the measured logs live in ../shared/data/measured)", file=sys.stderr)
        return 2
    cfg = load_config(args.config)
    rep = replay_log(args.log, cfg, keep_estimates=True, two_pass=not args.causal)
    errs = heading_errors(rep.estimates)
    print(json.dumps(errs, indent=2))
    for c in rep.summary["compasses"]:
        print(f"compass {c['index']}: {c['status']} ({c['why']}), theta {np.round(c['theta_mgauss'], 1).tolist()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
