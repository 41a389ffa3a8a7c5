"""Product QA sweep: ``magcomp replay`` and ``magcomp diagnose`` on varied simulated logs and damaged files.

Each case is a file the project has not seen: a simulated flight with one knob changed (rates, yaw source,
external compass, calibration, place, theta's size, link loss, no GPS, PX4 ULog, a hidden effect) or a
damaged one (truncated mid-message, random bytes flipped, two logs concatenated, throttle / parameter /
GPS messages removed, a clock reset, 5 s long, empty, a directory, not a log). For each the sweep runs, as
a user would, with no configuration::

    magcomp replay LOG --json OUT.json --emit OUT.tlog   (plus --causal on a few)
    magcomp diagnose LOG --json OUT.json

and checks: no traceback (bad input: one line on stderr and a non-zero exit); the JSON strictly valid (no
NaN / Infinity) with a status and a reason per compass; where the log has a simulated truth, the rms heading
error (after the first 60 s of flight, ``magcomp.service.demo.rms_after_learning``) of the corrected and
uncorrected headings read back from the emitted MAGCOMP_HEADING, and the oracle's (true calibration and
theta, no learning; not with ``--quick``), and the reported heading sigma against the error.

One line per case: case, replay exit / per compass status, corrected / uncorrected / oracle rms (deg),
the reported heading sigma (deg), diagnose's exit, and any problem (``PROBLEM:`` marks a failed check).

    .venv/bin/python benchmarks/product_sweep.py [--quick] [--seed 0] [--keep DIR] [--only NAME ...]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import logging
import math
import shutil
import struct
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from magcomp.sim import SimConfig, simulate
from magcomp.sim.config import apply_settings

#: MAVLink message ids removed by the damage cases
THROTTLE_IDS = {36, 35, 65, 74, 291}  # SERVO_OUTPUT_RAW, RC_CHANNELS_RAW, RC_CHANNELS, VFR_HUD, ESC_STATUS
PARAM_IDS = {22}  # PARAM_VALUE
GPS_IDS = {24, 33, 2}  # GPS_RAW_INT, GLOBAL_POSITION_INT, SYSTEM_TIME
MAGCOMP_HEADING_ID = 45000


@dataclass
class Case:
    name: str
    build: Callable[[Path], tuple[Path, Any]]  # tmp dir -> (log path, SimResult or None)
    causal: bool = False  # also run replay --causal
    expect_error: bool = False  # bad input: a non-zero exit with one line is the right answer


@dataclass
class Est:
    """What rms_after_learning reads of a HeadingEstimate, from an emitted MAGCOMP_HEADING."""

    t_s: float
    mag_index: int
    heading_deg: float
    heading_raw_deg: float
    flags: int


# ---------------------------------------------------------------- tlog frames


def tlog_frames(data: bytes) -> list[tuple[bytes, int]]:
    """Split a tlog into (timestamp + frame bytes, msgid); stops at the first frame that does not fit."""
    out: list[tuple[bytes, int]] = []
    i = 0
    while i + 8 < len(data):
        magic = data[i + 8]
        if magic == 0xFD:
            n = data[i + 9]
            sig = 13 if data[i + 10] & 1 else 0
            end = i + 8 + 10 + n + 2 + sig
            msgid = int.from_bytes(data[i + 15 : i + 18], "little")
        elif magic == 0xFE:
            n = data[i + 9]
            end = i + 8 + 6 + n + 2
            msgid = data[i + 13]
        else:
            break
        if end > len(data):
            break
        out.append((data[i:end], msgid))
        i = end
    return out


def drop_messages(src: Path, dst: Path, ids: set[int]) -> None:
    dst.write_bytes(b"".join(f for f, m in tlog_frames(src.read_bytes()) if m not in ids))


def read_headings(path: Path) -> list[Est]:
    """MAGCOMP_HEADING (MAVLink 2, payload zero-truncated) from an emitted tlog."""
    out: list[Est] = []
    for frame, msgid in tlog_frames(path.read_bytes()):
        if msgid != MAGCOMP_HEADING_ID:
            continue
        n = frame[9]
        payload = frame[18 : 18 + n].ljust(42, b"\0")
        ms, hdg, raw = struct.unpack_from("<Iff", payload, 0)
        idx, flags = payload[40], payload[41]
        out.append(Est(ms / 1000.0, idx, hdg, raw, flags))
    return out


# ---------------------------------------------------------------- cases


def _sim(name: str, scenario: str, settings: list[str], duration: float | None, seed: int,
         n_compasses: int = 2, effects: dict[str, float] | None = None, ulog: bool = False,
         dataflash: bool = False,
         dataflash_4x: bool = False) -> Callable[[Path], tuple[Path, Any]]:  # fmt: skip
    def build(tmp: Path) -> tuple[Path, Any]:
        from magcomp.adapters.mavlink_emit import write_tlog, write_truth

        cfg = SimConfig(scenario=scenario, duration_s=duration, seed=seed, n_compasses=n_compasses,
                        effects=effects or {})  # fmt: skip
        cfg = apply_settings(cfg, settings) if settings else cfg
        result = simulate(cfg)
        path = tmp / (name + (".ulg" if ulog else ".bin" if dataflash or dataflash_4x else ".tlog"))
        if dataflash_4x:  # as ArduPilot 4.x logs it (PARM, MSG, IMU, MAG, ATT, RCOU, CTUN, BAT, GPS)
            from magcomp.adapters.dataflash_writer import write_sim_dataflash

            write_sim_dataflash(result, path)
        elif dataflash:  # the tests' minimal ArduPilot DataFlash writer (FMT, MSG, IMU, MAG, CTUN)
            from tests.faultgen import write_dataflash

            write_dataflash(result, path)
        elif ulog:
            from magcomp.adapters.ulog_writer import write_sim_ulog

            # as PX4's default logging profile has them: vehicle_magnetometer (body frame, calibrated) beside
            # sensor_mag in the drivers' frames (a yawed board, a rolled external compass, offsets)
            write_sim_ulog(result, path, mag_topic="both", sensor_frame=True)
        else:
            write_tlog(result, path)
        write_truth(result, path)
        return path, result

    return build


def _damaged(name: str, base: Callable[[Path], tuple[Path, Any]], damage: Callable[[Path, Path], None],
             keep_truth: bool = False) -> Callable[[Path], tuple[Path, Any]]:  # fmt: skip
    def build(tmp: Path) -> tuple[Path, Any]:
        sub = tmp / (name + ".src")
        sub.mkdir()
        src, result = base(sub)
        dst = tmp / (name + src.suffix)
        damage(src, dst)
        return dst, (result if keep_truth else None)

    return build


def _truncate(src: Path, dst: Path) -> None:
    data = src.read_bytes()
    dst.write_bytes(data[: int(len(data) * 0.6) + 7])  # mid-message


def _flip(seed: int) -> Callable[[Path, Path], None]:
    def damage(src: Path, dst: Path) -> None:
        data = bytearray(src.read_bytes())
        rng = np.random.default_rng(seed)
        for k in rng.integers(0, len(data), size=len(data) // 2000):
            data[int(k)] ^= int(rng.integers(1, 256))
        dst.write_bytes(bytes(data))

    return damage


def _concat(other: Callable[[Path], tuple[Path, Any]], head: float = 1.0) -> Callable[[Path, Path], None]:
    def damage(src: Path, dst: Path) -> None:
        sub = dst.parent / (dst.stem + ".other")
        sub.mkdir()
        o, _ = other(sub)
        data = src.read_bytes()
        frames = tlog_frames(data)
        first = b"".join(f for f, _ in frames[: int(len(frames) * head)])
        dst.write_bytes(first + o.read_bytes())

    return damage


def _drop(ids: set[int]) -> Callable[[Path, Path], None]:
    return lambda src, dst: drop_messages(src, dst, ids)


def _empty(tmp: Path) -> tuple[Path, Any]:
    p = tmp / "empty.tlog"
    p.write_bytes(b"")
    return p, None


def _directory(tmp: Path) -> tuple[Path, Any]:
    p = tmp / "adir.tlog"
    p.mkdir()
    return p, None


def _text(tmp: Path) -> tuple[Path, Any]:
    p = tmp / "notes.tlog"
    p.write_text("this is a shopping list, not a flight log\n" * 200)
    return p, None


def _random_bin(tmp: Path) -> tuple[Path, Any]:
    p = tmp / "noise.bin"
    p.write_bytes(np.random.default_rng(3).integers(0, 256, 200_000, dtype=np.uint8).tobytes())
    return p, None


def _missing(tmp: Path) -> tuple[Path, Any]:
    return tmp / "does_not_exist.tlog", None


def cases(seed: int, quick: bool) -> list[Case]:
    d = 150.0 if quick else None  # the scenario's own duration (300 s ordinary) in the full sweep
    s = seed
    ordinary = _sim("ordinary", "ordinary", [], d, s)
    out = [
        Case("ordinary", ordinary, causal=True),
        Case("ordinary_x6", _sim("ordinary_x6", "ordinary", ["theta_scale=6"], d, s + 1), causal=True),
        Case("plane", _sim("plane", "ordinary_plane", [], d, s + 2)),
        Case("tlm_1hz", _sim("tlm_1hz", "ordinary", ["telemetry_hz=1", "theta_scale=6"], d, s + 3)),
        Case("mag_10hz", _sim("mag_10hz", "ordinary", ["mag_hz=10"], d, s + 4)),
        Case("yaw_truth", _sim("yaw_truth", "ordinary", ["yaw_source=truth", "theta_scale=6"], d, s + 5)),
        Case(
            "external0",
            _sim("external0", "ordinary", ["external_compass0=on", "theta_scale=6"], d, s + 6),
            causal=True,
        ),
        Case(
            "primary1_3c",
            _sim("primary1_3c", "ordinary", ["primary_compass=1", "theta_scale=3"], d, s + 7, n_compasses=3),
        ),
        Case("1compass", _sim("1compass", "ordinary", ["theta_scale=6"], d, s + 8, n_compasses=1)),
        Case("ap_cal_off", _sim("ap_cal_off", "ordinary", ["ap_calibration=off", "theta_scale=6"], d, s + 9)),
        Case("hard_iron_60", _sim("hard_iron_60", "ordinary", ["ap_cal_hard_iron_mgauss=60"], d, s + 10)),
        Case(
            "ljubljana",
            _sim(
                "ljubljana",
                "ordinary",
                ["lat_deg=46.05", "lon_deg=14.5", "decimal_year=2027.2", "theta_scale=6"],
                d,
                s + 11,
            ),
        ),
        Case(
            "high_lat",
            _sim("high_lat", "ordinary", ["lat_deg=78.2", "lon_deg=15.6", "theta_scale=6"], d, s + 12),
        ),
        Case(
            "ar1_noise", _sim("ar1_noise", "ordinary", ["mag_ar1_sigma_mgauss=5", "theta_scale=6"], d, s + 13)
        ),
        Case("link_loss", _sim("link_loss", "ordinary", ["link_loss=0.2", "theta_scale=6"], d, s + 14)),
        Case("gps_off", _sim("gps_off", "ordinary", ["gps=off", "theta_scale=6"], d, s + 15)),
        Case("hover_0.3", _sim("hover_0.3", "ordinary", ["hover_throttle=0.3", "theta_scale=6"], d, s + 16)),
        Case("px4_ulog", _sim("px4_ulog", "ordinary", ["theta_scale=6"], d, s + 17, ulog=True), causal=True),
        Case(
            "effect_offset",
            _sim(
                "effect_offset", "ordinary", ["theta_scale=6"], d, s + 18, effects={"throttle_offset": 0.15}
            ),
        ),
        Case("paper", _sim("paper", "paper", [], None, s + 19)),
        Case("bench", _sim("bench", "bench", [], None, s + 20)),
        Case("flight_fw", _sim("flight_fw", "flight_fixedwing", [], None, s + 21)),
        Case("short_5s", _sim("short_5s", "ordinary", [], 5.0, s + 22)),
        # damaged
        Case("truncated", _damaged("truncated", ordinary, _truncate, keep_truth=True)),
        Case("flipped", _damaged("flipped", ordinary, _flip(s), keep_truth=True)),
        Case("concat", _damaged("concat", ordinary, _concat(_sim("o2", "ordinary", [], d, s + 30)))),
        Case(
            "clock_reset",
            _damaged(
                "clock_reset",
                ordinary,
                _concat(_sim("o3", "ordinary", ["theta_scale=6"], d, s + 31), head=0.5),
            ),
        ),
        Case("no_throttle", _damaged("no_throttle", ordinary, _drop(THROTTLE_IDS), keep_truth=True)),
        Case(
            "no_params",
            _damaged(
                "no_params",
                _sim("np6", "ordinary", ["theta_scale=6"], d, s + 32),
                _drop(PARAM_IDS),
                keep_truth=True,
            ),
        ),
        Case("no_gps_msgs", _damaged("no_gps_msgs", ordinary, _drop(GPS_IDS), keep_truth=True)),
        Case(
            "dataflash_bin", _sim("dataflash_bin", "ordinary", ["theta_scale=6"], d, s + 34, dataflash=True)
        ),
        Case(
            "dataflash_4x",
            _sim("dataflash_4x", "ordinary", ["theta_scale=6"], d, s + 36, dataflash_4x=True),
            causal=True,
        ),
        Case(
            "dataflash_4x_plane",
            _sim("dataflash_4x_plane", "ordinary_plane", [], d, s + 37, dataflash_4x=True),
        ),
        Case(
            "flipped_bin",
            _damaged(
                "flipped_bin",
                _sim("fb", "ordinary", [], d, s + 35, dataflash=True),
                _flip(s),
                keep_truth=True,
            ),
        ),
        Case(
            "truncated_ulog",
            _damaged("truncated_ulog", _sim("tu", "ordinary", [], d, s + 33, ulog=True), _truncate),
        ),
        Case("empty", _empty, expect_error=True),
        Case("directory", _directory, expect_error=True),
        Case("text_file", _text, expect_error=True),
        Case("random_bytes", _random_bin, expect_error=True),
        Case("missing", _missing, expect_error=True),
    ]
    if quick:
        keep = {
            "ordinary",
            "ordinary_x6",
            "tlm_1hz",
            "external0",
            "1compass",
            "gps_off",
            "px4_ulog",
            "short_5s",
            "truncated",
            "flipped",
            "concat",
            "no_throttle",
            "no_params",
            "empty",
            "directory",
            "text_file",
            "missing",
            "random_bytes",
            "flipped_bin",
        }
        out = [c for c in out if c.name in keep]
    return out


# ---------------------------------------------------------------- checks


def _run(argv: list[str], timeout: float) -> tuple[int, str, str]:
    try:
        p = subprocess.run([sys.executable, "-m", "magcomp", *argv], capture_output=True, text=True,
                           timeout=timeout, cwd=Path(__file__).resolve().parents[1])  # fmt: skip
    except subprocess.TimeoutExpired:
        return -999, "", "timeout"
    return p.returncode, p.stdout, p.stderr


def _strict_json(path: Path) -> tuple[dict[str, Any] | None, str]:
    def bad(token: str) -> Any:
        raise ValueError(f"non-finite {token}")

    try:
        return json.loads(path.read_text(), parse_constant=bad), ""
    except (OSError, ValueError) as exc:
        return None, f"JSON invalid: {exc}"


def _stderr_problems(rc: int, err: str, expect_error: bool, what: str) -> list[str]:
    problems = []
    if "Traceback" in err or rc == -999:
        last = [ln for ln in err.strip().splitlines() if ln.strip()][-1:] or ["?"]
        problems.append(f"{what} {'timeout' if rc == -999 else 'TRACEBACK: ' + last[0][:160]}")
    elif rc != 0 and not err.strip():
        problems.append(f"{what} exit {rc} without a message")
    if expect_error and rc == 0:
        problems.append(f"{what} exit 0 on bad input")
    return problems


def _oracle(path: Path, result: Any) -> list[Any]:
    from magcomp.adapters.config import Config
    from magcomp.adapters.state_store import StateStore
    from magcomp.service.demo import save_true_states
    from magcomp.service.replay import replay_log

    cfg = Config()
    ocfg = replace(cfg, observer=replace(cfg.observer, learn=False),
                   calibration=replace(cfg.calibration, mode="stored"))  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        store = StateStore(Path(tmp) / "oracle")
        save_true_states(result, store)
        logging.disable(logging.WARNING)  # the oracle's own warnings (e.g. no throttle) are the replay's too
        try:
            with contextlib.redirect_stderr(io.StringIO()):
                return list(replay_log(path, ocfg, store=store, keep_estimates=True).estimates)
        finally:
            logging.disable(logging.NOTSET)


def run_case(case: Case, tmp: Path, oracle: bool, timeout: float) -> str:
    from magcomp.service.demo import rms_after_learning

    problems: list[str] = []
    try:
        log, result = case.build(tmp)
    except Exception as exc:  # the sweep's own setup; reported, never hidden
        return f"{case.name:15s} SETUP FAILED {type(exc).__name__}: {exc}"
    out_json, out_emit = tmp / f"{case.name}.out.json", tmp / f"{case.name}.out.tlog"
    t0 = time.perf_counter()
    rc, stdout, err = _run(["replay", str(log), "--json", str(out_json), "--emit", str(out_emit)], timeout)
    wall = time.perf_counter() - t0
    problems += _stderr_problems(rc, err, case.expect_error, "replay")
    parts = [f"replay {rc}"]
    doc = None
    if rc == 0:
        doc, msg = _strict_json(out_json)
        if msg:
            problems.append(msg)
    elif not case.expect_error:
        parts.append("'" + (err.strip().splitlines() or ["?"])[-1][:120] + "'")
    elif err.strip():
        parts.append("'" + err.strip().splitlines()[-1][:100] + "'")
        if len([ln for ln in err.strip().splitlines() if ln.strip()]) > 2:
            problems.append(f"replay error is {len(err.strip().splitlines())} lines")
    ests = read_headings(out_emit) if rc == 0 and out_emit.exists() else []
    comps = (doc or {}).get("compasses", [])
    if doc is not None and not comps:
        parts.append("no compasses in JSON")
    orc: list[Any] = []
    if oracle and result is not None and rc == 0 and comps:
        try:
            orc = _oracle(log, result)
        except Exception as exc:
            parts.append(f"oracle failed {type(exc).__name__}")
    for c in comps:
        j = c.get("index")
        status, why = c.get("status"), c.get("why")
        if not status or not why:
            problems.append(f"compass {j}: no status/why")
        tag = f"c{j} {status}"
        sig = (c.get("inflight") or {}).get("heading_sigma_deg")
        if result is not None and any(e.mag_index == j for e in ests):
            try:
                with np.errstate(all="ignore"), warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)
                    cor, raw = rms_after_learning(result, ests, j)  # type: ignore[arg-type]
                    if not math.isfinite(cor):  # under 60 s of flight: score all of it ('*')
                        cor, raw = rms_after_learning(result, ests, j, learn_s=0.0)  # type: ignore[arg-type]
                        tag += "*"
            except Exception as exc:
                problems.append(f"c{j} scoring {type(exc).__name__}: {exc}")
                cor = raw = float("nan")
            tag += f" {cor:.2f}/{raw:.2f}"
            learn_s = 60.0 if "*" not in tag else 0.0
            o_rms = rms_after_learning(result, orc, j, learn_s=learn_s)[0] if orc else 0.0
            if orc:
                tag += f" oracle {o_rms:.2f}"
            if status == "corrected" and math.isfinite(cor) and math.isfinite(raw) and cor > raw + 0.5 \
                    and cor > 1.2 * raw:  # fmt: skip
                problems.append(f"c{j} corrected worse than uncorrected ({cor:.2f} > {raw:.2f} deg)")
            # the sigma covers what learning adds: compare it with the error beyond the oracle's (when run)
            excess = math.sqrt(max(cor**2 - o_rms**2, 0.0)) if math.isfinite(o_rms) else cor
            if sig is not None and math.isfinite(cor) and status == "corrected" and excess > 5 * sig + 0.5:
                ref = "beyond the oracle's" if orc else "(no oracle run)"
                problems.append(f"c{j} sigma {sig:.2f} deg << error {excess:.2f} deg {ref}")
        if sig is not None:
            tag += f" sig {sig:.2f}"
        parts.append(tag)
    if case.causal and rc == 0:
        rc_c, _, err_c = _run(["replay", str(log), "--causal", "--json", str(tmp / "causal.json")], timeout)
        problems += _stderr_problems(rc_c, err_c, False, "replay --causal")
        if rc_c == 0:
            cdoc, msg = _strict_json(tmp / "causal.json")
            if msg:
                problems.append("causal " + msg)
            parts.append(
                "causal " + ",".join(str(c.get("status")) for c in (cdoc or {}).get("compasses", []))
            )
    diag_json = tmp / f"{case.name}.diagnose.json"
    rc_d, out_d, err_d = _run(["diagnose", str(log), "--json", str(diag_json)], timeout)
    problems += _stderr_problems(rc_d, err_d, case.expect_error, "diagnose")
    parts.append(f"diagnose {rc_d}")
    if rc_d == 0:
        _, msg = _strict_json(diag_json)
        if msg:
            problems.append("diagnose " + msg)
    if rc_d != 0 and not case.expect_error:
        parts.append("'" + (err_d.strip().splitlines() or ["?"])[-1][:120] + "'")
    for pat in ("nan", "inf "):
        if pat in (stdout + out_d).lower().replace("infl", "").replace("info", ""):
            problems.append(f"'{pat.strip()}' in the console text")
    line = f"{case.name:15s} {wall:5.1f}s  " + "; ".join(parts)
    if problems:
        line += "  PROBLEM: " + " | ".join(problems)
    return line


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer cases, 150 s flights, no oracle")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", nargs="+", default=[], help="case names")
    ap.add_argument("--keep", type=Path, help="keep the logs and outputs in this directory")
    ap.add_argument("--timeout", type=float, default=300.0, help="per command, s")
    args = ap.parse_args()
    todo = [c for c in cases(args.seed, args.quick) if not args.only or c.name in args.only]
    print("case            replay  status per compass: corrected/uncorrected rms deg (after 60 s of flight), "
          "oracle rms, reported heading sigma; diagnose exit")  # fmt: skip
    bad = 0
    for case in todo:
        tmp = Path(tempfile.mkdtemp(prefix=f"sweep-{case.name}-"))
        try:
            line = run_case(case, tmp, oracle=not args.quick, timeout=args.timeout)
        finally:
            if args.keep:
                dst = args.keep / case.name
                shutil.rmtree(dst, ignore_errors=True)
                shutil.copytree(tmp, dst, symlinks=True)
            shutil.rmtree(tmp, ignore_errors=True)
        bad += "PROBLEM" in line
        print(line, flush=True)
    print(f"\n{len(todo)} cases, {bad} with a problem")
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
