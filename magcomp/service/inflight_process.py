"""The types by which the calibrate stage and the compass state name a compass's in-flight calibration.

The two-pass replay runs in one process (service/replay.py): the forked in-flight and observer layers
are gone (CPU per log is what a fleet of logs pays; benchmarks/replay_speed.py). What is left here is the
call surface of :class:`~magcomp.service.inflight_stage.InflightStage` that ``service/calibrate.py`` and
``service/compass.py`` still name, with their remote branches, which no caller reaches any more; this
module goes once those branches are removed.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from magcomp.service.attitude import GyroYaw
from magcomp.service.inflight_stage import InflightOutput, InflightStage

F64 = NDArray[np.float64]


class InflightSink(Protocol):
    """What the calibrate stage calls on a compass's in-flight calibration (the stage itself)."""

    @property
    def mode(self) -> str: ...

    def reset_pairs(self) -> None: ...

    def restart(self, field_norm_mgauss: float) -> None: ...

    def feed(
        self,
        t_s: float,
        field_mgauss: F64 | tuple[float, float, float],
        throttle_01: float,
        motors_01: tuple[float, ...],
        r_abs_nb: F64 | None,
        field_ref_n_mgauss: F64 | None,
        r_rel_nb: F64 | None,
        r_t_s: float | None = None,
        throttle_t_s: float | None = None,
        gyro_yaw: GyroYaw | None = None,
    ) -> None: ...

    def output(
        self,
        t_s: float,
        field_mgauss: tuple[float, float, float],
        throttle_01: float,
        motors_01: tuple[float, ...],
    ) -> InflightOutput | None: ...


class RemoteInflight(InflightSink, Protocol):
    """A stage run elsewhere (none is any more; see the module's doc)."""

    def state(self) -> None: ...


class InflightProcess(Protocol):
    """Where stages ran elsewhere (none does any more; see the module's doc)."""

    def stage(
        self, idx: int, stage: InflightStage, replacing: RemoteInflight | None = None
    ) -> RemoteInflight: ...


__all__ = ["InflightProcess", "InflightSink", "RemoteInflight"]
