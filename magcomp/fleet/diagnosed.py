"""`magcomp diagnose` inside a fleet row: its findings with their intervals, its theta (free fit, or with the
autopilot's calibration as prior where only that is unobservable) and the compensation parameters it would
write, per compass; and the log's excitation from the same read (no second pass over the estimates).

The diagnosis is the one ``magcomp diagnose LOG`` prints with no option (commands/diagnose.py
``diagnose_file``). A diagnosis that fails leaves the replay's row intact with ``diagnose_status = failed``
and its one-line reason.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from magcomp.diagnosis.export import finding_text
from magcomp.service.console import json_safe

#: a throttle above this (0..1) counts as flying, for ``flight_s``
FLYING_THROTTLE = 0.15


@dataclass
class LogDiagnosis:
    """Per compass index the ``diagnose_*`` columns; the excitation of the log (its first compass's samples,
    the throttle at them)."""

    columns: dict[int, dict[str, Any]] = field(default_factory=dict)
    duration_s: float = math.nan
    flight_s: float = math.nan
    throttle_min: float = math.nan
    throttle_max: float = math.nan


def diagnose_columns(path: str, config: str | None) -> LogDiagnosis:
    """The diagnosis of one log as row columns (raises what diagnose raises: the caller makes it a reason)."""
    from magcomp.commands.diagnose import add_heading_checks, diagnose_file

    d, log = diagnose_file(path, config=config)
    out = LogDiagnosis()
    _excitation(out, log)
    j = d.to_json()
    add_heading_checks(j, d, log)
    for c in j["compasses"]:
        out.columns[int(c["index"])] = compass_columns(c)
    return out


def _excitation(out: LogDiagnosis, log: Any) -> None:
    """Duration, flying time and throttle range over the first compass's samples (throttle interpolated)."""
    mags = [log.mag[i] for i in sorted(log.mag) if len(log.mag[i]) >= 2]
    if not mags:
        return
    t = np.asarray(mags[0].t_s, dtype=float)
    out.duration_s = float(t[-1] - t[0])
    thr = log.throttle_01
    if len(thr) < 2:
        return
    tt, tv = np.asarray(thr.t_s, dtype=float), np.asarray(thr.values, dtype=float).ravel()
    ok = np.isfinite(tv)
    if np.count_nonzero(ok) < 2:
        return
    at = np.interp(t, tt[ok], tv[ok])
    out.throttle_min, out.throttle_max = float(np.min(at)), float(np.max(at))
    out.flight_s = out.duration_s * float(np.mean(at > FLYING_THROTTLE))


def compass_columns(c: dict[str, Any]) -> dict[str, Any]:
    """One compass of ``Diagnosis.to_json()`` as the row's ``diagnose_*`` columns."""
    prior = c.get("theta_given_prior")
    if c.get("observable"):
        theta, hw, frm = c.get("theta"), c.get("theta_ci95_halfwidth"), "free fit"
        joint = c.get("theta_ci95_joint_halfwidth")
        gate = c.get("gate")
        gate = gate if isinstance(gate, dict) else {}
        identifiable = bool(gate.get("theta_identifiable", True))
    elif prior:
        theta, hw = prior.get("theta"), prior.get("theta_ci95_halfwidth")
        joint = prior.get("theta_ci95_joint_halfwidth")
        frm = "autopilot calibration as prior"
        identifiable = bool(prior.get("identifiable"))
    else:
        theta, hw, joint, frm, identifiable = None, None, None, "", False
    theta = theta or [None] * 3
    hw = hw or [None] * 3
    joint = joint or [None] * 3
    findings = c.get("findings") or []
    params = c.get("autopilot") or {}
    if (c.get("heading_vs_gyro") or {}).get("worse"):
        params = {}  # its theta makes the heading worse against the gyro: diagnose writes none for it
    return {
        "diagnose_status": "ok",
        "diagnose_observable": bool(c.get("observable")),
        "diagnose_why": str(c.get("unobservable_why") or ""),
        "diagnose_theta_from": frm,
        "diagnose_theta_x_mgauss": theta[0],
        "diagnose_theta_y_mgauss": theta[1],
        "diagnose_theta_z_mgauss": theta[2],
        "diagnose_theta_ci95_x_mgauss": hw[0],
        "diagnose_theta_ci95_y_mgauss": hw[1],
        "diagnose_theta_ci95_z_mgauss": hw[2],
        # the box that holds the whole vector with 95 % (Bonferroni over the axes, diagnosis.intervals)
        "diagnose_theta_ci95_joint_x_mgauss": joint[0],
        "diagnose_theta_ci95_joint_y_mgauss": joint[1],
        "diagnose_theta_ci95_joint_z_mgauss": joint[2],
        "diagnose_theta_identifiable": identifiable if theta[0] is not None else None,
        "diagnose_findings": "; ".join(finding_text(f) for f in findings) or "no finding",
        "diagnose_findings_json": json.dumps(json_safe(findings), allow_nan=False, default=str),
        "diagnose_params_json": json.dumps(json_safe(params), allow_nan=False) if params else None,
    }


def failed_columns(why: str) -> dict[str, Any]:
    return {"diagnose_status": "failed", "diagnose_error": why}
