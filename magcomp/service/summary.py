"""The per-compass part of the pipeline's summary (plain values for JSON)."""

from __future__ import annotations

import math
from dataclasses import asdict
from typing import NamedTuple

import numpy as np

from magcomp.core.hover_theta import HoverTheta
from magcomp.core.selfcheck import SelfCheck
from magcomp.service.compass import CompassCorrector


class Status(NamedTuple):
    """Whether a compass's headings are corrected (``corrected`` | ``uncorrected``) and why, one phrase."""

    status: str
    why: str


def compass_summary(
    c: CompassCorrector, status: Status, check: SelfCheck | None = None, hover: HoverTheta | None = None
) -> dict[str, object]:
    """Calibration, theta, whether the headings are corrected and why: one compass."""
    cal = c.calibration
    st = c.inflight
    theta = np.asarray(c.theta.est.theta_mgauss, dtype=float).tolist()
    converged = bool(c.theta.est.converged)
    calibrated = c.calib.calibrated
    calib_doc: dict[str, object] | None = None
    if cal is not None:
        calib_doc = {
            "source": cal.source,
            "residual_rms_mgauss": cal.residual_rms_mgauss,
            "coverage": cal.coverage,
            "n": cal.n,
            "L": None if c.calib.calib_l is None else np.asarray(c.calib.calib_l).tolist(),
            "d_mgauss": None if c.calib.calib_d is None else np.asarray(c.calib.calib_d).tolist(),
        }
    elif st is not None and st.solution is not None and st.applied:
        sol = st.solution
        calibrated = True
        theta = sol.theta_mgauss.tolist()
        converged = sol.heading_sigma_deg < st.params.heading_converged_deg
        calib_doc = {
            "source": "in-flight",
            "residual_rms_mgauss": sol.residual_rms_mgauss,
            "n": sol.n,
            "L": sol.calib_l.tolist(),
            "d_mgauss": sol.calib_d.tolist(),
        }
    if hover is not None and status.status == "corrected":  # theta against the autopilot's calibration
        calibrated = True
        theta = hover.theta_mgauss.tolist()
        converged = False
        calib_doc = {
            "source": "autopilot",
            "residual_rms_mgauss": hover.residual_rms_mgauss,
            "n": hover.n,
            "theta_sigma_mgauss": hover.theta_sigma_mgauss.tolist(),
            # the jackknife's blocks of time (0: none; the sigma is per axis the larger of it and the fit's
            # own, white-residual one) and whether a block left out left too little to fit (a lower bound)
            "theta_sigma_blocks": hover.sigma_blocks,
            "theta_sigma_lower_bound": hover.sigma_lower_bound,
            "offset_change_mgauss": hover.offset_mgauss.tolist(),
            "heading_anchor_deg": math.degrees(hover.anchor_rad),
            "yaw_source": hover.yaw_source,
        }
    return {
        "index": c.mag_index,
        "calibrated": calibrated,
        "calibration": calib_doc,
        "theta_mgauss": theta,
        "theta_converged": converged,
        "estimates": c.n_out,
        "status": status.status,
        "why": status.why,
        "time_s": dict(c.time_s),
        "throttle2_flown": None if math.isnan(t2 := c.heading.throttle2_flown) else t2,
        "inflight": None if st is None else {**st.summary(), "rotation": c.rel_source.kind},
        "self_check": None if check is None else asdict(check),
    }
