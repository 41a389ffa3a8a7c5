"""The innovation gate of the in-flight estimator: whether a row's a-priori residual is implausible under its
predictive covariance once the estimate has converged (a glitch), so that one bad sample cannot move a
converged estimate while a change the current uncertainty allows (e.g. the first throttle) is learned.
Pure (no state, no I/O)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from magcomp.core.inflight.base import (
    F64,
    GATE_CHI2_3DOF,
    GATE_SIGMA_FLOOR_MGAUSS,
    InflightParams,
    InflightSolution,
)


def innovation_gated(
    r: F64,
    rn2: float,
    rows: F64,
    nuisance: F64 | None,
    h_ee: F64 | None,
    cov: F64 | None,
    sol: InflightSolution | None,
    p: InflightParams,
) -> bool:
    """True when the a-priori residual ``r`` (3,; ``rn2`` = r'r, the window's nuisance removed) of a row
    (``rows``, nuisance columns ``nuisance`` with the window's unit-weight information ``h_ee``, None: the
    nuisance fitted to this row alone) is implausible under the predictive covariance: noise plus the
    parameters' own uncertainty (``cov``, unit weight) plus the nuisance's; chi-square, 3 dof, p = 1e-6 ->
    30.7. Only once the last solution ``sol`` has converged (heading sigma below
    ``p.heading_converged_deg``), and with the model error allowed for (the floor
    GATE_SIGMA_FLOOR_MGAUSS): before that, a large residual is the model learning, not a glitch. The noise
    scale is the last solution's."""
    if cov is None or sol is None or not sol.heading_sigma_deg < p.heading_converged_deg:
        return False
    s2 = max(sol.residual_rms_mgauss**2, GATE_SIGMA_FLOOR_MGAUSS**2)
    # pred >= s2 I, so r' pred^-1 r <= |r|^2 / s2: most samples pass without the 3x3 solve
    pred = s2 * np.eye(3) + rows @ cov @ rows.T if rn2 > GATE_CHI2_3DOF * s2 else None
    if pred is not None and nuisance is not None and h_ee is not None:
        # the window's nuisance is uncertain too (its covariance H_ee^-1, unit weight)
        pred = pred + s2 * (nuisance @ np.linalg.solve(h_ee, nuisance.T))
    try:
        m2 = 0.0 if pred is None else float(r @ np.linalg.solve(pred, r))
    except np.linalg.LinAlgError:
        m2 = 0.0
    return m2 > GATE_CHI2_3DOF


def innovation_gated_block(
    r: F64,
    rows: F64,
    nuisance: F64,
    h_ee: F64 | None,
    cov: F64 | None,
    sol: InflightSolution | None,
    p: InflightParams,
) -> NDArray[np.bool_]:
    """:func:`innovation_gated` for N rows of one nuisance window (a-priori residuals ``r`` (N, 3), rows
    (N, 3, n), nuisance columns (N, 3, k)): a mask (N,) of the implausible ones. The residuals are compared
    with the noise alone first, in one product; only the few above it are judged one by one."""
    out = np.zeros(r.shape[0], dtype=bool)
    if cov is None or sol is None or not sol.heading_sigma_deg < p.heading_converged_deg:
        return out
    s2 = max(sol.residual_rms_mgauss**2, GATE_SIGMA_FLOOR_MGAUSS**2)
    rn2 = np.einsum("ni,ni->n", r, r)
    for i in np.flatnonzero(rn2 > GATE_CHI2_3DOF * s2).tolist():
        out[i] = innovation_gated(r[i], float(rn2[i]), rows[i], nuisance[i], h_ee, cov, sol, p)
    return out
