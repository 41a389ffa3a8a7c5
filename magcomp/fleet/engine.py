"""Running the fleet: which logs to analyse (content hash vs. the dataset), then the analyses on Dask (a local
cluster, or an existing one by its scheduler's address), each result written as its own part as it arrives.

The client (this process) hashes the logs, submits one task per log and writes the parts; the workers only
read logs and return rows, so they need to see the logs under the same paths (one machine, or a shared file
system) but not the output folder.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from magcomp import __version__
from magcomp.errors import InputError
from magcomp.fleet import store
from magcomp.fleet.analyse import LogTask, analyse_log, content_hash
from magcomp.fleet.discover import VehicleMap

#: the analyses a worker may lose (crash, memory limit) before its log is a failure row
ALLOWED_FAILURES = 1

#: Dask settings of a local cluster's workers. Dask's nanny starts each worker with
#: MALLOC_TRIM_THRESHOLD_=65536 (so that freed memory goes back to the OS); setting it also switches off
#: glibc's adaptive mmap threshold, so every array over 128 KiB is a fresh mmap whose pages are faulted in
#: again, and diagnose's fits allocate many such temporaries. Measured (six 10-min logs of
#: benchmarks/fleet.py, 1 worker): diagnose 3.45 -> 2.08 s of CPU per log and the whole log 11.3 -> 9.5 s
#: without it, the worker's peak RSS after the sixth log 250 -> 244 MB. So the workers keep glibc's
#: default, as the CLI has (None unsets Dask's default; a value the environment sets still passes through).
#: A remote cluster's workers are set up by whoever started them.
LOCAL_WORKER_CONFIG: dict[str, Any] = {"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}
#: that variable as this process had it before any cluster (a nanny writes Dask's value into its parent's
#: environment and leaves it there, where the next cluster's workers would inherit it)
_MALLOC_TRIM_OWN = os.environ.get("MALLOC_TRIM_THRESHOLD_")


@dataclass
class Plan:
    """The logs found, and which of them to analyse now."""

    tasks: list[LogTask]
    found: int
    skipped: int
    duplicates: int
    outdated_kept: int


@dataclass
class RunStats:
    """What a run did, for its closing line and ``benchmarks/fleet.py``."""

    #: logs analysed in this run (skipped ones not counted), and of them those with a row and those failed
    analysed: int = 0
    ok: int = 0
    failed: int = 0
    #: rows written (one per compass, or one for a failed log)
    rows: int = 0
    #: CPU of the logs' analyses summed over the workers, and the run's wall time (s)
    cpu_s: float = 0.0
    wall_s: float = 0.0
    #: workers the analyses ran on (1: in this process)
    workers: int = 0
    #: the largest resident set a worker reached, per worker address (MB)
    peak_rss_mb: dict[str, float] = field(default_factory=dict)


def plan(
    logs: list[Path], out: Path, rerun: str = "none", config: str | None = None, diagnose: bool = True
) -> Plan:
    """Hash every log; skip those with a part already (``rerun``: ``none``; ``outdated``: also analyse those
    a different magcomp version did; ``all``: analyse everything again). ``diagnose``: the rows carry
    ``magcomp diagnose``'s results too."""
    done = store.done(out)
    hashes = _HashCache(out)
    tasks: list[LogTask] = []
    seen: set[str] = set()
    skipped = duplicates = outdated = 0
    for p in logs:
        try:
            sha, size = hashes.get(p)
        except OSError as exc:
            raise InputError(f"{p}: unreadable ({exc.strerror or type(exc).__name__})") from None
        if sha in seen:
            duplicates += 1
            continue
        seen.add(sha)
        version = done.get(sha)
        if version is not None and rerun != "all":
            if rerun == "outdated" and version != __version__:
                pass
            else:
                skipped += 1
                if version != __version__:
                    outdated += 1
                continue
        tasks.append(LogTask(path=str(p), sha256=sha, size_bytes=size, config=config, diagnose=diagnose))
    hashes.save()
    return Plan(tasks, len(logs), skipped, duplicates, outdated)


class _HashCache:
    """The content hash of each file seen before, by (absolute path, size, modification time in ns): a
    re-run does not read every log again to find it done. ``OUT/hashes.json``; any doubt: hash again."""

    NAME = "hashes.json"

    def __init__(self, out: Path) -> None:
        self.path = out / self.NAME
        self.known: dict[str, list[Any]] = {}
        self.changed = False
        try:
            doc = json.loads(self.path.read_text(encoding="utf-8"))
            if isinstance(doc, dict):
                self.known = {k: v for k, v in doc.items() if isinstance(v, list) and len(v) == 3}
        except (OSError, ValueError):
            pass

    def get(self, p: Path) -> tuple[str, int]:
        key = str(p.resolve())
        st = p.stat()
        hit = self.known.get(key)
        if hit is not None and hit[0] == st.st_size and hit[1] == st.st_mtime_ns and isinstance(hit[2], str):
            return hit[2], st.st_size
        sha = content_hash(p)
        self.known[key] = [st.st_size, st.st_mtime_ns, sha]
        self.changed = True
        return sha, st.st_size

    def save(self) -> None:
        if not self.changed:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(f".{self.NAME}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(self.known), encoding="utf-8")
        os.replace(tmp, self.path)


def _apply_map(rows: list[dict[str, Any]], vmap: VehicleMap) -> list[dict[str, Any]]:
    for r in rows:
        detected = str(r.get("vehicle_detected") or "")
        name = vmap.vehicle(str(r.get("path", "")), str(r.get("sha256", "")), detected)
        if name is not None:
            r["vehicle"] = name
            r["identity_source"] = "mapping file"
    return rows


def _failure(task: LogTask, why: str) -> list[dict[str, Any]]:
    return [
        {
            "sha256": task.sha256,
            "path": task.path,
            "file_name": Path(task.path).name,
            "size_bytes": task.size_bytes,
            "status": "failed",
            "error": why,
            "magcomp_version": __version__,
        }
    ]


class _Progress:
    """A bar with the counts and an ETA on a terminal; otherwise a line now and then (and none in CI)."""

    def __init__(self, total: int, enabled: bool) -> None:
        from magcomp.service.console import progress_enabled, quiet_tqdm

        self.total = total
        self.bar: Any = None
        self.lines = enabled and not progress_enabled() and not os.environ.get("CI")
        self.t0 = time.monotonic()
        self.last_line = self.t0
        if enabled and progress_enabled():
            self.bar = quiet_tqdm()(
                total=total, desc="fleet", unit="log", file=sys.stderr, dynamic_ncols=True, mininterval=0.5
            )

    def update(self, st: RunStats) -> None:
        if self.bar is not None:
            self.bar.set_postfix_str(f"ok {st.ok}, failed {st.failed}", refresh=False)
            self.bar.update(1)
        elif self.lines:
            now = time.monotonic()
            if now - self.last_line >= 30.0 or st.analysed == self.total:
                self.last_line = now
                rate = st.analysed / max(now - self.t0, 1e-9)
                eta = (self.total - st.analysed) / rate if rate > 0 else float("nan")
                print(
                    f"fleet: {st.analysed}/{self.total} logs (ok {st.ok}, failed {st.failed}), "
                    f"ETA {eta:.0f} s",
                    file=sys.stderr,
                    flush=True,
                )

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def run(
    tasks: list[LogTask],
    out: Path,
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    memory_limit: str = "auto",
    vmap: VehicleMap | None = None,
    progress: bool = True,
    on_done: Callable[[LogTask, list[dict[str, Any]]], None] | None = None,
) -> RunStats:
    """Analyse ``tasks``; each log's rows become its part in ``out`` as soon as they arrive.

    ``scheduler``: the address of an existing Dask scheduler (``tcp://HOST:8786``); None: a local cluster of
    ``workers`` processes (default: one per core), one thread each, ``memory_limit`` each; ``workers=0``:
    in this process, one log after another (no Dask).
    """
    vmap = vmap or VehicleMap()
    store.logs_dir(out).mkdir(parents=True, exist_ok=True)
    with _exclusive(out):
        return _run(tasks, out, scheduler, workers, memory_limit, vmap, progress, on_done)


@contextlib.contextmanager
def _exclusive(out: Path) -> Iterator[None]:
    """One run at a time per output folder (a second one would delete the first's temporary files); the
    lock goes with the process, kill -9 included."""
    import fcntl

    with open(out / ".lock", "a+b") as f:
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise InputError(f"{out}: another magcomp fleet is writing there") from None
        try:
            yield
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)


def _run(
    tasks: list[LogTask],
    out: Path,
    scheduler: str | None,
    workers: int | None,
    memory_limit: str,
    vmap: VehicleMap,
    progress: bool,
    on_done: Callable[[LogTask, list[dict[str, Any]]], None] | None,
) -> RunStats:
    store.clean_leftovers(out)
    st = RunStats()
    t0 = time.perf_counter()
    bar = _Progress(len(tasks), progress)
    try:
        results = (
            _inline(tasks, st)
            if workers == 0 and scheduler is None
            else _dask(tasks, st, scheduler, workers, memory_limit)
        )
        for task, rows in results:
            rows = _apply_map(rows, vmap)
            # the version that analysed it (a remote worker's may differ from this process's)
            version = str(rows[0].get("magcomp_version") or __version__) if rows else __version__
            store.write_part(out, task.sha256, rows, version)
            st.analysed += 1
            st.rows += len(rows)
            if rows and rows[0].get("status") == "ok":
                st.ok += 1
            else:
                st.failed += 1
            st.cpu_s += float(rows[0].get("cpu_s") or 0.0) if rows else 0.0
            host = str(rows[0].get("host") or "?") if rows else "?"
            rss = float(rows[0].get("peak_rss_mb") or 0.0) if rows else 0.0
            st.peak_rss_mb[host] = max(st.peak_rss_mb.get(host, 0.0), rss)
            bar.update(st)
            if on_done is not None:
                on_done(task, rows)
    finally:
        bar.close()
    st.wall_s = time.perf_counter() - t0
    return st


def _inline(tasks: list[LogTask], st: RunStats) -> Iterator[tuple[LogTask, list[dict[str, Any]]]]:
    st.workers = 1
    for t in tasks:
        yield t, analyse_log(t)


def local_cluster(workers: int, memory_limit: str) -> Any:
    """A local Dask cluster of ``workers`` processes, one thread each, ``memory_limit`` each, its workers
    started with :data:`LOCAL_WORKER_CONFIG`."""
    import dask
    from distributed import LocalCluster

    if _MALLOC_TRIM_OWN is None:  # not the user's: an earlier cluster's nanny left Dask's value here
        os.environ.pop("MALLOC_TRIM_THRESHOLD_", None)
    with dask.config.set(LOCAL_WORKER_CONFIG):  # read by each nanny as the cluster starts it
        return LocalCluster(
            n_workers=workers,
            threads_per_worker=1,
            processes=True,
            memory_limit=memory_limit,
            dashboard_address=None,
            silence_logs=logging.ERROR,
        )


def _dask(
    tasks: list[LogTask], st: RunStats, scheduler: str | None, workers: int | None, memory_limit: str
) -> Iterator[tuple[LogTask, list[dict[str, Any]]]]:
    import dask
    from distributed import Client, as_completed

    cluster: Any = None
    with dask.config.set({"distributed.scheduler.allowed-failures": ALLOWED_FAILURES}):
        if scheduler is None:
            n = workers if workers is not None else len(os.sched_getaffinity(0))
            cluster = local_cluster(n, memory_limit)
            client = Client(cluster)
        else:
            try:  # waits up to Dask's distributed.comm.timeouts.connect (30 s unless configured)
                client = Client(scheduler)
            except (OSError, TimeoutError, ValueError) as exc:
                raise InputError(f"--scheduler {scheduler}: cannot connect ({type(exc).__name__})") from None
        try:
            st.workers = len(client.scheduler_info().get("workers", {}))
            by_key = {}
            futures = []
            for i, t in enumerate(tasks):
                fut = client.submit(analyse_log, t, key=f"magcomp-fleet-{i}-{t.sha256[:16]}", pure=False)
                by_key[fut.key] = t
                futures.append(fut)
            for fut in as_completed(futures):
                task = by_key[fut.key]
                try:
                    rows = fut.result()
                except Exception as exc:  # the worker died under it (memory limit, crash)
                    why = str(exc).splitlines()[0] if str(exc) else ""
                    rows = _failure(
                        task, f"the worker analysing it was lost ({type(exc).__name__}: {why})"[:300]
                    )
                fut.release()
                yield task, rows
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
