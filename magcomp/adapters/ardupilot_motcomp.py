"""ArduPilot's own motor compensation (COMPASS_MOTCT != 0), rebuilt from its parameters and undone.

What the autopilot does (ArduPilot AP_Compass, ``AP_Compass_Backend::correct_field``; same in Copter 3.3
through 4.x): after its offsets and the elliptical correction,
``state.motor_offset = mot * _compass._thr`` for ``AP_COMPASS_MOT_COMP_THROTTLE`` (COMPASS_MOTCT = 1) or
``mot * current`` for ``AP_COMPASS_MOT_COMP_CURRENT`` (COMPASS_MOTCT = 2, ``battery.current_amps()``), and
then ``mag += state.motor_offset``. ``mot`` is COMPASS_MOT_X/Y/Z for the first compass, COMPASS_MOT2_* and
COMPASS_MOT3_* for the others (mgauss per unit throttle, or per amp). The throttle is the one Copter hands to
``compass.set_throttle(motors->get_throttle())``: the collective 0..1, which is also what VFR_HUD.throttle
reports in percent (``GCS_MAVLINK_Copter::vfr_hud_throttle`` = ``motors->get_throttle() * 100``; Plane
reports its throttle percentage, which it also gives the compass). So the field a tlog carries in RAW_IMU /
SCALED_IMU2/3 is ``y_logged = y + mot * x`` and the field the motors disturbed is ``y = y_logged - mot * x``,
with x = VFR_HUD.throttle / 100 (COMPASS_MOTCT = 1) or SYS_STATUS.current_battery (A, COMPASS_MOTCT = 2),
the latest value received (the autopilot itself updates the compass at 10 Hz from its latest throttle).

DataFlash logs record the applied offset itself (MAG.MOfsX..), which the source subtracts directly (and
hands to :meth:`OnboardMotorComp.record` with CTUN's throttle, for the comparison below); the rebuilding is
for MAVLink (tlogs and live links), which carry only the compensated field.

Limits: compensation is undone only from the moment the parameters (PARAM_VALUE) and the driving quantity
are both known; samples before are counted (``motor_comp_unknown``) and pass unchanged. Per-motor
compensation (COMPASS_PMOT_EN = 1, compass 0 only) needs per-motor outputs scaled by the battery voltage:
not rebuilt (``motor_comp_per_motor``).

The onboard compensation is linear in x; the paper's model is theta * throttle^2 (eq. (11)). To compare them
in the same units, the applied offsets o_k are projected onto throttle^2 by least squares over the samples
where it was undone: theta_onboard = -sum(o_k delta_k^2) / sum(delta_k^4) (the bias the autopilot believed
in, as the theta of eq. (11) that best reproduces it over this flight's throttle).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from magcomp.core.autopilot_params import (
    MOTCT_CURRENT,
    MOTCT_THROTTLE,
    is_motor_comp_param,
    motor_comp_prefix,
    motor_comp_type,
    motor_comp_vector,
    per_motor_comp,
)

#: the onboard compensation differs from the learned theta when the chi-square of the difference (3 axes,
#: each over the learned theta's 1-sigma) exceeds this: the 99th percentile of chi-square with 3 degrees of
#: freedom, a 1 % false-alarm rate when the learned sigma is right
CHI2_3DOF_99 = 11.345


class OnboardMotorComp:
    """The autopilot's motor compensation as seen on the link: parameters, throttle, current."""

    def __init__(self) -> None:
        #: the motor-compensation parameters (set through :meth:`param`)
        self.params: dict[str, float] = {}
        self._motct = 0  # COMPASS_MOTCT of ``params``, taken again at each parameter (read per sample)
        self.throttle_01: float | None = None
        self.current_a: float | None = None
        # per compass: sum of o_k delta_k^2 (3), sum of delta_k^4, samples undone, last MOT vector
        self._sums: dict[int, list[Any]] = {}
        #: compasses whose COMPASS_MOT* is not a finite number (NaN: the autopilot's own output is then NaN
        #: too, or it ignores the compensation; either way it cannot be undone)
        self.invalid: set[int] = set()

    def param(self, name: str, value: float) -> None:
        if is_motor_comp_param(name):
            self.params[name] = float(value)
            self._motct = motor_comp_type(self.params)

    @property
    def motct(self) -> int:
        return self._motct

    def mot(self, index: int) -> tuple[float, float, float] | None:
        return motor_comp_vector(self.params, index)

    def offset(self, index: int, counts: dict[str, int]) -> tuple[float, float, float] | None:
        """The offset the autopilot added to compass ``index``'s field now (mgauss), or None when it added
        none or it cannot be known yet."""
        ct = self.motct
        if ct not in (MOTCT_THROTTLE, MOTCT_CURRENT):
            return None
        if per_motor_comp(self.params, index):
            counts["motor_comp_per_motor"] += 1
            return None
        mot = self.mot(index)
        x = self.throttle_01 if ct == MOTCT_THROTTLE else self.current_a
        if mot is None or x is None or not math.isfinite(x):
            counts["motor_comp_unknown"] += 1
            return None
        if not all(math.isfinite(v) for v in mot):
            self.invalid.add(index)
            counts["motor_comp_invalid"] += 1
            return None
        if not (mot[0] or mot[1] or mot[2]):
            return None
        o = (mot[0] * x, mot[1] * x, mot[2] * x)
        self.record(index, o)
        return o

    def record(self, index: int, applied: tuple[float, float, float] | Any) -> None:
        """Count an offset the autopilot applied to compass ``index`` (rebuilt here, or DataFlash MOfs) at the
        latest throttle, for the equivalent theta of :meth:`report`."""
        d = self.throttle_01
        if d is None:
            return
        s = self._sums.get(index)
        if s is None:
            s = self._sums[index] = [np.zeros(3), 0.0, 0, None]
        d2 = d * d
        s[0] += np.asarray(applied, dtype=float) * d2
        s[1] += d2 * d2
        s[2] += 1
        s[3] = self.mot(index)

    def report(self) -> dict[int, dict[str, Any]]:
        """Per compass whose compensation was undone: COMPASS_MOTCT, the last MOT vector, the samples, and
        the equivalent theta of eq. (11) in the logged frame (None without throttle^2 excitation)."""
        out: dict[int, dict[str, Any]] = {}
        for idx in sorted(self.invalid - set(self._sums)):
            out[idx] = {
                "motct": self.motct,
                "mot": None,
                "samples_undone": 0,
                "theta_equivalent_mgauss": None,
                "invalid": True,
            }
        for idx, (s_od2, s_d4, n, mot) in sorted(self._sums.items()):
            theta = None if s_d4 <= 1e-9 else (-s_od2 / s_d4).tolist()
            out[idx] = {
                "motct": self.motct,
                "mot": None if mot is None else list(mot),
                "samples_undone": int(n),
                "theta_equivalent_mgauss": theta,
            }
        return out


def onboard_comp_warnings(report: dict[int, dict[str, Any]], summary: dict[str, Any]) -> list[str]:
    """One warning per compass whose onboard compensation differs from the theta learned in flight by more
    than the learned theta's uncertainty (chi-square over its 1-sigma, 1 % false alarms; see CHI2_3DOF_99).
    Compared in the calibrated frame (the learned L maps the logged-frame equivalent there)."""
    out = []
    for idx, bad in sorted(report.items()):
        if bad.get("invalid"):
            pre = motor_comp_prefix(idx).rstrip("_")
            out.append(
                f"compass {idx}: {pre}_X/Y/Z is not a finite number with COMPASS_MOTCT={bad['motct']}: the "
                "autopilot's own motor compensation cannot be undone (its compass output is suspect; re-run "
                "compassmot or set COMPASS_MOTCT = 0)"
            )
    for c in summary.get("compasses", []):
        rep = report.get(int(c["index"]))
        inflight = c.get("inflight") or {}
        sig = inflight.get("theta_sigma_mgauss")
        if rep is None or rep["theta_equivalent_mgauss"] is None or sig is None:
            continue
        if c.get("status") != "corrected":
            continue
        cal = c.get("calibration") or {}
        l_mat = np.asarray(cal.get("L") or np.eye(3), dtype=float)
        onboard = l_mat @ np.asarray(rep["theta_equivalent_mgauss"], dtype=float)
        learned = np.asarray(c["theta_mgauss"], dtype=float)
        sd = np.maximum(np.asarray(sig, dtype=float), 1e-6)
        chi2 = float(np.sum(((onboard - learned) / sd) ** 2))
        rep["theta_onboard_calibrated_frame_mgauss"] = onboard.tolist()
        rep["chi2_vs_learned"] = chi2
        rep["differs"] = chi2 > CHI2_3DOF_99
        if chi2 > CHI2_3DOF_99:
            ob = ", ".join(f"{v:.1f}" for v in onboard)
            le = ", ".join(f"{v:.1f}" for v in learned)
            sg = ", ".join(f"{v:.1f}" for v in sd)
            pre = motor_comp_prefix(int(c["index"])).rstrip("_")
            out.append(
                f"compass {c['index']}: the autopilot's own motor compensation ({pre}*, COMPASS_MOTCT="
                f"{rep['motct']}) was wrong: as theta it is ({ob}) mgauss, the flight shows ({le}) +- "
                f"({sg}); magcomp undid it and corrects with the learned theta"
            )
    return out
