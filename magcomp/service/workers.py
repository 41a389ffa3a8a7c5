"""The pipeline's background work, owned by whoever runs it (the daemon, a replay) and shut down with it.

Two jobs leave the sample loop: the refined calibration fit (tens to hundreds of ms, adopted a fixed number
of samples later whichever way it ran, so the numbers do not depend on the executor) and the state writes
(fsyncs, kept in submission order by a single thread). :meth:`Workers.threads` gives each one thread;
:meth:`Workers.inline` runs both in the caller (tests, short tools: no threads to shut down).
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from dataclasses import dataclass
from types import TracebackType
from typing import ParamSpec, TypeVar

P = ParamSpec("P")
T = TypeVar("T")


class InlineExecutor(Executor):
    """Runs each job at once in the calling thread; returns its finished future."""

    def submit(self, fn: Callable[P, T], /, *args: P.args, **kwargs: P.kwargs) -> Future[T]:
        fut: Future[T] = Future()
        try:
            fut.set_result(fn(*args, **kwargs))
        except Exception as exc:  # handed to whoever asks for the result, as a thread pool does
            fut.set_exception(exc)
        return fut


@dataclass(frozen=True)
class Workers:
    """``fits``: refined calibration fits; ``state``: state writes (one thread: in order)."""

    fits: Executor
    state: Executor

    @classmethod
    def threads(cls) -> Workers:
        return cls(
            fits=ThreadPoolExecutor(max_workers=1, thread_name_prefix="magcomp-calibration"),
            state=ThreadPoolExecutor(max_workers=1, thread_name_prefix="magcomp-state"),
        )

    @classmethod
    def inline(cls) -> Workers:
        return cls(fits=InlineExecutor(), state=InlineExecutor())

    def shutdown(self) -> None:
        """Wait for the jobs submitted so far, then stop the threads."""
        self.fits.shutdown(wait=True)
        self.state.shutdown(wait=True)

    def __enter__(self) -> Workers:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.shutdown()
