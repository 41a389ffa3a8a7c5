"""Real-flight accuracy: plain ``magcomp replay`` (no configuration) on a measured log, external compass 0.

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
import sys
from pathlib import Path

import numpy as np

from magcomp.adapters.config import load_config
from magcomp.service.evaluate import heading_agreement
from magcomp.service.replay import replay_log

DEFAULT_LOG = (
    Path(__file__).resolve().parents[1].parent / "shared/data/measured/dronekit_log171_copter33_quad.bin"
)
CRASH_AFTER_S = 226.0


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
    errs = heading_agreement(rep.estimates, 0, CRASH_AFTER_S)
    print(json.dumps({f"compass {k}": v for k, v in errs.items()}, indent=2))
    for c in rep.summary["compasses"]:
        print(
            f"compass {c['index']}: {c['status']} ({c['why']}), "
            f"theta {np.round(c['theta_mgauss'], 1).tolist()}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
