"""`magcomp simulate`: a synthetic vehicle's MAVLink stream, to a tlog (+ truth) or a live endpoint."""

from __future__ import annotations

import argparse
import sys

from magcomp.core.identity import SIM_UID
from magcomp.errors import InputError

_SCENARIOS = (
    "tumble",
    "spin",
    "pan",
    "ramp",
    "step",
    "bench",
    "flight",
    "paper",
    "ordinary",
    "ordinary_plane",
    "flight_fixedwing",
    "flight_multirotor",
)
_EFFECTS = (
    "throttle_offset",
    "throttle_exponent",
    "current_lag",
    "time_skew",
    "voltage_sag",
    "temperature_drift",
    "per_motor",
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--scenario", default="paper", help=f"one of: {', '.join(_SCENARIOS)} (default paper)"
    )
    parser.add_argument(
        "--effect",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help=f"hidden effect, repeatable; NAME in: {', '.join(_EFFECTS)}",
    )
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--duration", type=float, default=None, help="seconds (default: the scenario's)")
    parser.add_argument(
        "--vehicle",
        choices=("fixedwing", "multirotor"),
        default=None,
        help="airframe (default fixedwing; flight_* aliases set it)",
    )
    parser.add_argument("--compasses", type=int, default=2, help="number of compasses 1..3 (default 2)")
    parser.add_argument(
        "--uid",
        default=SIM_UID,
        metavar="HEX",
        help=f"the simulated board's unique id, 1-12 bytes of hex (default {SIM_UID}): state is kept per id",
    )
    parser.add_argument("--lat", type=float, default=None, help="latitude deg (default: Gainesville, FL)")
    parser.add_argument("--lon", type=float, default=None, help="longitude deg")
    parser.add_argument("--alt", type=float, default=None, help="altitude m above the ellipsoid")
    parser.add_argument(
        "--year", type=float, default=None, help="decimal year, 2025.0-2030.0 (default 2025.5)"
    )
    parser.add_argument(
        "--imu-rate", type=float, default=50.0, help="IMU/compass message rate Hz (default 50)"
    )
    parser.add_argument(
        "--attitude-rate", type=float, default=25.0, help="ATTITUDE and SERVO rate Hz (default 25)"
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        dest="settings",
        help="variation knob, repeatable (see magcomp/sim/config.py): e.g. telemetry_hz=2, mag_hz=10, "
        "yaw_source=truth, external_compass0=on, ap_cal_hard_iron_mgauss=30, mag_ar1_sigma_mgauss=3, "
        "att_roll_bias_deg=1, lat_deg=46.05, decimal_year=2026.3",
    )
    out = parser.add_mutually_exclusive_group(required=True)
    out.add_argument(
        "--out",
        metavar="FILE.tlog|FILE.ulg|FILE.bin",
        help="write a tlog (a PX4 ULog when FILE ends in .ulg, an ArduPilot 4.x DataFlash log when it ends "
        "in .bin) and FILE.truth.json / FILE.truth.npz",
    )
    out.add_argument("--link", metavar="URL", help="live endpoint: udpout:HOST:PORT or tcpout:HOST:PORT")
    parser.add_argument(
        "--speed",
        type=float,
        default=1.0,
        help="live playback speed-up (default 1 = real time; 0 = as fast as possible)",
    )


def _config(args: argparse.Namespace) -> object:
    from magcomp.sim.config import Location, Rates, SimConfig, apply_settings, parse_effect

    effects: dict[str, float] = {}
    for text in args.effect:
        name, value = parse_effect(text)
        effects[name] = value
    loc_kwargs = {
        k: v
        for k, v in (
            ("lat_deg", args.lat),
            ("lon_deg", args.lon),
            ("alt_m", args.alt),
            ("decimal_year", args.year),
        )
        if v is not None
    }
    if args.imu_rate <= 0 or args.attitude_rate <= 0:
        raise InputError("rates must be positive")
    att = min(args.attitude_rate, args.imu_rate)
    rates = Rates(
        imu_hz=args.imu_rate,
        attitude_hz=att,
        servo_hz=att,
        rc_hz=min(10.0, att),
        vfr_hud_hz=min(10.0, att),
        power_hz=min(10.0, att),
    )
    kwargs: dict[str, object] = {}
    if args.vehicle is not None:
        kwargs["vehicle"] = args.vehicle
    fixed = {"ordinary": "multirotor", "ordinary_plane": "fixedwing"}.get(args.scenario)
    if fixed is not None and args.vehicle not in (None, fixed):
        raise InputError(f"scenario {args.scenario} is a {fixed} flight: drop --vehicle {args.vehicle}")
    config = SimConfig(
        scenario=args.scenario,
        duration_s=args.duration,
        seed=args.seed,
        effects=effects,
        location=Location(**loc_kwargs),
        rates=rates,
        n_compasses=args.compasses,
        uid=args.uid,
        **kwargs,  # type: ignore[arg-type]
    )
    return apply_settings(config, args.settings) if args.settings else config


def execute(args: argparse.Namespace) -> int:
    from magcomp.adapters.mavlink_emit import stream_to_link, write_tlog, write_truth
    from magcomp.service.console import check_output_path
    from magcomp.sim import SimConfig, simulate

    if not (args.speed == 0 or 0.01 <= args.speed <= 1000.0):
        raise InputError(f"--speed must be 0 (as fast as possible) or in [0.01, 1000], got {args.speed:g}")
    if args.seed < 0:
        raise InputError(f"--seed must be >= 0, got {args.seed}")
    check_output_path(args.out, "--out")
    config = _config(args)
    assert isinstance(config, SimConfig)
    from magcomp.service.console import Busy

    with Busy(f"simulate: {config.scenario}"):
        result = simulate(config)
    if args.out:
        with Busy(f"simulate: writing {args.out}"):
            if str(args.out).lower().endswith(".ulg"):
                from magcomp.adapters.ulog_writer import write_sim_ulog

                count = write_sim_ulog(result, args.out)  # PX4 ULog (sensor_mag, sensor_combined, ...)
            elif str(args.out).lower().endswith(".bin"):
                from magcomp.adapters.dataflash_writer import write_sim_dataflash

                count = write_sim_dataflash(result, args.out)  # ArduPilot 4.x DataFlash (MAG, ATT, RCOU, ...)
            else:
                count = write_tlog(result, args.out)
            json_path, npz_path = write_truth(result, args.out)
        print(
            f"wrote {args.out}: {count} messages, {config.duration:.1f} s of {config.scenario} "
            f"({config.vehicle}); truth: {json_path.name}, {npz_path.name}"
        )
        return 0
    report = stream_to_link(result, args.link, speed=args.speed)
    got = ", ".join(f"{k} {v}" for k, v in sorted(report.received.items())) or "nothing"
    print(
        f"sent {report.sent} messages to {args.link} in {report.wall_s:.1f} s; received: {got}",
        file=sys.stdout,
    )
    return 0
