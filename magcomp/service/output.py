"""Stage 6, publish: output decimation on message time, and the :class:`HeadingEstimate` of a record.

The estimate object (numpy vectors) is built only when a consumer asks for it
(:meth:`magcomp.service.pipeline.Pipeline.last_estimate`); MAGCOMP_HEADING is encoded from it by
:mod:`magcomp.service.publish`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from magcomp.adapters.config import Config
from magcomp.core.types import FLAG_CALIBRATED, HeadingEstimate
from magcomp.service.align import Counts
from magcomp.service.record import MagRecord

if TYPE_CHECKING:
    from magcomp.service.compass import CompassCorrector

NAN = float("nan")
_NAN3 = (NAN, NAN, NAN)


class PublishStage:
    """Decides which records are published (``[output] rate_hz``) and keeps the last one."""

    def __init__(self, cfg: Config, counts: Counts) -> None:
        self.counts = counts
        self._period = 1.0 / cfg.output.rate_hz if cfg.output.rate_hz > 0 else 0.0
        self.last: MagRecord | None = None

    def run(self, rec: MagRecord, c: CompassCorrector) -> bool:
        """True when ``rec`` is published (it is then :attr:`last`)."""
        corrected = bool(rec.flags & FLAG_CALIBRATED and rec.have_throttle)
        if self.due(c, rec.t_s, rec.prev_t, rec.reset, corrected):
            self.last = rec
            return True
        return False

    def due(self, c: CompassCorrector, t: float, prev_t: float | None, reset: bool, corrected: bool) -> bool:
        """True when compass ``c``'s sample at ``t`` is published; counts it and the time ``c`` spent
        ``corrected`` (calibrated, with the throttle known) or not (the summary)."""
        if prev_t is not None and not reset:
            c.time_s["corrected" if corrected else "uncorrected"] += t - prev_t
        if self._period > 0.0:
            if c.n_out > 0 and prev_t is not None and t - c.out_t < self._period and not reset:
                return False
            c.out_t = t
        c.n_out += 1
        self.counts["estimates"] += 1
        return True


def estimate(rec: MagRecord, boot_offset_s: float) -> HeadingEstimate:
    """The :class:`HeadingEstimate` of a published record (``boot_offset_s``: t_s - the autopilot's clock)."""
    info = rec.info
    return HeadingEstimate(
        t_s=rec.t_s,
        mag_index=rec.mag_index,
        heading_deg=rec.heading_deg,
        heading_raw_deg=rec.heading_raw_deg,
        theta_mgauss=np.array(rec.theta, dtype=float),
        bias_mgauss=np.array(rec.bias, dtype=float),
        throttle_01=rec.throttle_01,
        flags=rec.flags,
        field_raw_mgauss=rec.sample.field_b_mgauss,
        field_cal_mgauss=np.array(rec.field_corrected, dtype=float),
        residual_norm_mgauss=NAN if info is None else info.residual_norm_mgauss,
        excitation=NAN if info is None else info.excitation,
        t_boot_s=rec.t_s - boot_offset_s,
        theta_sigma_mgauss=_NAN3 if info is None or rec.inflight is not None else info.theta_std_mgauss,
    )
