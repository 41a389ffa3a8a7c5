"""Regenerate the sample logs in replay_logs/ (deterministic: fixed seeds; same pymavlink -> same bytes).

    .venv/bin/python scripts/make_replay_logs.py [--out replay_logs]

Each log comes with FILE.truth.json / FILE.truth.npz (theta, K, b, effect parameters, truth arrays).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

# (file stem, scenario, vehicle, duration s, effects, seed)
LOGS: list[tuple[str, str, str, float, dict[str, float], int]] = [
    ("paper_clean", "paper", "fixedwing", 133.0, {}, 1),
    ("bench_clean", "bench", "fixedwing", 40.0, {}, 1),
    ("flight_multirotor_clean", "flight", "multirotor", 45.0, {}, 2),
    ("effect_throttle_offset", "bench", "fixedwing", 40.0, {"throttle_offset": 0.15}, 1),
    ("effect_throttle_exponent", "bench", "fixedwing", 40.0, {"throttle_exponent": 3.0}, 1),
    ("effect_current_lag", "paper", "fixedwing", 50.0, {"current_lag": 0.4}, 1),
    ("effect_time_skew", "paper", "fixedwing", 50.0, {"time_skew": 0.25}, 1),
    ("effect_voltage_sag", "bench", "fixedwing", 40.0, {"voltage_sag": 1.0}, 1),
    ("effect_temperature_drift", "spin", "fixedwing", 45.0, {"temperature_drift": 1.5}, 1),
    ("effect_per_motor", "flight", "multirotor", 45.0, {"per_motor": 1.5}, 2),
]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "replay_logs"))
    args = parser.parse_args(argv)
    from magcomp.adapters.mavlink_emit import write_tlog, write_truth
    from magcomp.sim import SimConfig, simulate

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    total = 0
    for stem, scenario, vehicle, duration, effects, seed in LOGS:
        cfg = SimConfig(scenario=scenario, vehicle=vehicle, duration_s=duration, effects=effects, seed=seed)
        result = simulate(cfg)
        path = out / f"{stem}.tlog"
        count = write_tlog(result, path)
        json_path, npz_path = write_truth(result, path, single_precision=True)
        size = sum(p.stat().st_size for p in (path, json_path, npz_path))
        total += size
        print(
            f"{path.name}: {count} messages, {duration:.0f} s {scenario}/{vehicle} {effects or ''} "
            f"({size / 1e6:.2f} MB with truth)"
        )
    print(f"total {total / 1e6:.2f} MB in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
