"""The types by which the compass state and the theta stage name an observer stepped elsewhere.

The two-pass replay runs in one process (service/replay.py): the forked observer layer is gone (CPU per
log is what a fleet of logs pays; benchmarks/replay_speed.py). What is left here is the call surface that
``service/compass.py`` and ``service/theta.py`` still name in their remote branches, which no caller
reaches any more; this module goes once those branches are removed.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from magcomp.adapters.config import Config
from magcomp.service.estimators import ThetaEstimator, ThetaStepInfo

F64 = NDArray[np.float64]


class RemoteTheta(Protocol):
    """An observer stepped elsewhere (none is any more; see the module's doc)."""

    local: ThetaEstimator
    last_info: ThetaStepInfo | None

    def step(self, omega_b_rad_s: Sequence[float], field_b_mgauss: Sequence[float], throttle_01: float,
             dt_s: float) -> None: ...  # fmt: skip

    def reset_filters(self) -> None: ...

    def sync(self) -> None: ...


class ObserverProcess(Protocol):
    """Where observers stepped elsewhere (none does any more; see the module's doc)."""

    def estimator(self, idx: int, cfg: Config, theta0_mgauss: F64 | None) -> RemoteTheta: ...


__all__ = ["ObserverProcess", "RemoteTheta"]
