"""Stage 7, persist: each compass's calibration and theta saved on message time (and at the end).

A compass whose state changed is saved at most every ``[state] save_interval_s`` of message time, on
each new calibration, and when the pipeline closes. The writes (two fsyncs each, tens of ms on some
disks) run on the ``state`` executor the pipeline was given: one thread keeps them in order.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from concurrent.futures import Executor, Future
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

from magcomp.adapters.state_store import CompassState

if TYPE_CHECKING:
    from magcomp.service.compass import CompassCorrector

log = logging.getLogger("magcomp.pipeline")


class StateSink(Protocol):
    """Where states go (:class:`~magcomp.adapters.state_store.StateStore`, or memory for a first pass)."""

    warnings: list[str]

    def save(self, state: CompassState) -> object: ...

    def load(self, system_id: int, mag_index: int, uid: str | None = None) -> CompassState | None: ...


@dataclass(eq=False)
class PersistStage:
    """Saves compass states to ``store`` (None: only the bookkeeping) through the ``writer`` executor, a
    changed compass at most every ``interval_s`` of message time, each state keyed by ``vehicle()`` (system
    id, unique id); a failed write becomes one warning in ``warnings``."""

    store: StateSink | None
    writer: Executor
    interval_s: float
    vehicle: Callable[[], tuple[int, str | None]]
    warnings: list[str]
    _pending: list[Future[None]] = field(default_factory=list, init=False)

    def run(self, c: CompassCorrector, t_s: float) -> None:
        """Save ``c`` if it changed and its last save is ``interval_s`` of message time old."""
        if c.dirty and (c.last_saved_t is None or t_s - c.last_saved_t >= self.interval_s):
            self.save(c, t_s)

    def save(self, c: CompassCorrector, t_s: float, final: bool = False) -> None:
        """Save ``c``'s state now (the write itself in the background); ``final``: the pipeline closes."""
        c.last_saved_t = t_s
        c.dirty = False
        if self.store is None:
            return
        sysid, uid = self.vehicle()
        state = c.to_state(sysid, t_s, vehicle_uid=uid)
        self._pending = [f for f in self._pending if not f.done()]
        self._pending.append(self.writer.submit(self._write, state))

    def _write(self, state: CompassState) -> None:
        assert self.store is not None
        try:
            self.store.save(state)
        except OSError as exc:
            msg = f"cannot write state for compass {state.mag_index}: {exc.strerror}"
            self.warnings.append(msg)
            log.warning(msg)

    def wait(self) -> None:
        """Wait for the writes submitted so far."""
        for f in self._pending:
            f.result()
        self._pending = []
