"""The first pass's observers of eq. (20) stepped a block at a time, in this process.

In the learn-only first pass of a replay (:class:`~magcomp.service.pipeline.Pipeline` with ``learn_only``) the
observer is a sink: every step's input (body rate, calibrated field, throttle at the sample's own time, dt)
is decided by the pipeline (service/theta.py: queue, throttle interpolation, resets), and nothing reads
theta-hat back before a state is saved or the pass ends. So its calls (``step``, ``reset_filters``) are
queued, each with its own inputs, and run in order BLOCK at a time: the same calls on the same estimators in
the same order, so the same numbers bit for bit, in a tight loop that keeps the observer's code and data in
the caches instead of interleaving it with the rest of the pipeline per sample (measured: docs/benchmarks.md,
"One process"). Whoever reads an estimator
(:meth:`DeferredTheta.sync`: a state save, the pass's end) first runs every queued call.

Not in the paper: a way of running eq. (20), not a change of it.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from magcomp.adapters.config import Config
from magcomp.service.estimators import ThetaEstimator, ThetaStepInfo

F64 = NDArray[np.float64]

#: queued observer calls run at once (the forked layer's pipe block was 512 steps)
BLOCK = 512


class RemoteTheta(Protocol):
    """An observer whose calls run later (service/theta.py's ``remote``): ``local`` is the estimator as of
    the last :meth:`sync`."""

    local: ThetaEstimator
    last_info: ThetaStepInfo | None

    def step(self, omega_b_rad_s: Sequence[float], field_b_mgauss: Sequence[float], throttle_01: float,
             dt_s: float) -> None: ...  # fmt: skip

    def reset_filters(self) -> None: ...

    def sync(self) -> None: ...


class ObserverProcess(Protocol):
    """Makes each compass's :class:`RemoteTheta` (service/compass.py)."""

    def estimator(self, idx: int, cfg: Config, theta0_mgauss: F64 | None) -> RemoteTheta: ...


#: one queued call: the observer and its step's inputs (None: a filter reset)
_Call = tuple["DeferredTheta", tuple[Sequence[float], Sequence[float], float, float] | None]


class BlockObservers:
    """Every compass's observer of one pass, their calls queued together and run BLOCK at a time."""

    def __init__(self, block: int = BLOCK) -> None:
        self._calls: list[_Call] = []
        self._block = block

    def estimator(self, idx: int, cfg: Config, theta0_mgauss: F64 | None) -> DeferredTheta:
        """Compass ``idx``'s observer, ``ThetaEstimator(cfg, theta0_mgauss)`` as the inline one."""
        return DeferredTheta(self, ThetaEstimator(cfg, theta0_mgauss))

    def put(self, call: _Call) -> None:
        calls = self._calls
        calls.append(call)
        if len(calls) >= self._block:
            self.run()

    def run(self) -> None:
        """Every queued call, in order (taken off the queue first: a ^C inside never runs one twice)."""
        calls, self._calls = self._calls, []
        for obs, args in calls:
            est = obs.local
            if args is None:
                est.reset_filters()
            else:
                obs.last_info = est.step(*args)


class DeferredTheta:
    """A :class:`~magcomp.service.estimators.ThetaEstimator` whose calls :class:`BlockObservers` runs
    later."""

    __slots__ = ("_owner", "last_info", "local")

    def __init__(self, owner: BlockObservers, local: ThetaEstimator) -> None:
        self._owner = owner
        self.local = local
        self.last_info: ThetaStepInfo | None = None

    def step(self, omega_b_rad_s: Sequence[float], field_b_mgauss: Sequence[float], throttle_01: float,
             dt_s: float) -> None:  # fmt: skip
        """Queued (the inputs are the pipeline's tuples of floats, never changed later); the step's info is
        :attr:`last_info` after :meth:`sync`."""
        self._owner.put((self, (omega_b_rad_s, field_b_mgauss, throttle_01, dt_s)))

    def reset_filters(self) -> None:
        self._owner.put((self, None))

    def sync(self) -> None:
        """Run every call queued so far (of every compass: they are independent)."""
        self._owner.run()


__all__ = ["BLOCK", "BlockObservers", "DeferredTheta", "ObserverProcess", "RemoteTheta"]
