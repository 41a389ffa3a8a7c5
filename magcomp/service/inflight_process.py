"""The names by which the calibrate stage and the compass state refer to a compass's in-flight calibration.

The two-pass replay runs in one process (service/replay.py): the forked in-flight and observer layers
are gone (CPU per log is what a fleet of logs pays; benchmarks/replay_speed.py). What is left here are the
names ``service/calibrate.py`` and ``service/compass.py`` still use in their remote branches, which no
caller reaches any more (nothing passes them an :class:`InflightProcess`); this module goes once those
branches are removed.
"""

from __future__ import annotations

from typing import Protocol

from magcomp.service.inflight_stage import InflightStage

#: what the calibrate stage calls on a compass's in-flight calibration: the stage itself
InflightSink = InflightStage
#: a stage run elsewhere: none is any more (see the module's doc)
RemoteInflight = InflightStage


class InflightProcess(Protocol):
    """Where stages ran elsewhere: nothing implements it any more (see the module's doc)."""

    def stage(
        self, idx: int, stage: InflightStage, replacing: InflightStage | None = None
    ) -> InflightStage: ...


__all__ = ["InflightProcess", "InflightSink", "RemoteInflight"]
