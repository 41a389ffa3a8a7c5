"""Does `magcomp diagnose`'s theta repeat across the real flights of one vehicle? (issue 26, item 4)

The development logs (``../shared/data/real-corpus.md``, fetched into a folder, default ``/work/corpus``) hold
three vehicles with several flights: four flights of one PX4 quad (luk8426), three logs of one Pixhawk 1
(yladzislay) and five telemetry logs of one quad (squilter). Each log is diagnosed as ``magcomp diagnose LOG``
does with no option (commands/diagnose.py ``diagnose_file``); per compass its theta is the free fit's where
the validity gate passes, else theta with the autopilot's calibration as prior (docs/diagnosis.md), each with
its 95 % half-width per axis.

Compasses are paired by the sensor they are, not by slot: the device id each log's parameters give its slots
(:mod:`magcomp.diagnosis.identity`; a slot's sensor changes when a GPS compass is unplugged). A log that does
not name its sensors joins the one sensor its vehicle's other flights have in that slot, with a note. For
every pair of flights of one sensor: do the two intervals overlap on all three axes (|theta_a - theta_b| <=
hw_a + hw_b per axis)? Also counted: the pairs whose two thetas diagnose calls identifiable (theta with the
prior: interval narrower than |theta|; both: the model-error bound where it applies), since an interval wider
than theta overlaps almost anything. Per flight its operating point (throttle range, battery current and its
slope against throttle^2, voltage), and for a disjoint pair the two side by side: a vehicle that draws another
current at hover is another load on the wires.

Measured (2026-11-27, docs/diagnosis.md): 23/25 pairs overlap, 1/3 with both thetas identifiable; the two
disjoint pairs are luk8426 flight 86 (21.3 A against 10.0 A) against flight 66. Before (by slot, theta with
the prior without the jackknife floor): 14/25.

    PYTHONPATH=. .venv/bin/python benchmarks/diagnosis_real_repeat.py [DIR] [--workers 2]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as the CLI: before numpy loads

import argparse
import itertools
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

#: vehicle -> its logs (file names as real-corpus.md saves them)
VEHICLES: dict[str, list[str]] = {
    "luk8426 PX4 quad": [
        "luk8426_flugdrohne_dritterflugtag-log_65_2023-6-21-08-36-08.ulg",
        "luk8426_flugdrohne_dritterflugtag-log_66_2023-6-21-08-44-02.ulg",
        "luk8426_flugdrohne_dritterflugtag-log_86_2023-6-21-11-13-04.ulg",
        "luk8426_flugdrohne_dritterflugtag-log_94_2023-6-21-11-28-18.ulg",
    ],
    "yladzislay Pixhawk 1": [
        f"yladzislay_dataflash-parser_tests-logs-dataflash-sample-{i}.bin" for i in (1, 2, 3)
    ],
    "squilter quad (telemetry)": [
        "squilter_gridlines_archived-2014-2015-kresge_01.tlog",
        "squilter_gridlines_archived-2014-2015-kresge_02.tlog",
        "squilter_gridlines_archived-2014-2015-kresge_03.tlog",
        "squilter_gridlines_mav-4a2dd50.tlog",
        "squilter_gridlines_mav-af32710.tlog",
    ],
}


@dataclass(frozen=True)
class CompassTheta:
    """One compass of one flight: its slot, the sensor in it (device id, None: the log does not say), theta,
    its 95 % half-width, where it came from, and whether diagnose calls it identifiable."""

    index: int
    sensor: int | None
    sensor_text: str
    theta: list[float]
    halfwidth: list[float]
    source: str
    identifiable: bool


@dataclass(frozen=True)
class OperatingPoint:
    """How the flight loaded the powertrain (throttle above 5 %): throttle 5-50-95th percentiles, the mean
    battery current (A) and voltage (V) when logged, the current's slope against throttle^2 (A at full
    throttle^2: what a theta per throttle^2 scales with), and the flying time (s)."""

    throttle: tuple[float, float, float]
    current_a: float | None
    voltage_v: float | None
    current_per_throttle2_a: float | None
    flying_s: float

    def text(self) -> str:
        t = self.throttle
        out = f"throttle {t[0]:.2f}-{t[2]:.2f} (median {t[1]:.2f}) over {self.flying_s:.0f} s"
        if self.current_a is not None:
            out += f", {self.current_a:.1f} A"
        if self.current_per_throttle2_a is not None:
            out += f" ({self.current_per_throttle2_a:.0f} A per throttle^2)"
        if self.voltage_v is not None:
            out += f" at {self.voltage_v:.1f} V"
        return out


def operating_point(log: Any) -> OperatingPoint | None:
    """The flight's :class:`OperatingPoint` from its LogData (None: no flying throttle)."""
    import numpy as np

    thr = log.throttle_01
    if len(thr) < 2:
        return None
    fly = thr.values > 0.05
    if int(np.sum(fly)) < 2:
        return None
    tf = thr.values[fly]
    dt = np.diff(thr.t_s, append=thr.t_s[-1])
    p5, p50, p95 = (float(v) for v in np.percentile(tf, [5, 50, 95]))

    def mean_over_flying(s: Any) -> tuple[float | None, Any]:
        if len(s) < 2:
            return None, None
        at = np.interp(s.t_s, thr.t_s, thr.values)
        ok = (at > 0.05) & np.isfinite(s.values)
        return (float(np.mean(s.values[ok])), (at[ok], s.values[ok])) if np.sum(ok) >= 10 else (None, None)

    current, pairs = mean_over_flying(log.current_a)
    slope = None
    if pairs is not None and float(np.ptp(pairs[0] ** 2)) > 0.0:
        slope = float(np.polyfit(pairs[0] ** 2, pairs[1], 1)[0])
    voltage, _ = mean_over_flying(log.voltage_v)
    return OperatingPoint((p5, p50, p95), current, voltage, slope, float(np.sum(dt[fly])))


def thetas(path: str) -> tuple[list[CompassTheta], OperatingPoint | None]:
    """Per compass its :class:`CompassTheta` (theta None: diagnose gives none), and the flight's operating
    point."""
    from magcomp.commands.diagnose import diagnose_file

    d, log = diagnose_file(path)
    out: list[CompassTheta] = []
    for c in d.to_json()["compasses"]:
        sensor = c.get("sensor") or {}
        dev, text = sensor.get("device_id"), sensor.get("text", "sensor not named in the log")
        prior = c.get("theta_given_prior")
        if c["observable"] and c.get("theta"):
            th, hw, src = c["theta"], c["theta_ci95_halfwidth"], "free fit"
            ident = c["gate"].get("theta_identifiable", True) is not False
        elif prior:
            th, hw, src, ident = prior["theta"], prior["theta_ci95_halfwidth"], "prior", prior["identifiable"]
        else:
            th, hw, src, ident = [], [], "none", False
        out.append(CompassTheta(int(c["index"]), dev, text, th, hw, src, ident))
    return out, operating_point(log)


def _v(x: list[float]) -> str:
    return "(" + ", ".join(f"{v:.0f}" for v in x) + ")"


def _name(f: str) -> str:
    return f.rsplit("-", 1)[-1] if "flugdrohne" not in f else f.split("-")[1]


Row = tuple[str, CompassTheta]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", nargs="?", default="/work/corpus")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    folder = Path(args.folder)
    files = [f for fs in VEHICLES.values() for f in fs if (folder / f).is_file()]
    if not files:
        print(
            f"{folder}: none of the development logs (../shared/data/real-corpus.md says how to fetch them)"
        )
        return 1
    from multiprocessing import Pool

    with Pool(args.workers) as pool:
        results = dict(zip(files, pool.map(thetas, [str(folder / f) for f in files]), strict=True))
    counts = {"all": [0, 0], "identifiable": [0, 0]}
    for vehicle, logs in VEHICLES.items():
        print(f"{vehicle}:")
        rows: list[Row] = []
        ops: dict[str, OperatingPoint | None] = {}
        for f in logs:
            if f not in results:
                continue
            comps, op = results[f]
            name = _name(f)
            ops[name] = op
            print(f"  {name}: {op.text() if op else 'no flying throttle'}")
            for c in comps:
                if not c.theta:
                    print(
                        f"    compass {c.index} [{c.sensor_text}]: no theta (the throttle varies too little)"
                    )
                    continue
                flag = "" if c.identifiable else ", flagged not identifiable"
                print(
                    f"    compass {c.index} [{c.sensor_text}]: theta {_v(c.theta)} +- {_v(c.halfwidth)} "
                    f"mgauss ({c.source}{flag})"
                )
                rows.append((name, c))
        from magcomp.diagnosis.identity import group_by_sensor

        groups, notes = group_by_sensor([(name, c.index, c.sensor) for name, c in rows])
        for note in notes:
            print(f"  note: {note}")
        for key, positions in groups.items():
            members = [rows[i] for i in positions]
            for (na, a), (nb, b) in itertools.combinations(members, 2):
                gap = [
                    abs(x - y) / max(wx + wy, 1e-9)
                    for x, y, wx, wy in zip(a.theta, b.theta, a.halfwidth, b.halfwidth, strict=True)
                ]
                ok = max(gap) <= 1.0
                both = a.identifiable and b.identifiable
                counts["all"][0] += ok
                counts["all"][1] += 1
                counts["identifiable"][0] += ok and both
                counts["identifiable"][1] += both
                line = f"    {key}: {na} c{a.index} vs {nb} c{b.index}: {'overlap' if ok else 'DISJOINT'}"
                if not both:
                    line += " (a theta flagged not identifiable: its interval is wide)"
                if not ok:
                    line += f" (largest gap {max(gap):.1f}x the summed half-widths); " + differ(
                        ops[na], ops[nb]
                    )
                print(line)
    ok_all, n_all = counts["all"]
    ok_id, n_id = counts["identifiable"]
    print(f"pairs of flights (same sensor) whose theta intervals overlap on all three axes: {ok_all}/{n_all}")
    print(f"  of them with both thetas identifiable: {ok_id}/{n_id}")
    return 0


def differ(a: OperatingPoint | None, b: OperatingPoint | None) -> str:
    """How two flights loaded the powertrain, side by side (what a theta per throttle^2 depends on besides
    the wiring: the current drawn, which grows with the vehicle's weight, and the throttle range it
    covers)."""
    if a is None or b is None:
        return "operating points unknown"
    out = f"median throttle {a.throttle[1]:.2f} vs {b.throttle[1]:.2f}"
    lo, hi = max(a.throttle[0], b.throttle[0]), min(a.throttle[2], b.throttle[2])
    if hi <= lo:
        out += " (throttle ranges do not overlap: one theta is an extrapolation for the other flight)"
    if a.current_a is not None and b.current_a is not None and min(a.current_a, b.current_a) > 0.0:
        out += (
            f", current {a.current_a:.1f} vs {b.current_a:.1f} A "
            f"({max(a.current_a, b.current_a) / min(a.current_a, b.current_a):.1f}x)"
        )
    return out


if __name__ == "__main__":
    raise SystemExit(main())
