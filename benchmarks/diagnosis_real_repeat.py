"""Does `magcomp diagnose`'s theta repeat across the real flights of one vehicle? (issue 26, item 4)

The development logs (``../shared/data/real-corpus.md``, fetched into a folder, default ``/work/corpus``) hold
three vehicles with several flights: four flights of one PX4 quad (luk8426), three logs of one Pixhawk 1
(yladzislay) and five telemetry logs of one quad (squilter). Each log is diagnosed as ``magcomp diagnose LOG``
does with no option (commands/diagnose.py ``diagnose_file``); per compass its theta is the free fit's where
the validity gate passes, else theta with the autopilot's calibration as prior (docs/diagnosis.md), each with
its 95 % half-width per axis. For every pair of flights of one vehicle and compass index: do the two intervals
overlap on all three axes (|theta_a - theta_b| <= hw_a + hw_b per axis)?

    PYTHONPATH=. .venv/bin/python benchmarks/diagnosis_real_repeat.py [DIR] [--workers 2]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as the CLI: before numpy loads

import argparse
import itertools
import sys
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


def thetas(path: str) -> dict[int, tuple[list[float], list[float], str] | None]:
    """Per compass index: (theta, 95 % half-width, where it came from), or None where diagnose gives none."""
    from magcomp.commands.diagnose import diagnose_file

    d, _ = diagnose_file(path)
    out: dict[int, tuple[list[float], list[float], str] | None] = {}
    for c in d.to_json()["compasses"]:
        prior = c.get("theta_given_prior")
        if c["observable"] and c.get("theta"):
            out[int(c["index"])] = (c["theta"], c["theta_ci95_halfwidth"], "free fit")
        elif prior:
            out[int(c["index"])] = (prior["theta"], prior["theta_ci95_halfwidth"], "prior")
        else:
            out[int(c["index"])] = None
    return out


def _v(x: list[float]) -> str:
    return "(" + ", ".join(f"{v:.0f}" for v in x) + ")"


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
        results: dict[str, Any] = dict(
            zip(files, pool.map(thetas, [str(folder / f) for f in files]), strict=True)
        )
    total = agree = 0
    for vehicle, logs in VEHICLES.items():
        print(f"{vehicle}:")
        per: dict[int, list[tuple[str, list[float], list[float]]]] = {}
        for f in logs:
            for idx, th in sorted(results.get(f, {}).items()):
                name = f.rsplit("-", 1)[-1] if "flugdrohne" not in f else f.split("-")[1]
                if th is None:
                    print(f"  {name} compass {idx}: no theta (the throttle does not vary enough)")
                    continue
                print(f"  {name} compass {idx}: theta {_v(th[0])} +- {_v(th[1])} mgauss ({th[2]})")
                per.setdefault(idx, []).append((name, th[0], th[1]))
        for idx, rows in sorted(per.items()):
            for (na, a, ha), (nb, b, hb) in itertools.combinations(rows, 2):
                ok = all(abs(x - y) <= wx + wy for x, y, wx, wy in zip(a, b, ha, hb, strict=True))
                total += 1
                agree += ok
                print(f"    compass {idx}: {na} vs {nb}: {'overlap' if ok else 'DISJOINT'}")
    print(f"pairs of flights whose theta intervals overlap on all three axes: {agree}/{total}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
