"""Parameter files the ground stations load: QGroundControl ``.params`` and Mission Planner ``.param``.

QGroundControl (PX4 and ArduPilot): ``#`` comment lines, then one tab-separated row per parameter:
vehicle id, component id, name, value, MAV_PARAM_TYPE (6 = INT32, 9 = REAL32).
Mission Planner (ArduPilot): one ``NAME,VALUE`` line per parameter (``#`` comments allowed).

:func:`compensation_params` picks, from a diagnosis's per-compass suggestions, one consistent set for the
vehicle's autopilot: PX4's CAL_MAG_COMP_TYP and ArduPilot's COMPASS_MOTCT are global, so every compass uses
the primary compass's choice of throttle or current.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

from magcomp.adapters.files import write_file
from magcomp.errors import InputError

MAV_PARAM_TYPE_INT32 = 6
MAV_PARAM_TYPE_REAL32 = 9
_INTEGER_PARAMS = ("CAL_MAG_COMP_TYP", "COMPASS_MOTCT")
MAV_AUTOPILOT_PX4 = 12


def _is_int(name: str) -> bool:
    return name in _INTEGER_PARAMS or (name.startswith("CAL_MAG") and name.endswith("_ID"))


def _value_text(name: str, value: float) -> str:
    if _is_int(name):
        return str(round(value))
    return f"{value:.9g}"


def format_qgc_params(
    params: Mapping[str, float], *, vehicle_id: int = 1, component_id: int = 1, stack: str = ""
) -> str:
    lines = [f"# Onboard parameters for Vehicle {vehicle_id}", "#"]
    if stack:
        lines.append(f"# Stack: {stack}")
    lines += ["# written by magcomp", "#", "# Vehicle-Id Component-Id Name Value Type"]
    for name in sorted(params):
        ptype = MAV_PARAM_TYPE_INT32 if _is_int(name) else MAV_PARAM_TYPE_REAL32
        lines.append(f"{vehicle_id}\t{component_id}\t{name}\t{_value_text(name, params[name])}\t{ptype}")
    return "\n".join(lines) + "\n"


def format_mission_planner_param(params: Mapping[str, float]) -> str:
    lines = ["# written by magcomp"]
    lines += [f"{name},{_value_text(name, params[name])}" for name in sorted(params)]
    return "\n".join(lines) + "\n"


def write_param_file(
    path: str | os.PathLike[str], params: Mapping[str, float], *, vehicle_id: int = 1, stack: str = ""
) -> str:
    """Write ``params`` as QGroundControl ``.params`` or Mission Planner ``.param`` (by the extension);
    returns the format's name. InputError for another extension, a non-finite value or a write error."""
    bad = [name for name, value in params.items() if not math.isfinite(value)]
    if bad:
        raise InputError(f"cannot write {path}: no finite value for {', '.join(sorted(bad))}")
    suffix = Path(path).suffix.lower()
    if suffix == ".params":
        text, kind = format_qgc_params(params, vehicle_id=vehicle_id, stack=stack), "QGroundControl"
    elif suffix == ".param":
        text, kind = format_mission_planner_param(params), "Mission Planner"
    else:
        raise InputError(f"{path}: use .params (QGroundControl) or .param (Mission Planner)")
    write_file(path, text.encode("ascii"))
    return kind


def read_param_file(path: str | os.PathLike[str]) -> dict[str, float]:
    """Parameters of a ``.params`` (tab-separated) or ``.param`` (``NAME,VALUE``) file."""
    out: dict[str, float] = {}
    for line in Path(path).read_text(encoding="ascii").splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split("\t") if "\t" in line else line.replace(",", " ").split()
        name, value = (parts[2], parts[3]) if len(parts) >= 5 else (parts[0], parts[1])
        out[name] = float(value)
    return out


def compensation_params(
    suggestions: Sequence[tuple[int, Mapping[str, Mapping[str, float]]]], primary: int, autopilot: int
) -> tuple[dict[str, float], list[str]]:
    """One consistent parameter set from per-compass suggestions ``(index, {"px4": ..., "ardupilot": ...,
    "px4_throttle": ..., "px4_current": ...})``; returns it and notes on what was left out."""
    notes: list[str] = []
    by_index = dict(suggestions)
    if not by_index:
        return {}, ["no compensation parameters: no compass has any"]
    ref = primary
    if primary not in by_index:  # the shared setting (what drives the terms) follows the next compass's
        ref = min(by_index)
        notes.append(f"the primary compass {primary} has no compensation terms: the shared compensation type "
                     f"follows compass {ref}'s")  # fmt: skip
    out: dict[str, float] = {}
    if autopilot == MAV_AUTOPILOT_PX4:
        typ = by_index[ref].get("px4", {}).get("CAL_MAG_COMP_TYP", 1.0)
        key = "px4_current" if typ == 2.0 else "px4_throttle"
        for index, sugg in sorted(by_index.items()):
            chosen = sugg.get(key)
            if chosen is None:
                notes.append(f"compass {index}: no {key.split('_')[1]} terms, left out")
                continue
            out.update(chosen)
        return out, notes
    mot = by_index[ref].get("ardupilot", {})
    motct = mot.get("COMPASS_MOTCT", 1.0)
    for index, sugg in sorted(by_index.items()):
        ap = sugg.get("ardupilot", {})
        if ap.get("COMPASS_MOTCT", motct) != motct:
            notes.append(f"compass {index}: its terms use another COMPASS_MOTCT than compass {ref}'s, "
                         "left out")
            continue
        out.update({k: v for k, v in ap.items() if "_if_" not in k})
    return out, notes
