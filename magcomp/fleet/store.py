"""The fleet's results: one Parquet dataset, ``OUT/logs/``, one part file per log (``<sha256>.parquet``).

A part is written whole to a hidden temporary file, flushed to disk and renamed into place: a run killed at
any moment (kill -9 too) leaves every finished log's part whole and no partial one among them (readers skip
names starting with ``.``, and the next run removes the leftovers). A log is done when its part exists;
the magcomp version that wrote it is kept in the part's metadata and in the ``magcomp_version`` column.

Read it with pyarrow (``pyarrow.dataset.dataset("OUT/logs")``), pandas (``pd.read_parquet("OUT/logs")``),
polars (``pl.read_parquet("OUT/logs/*.parquet")``) or DuckDB (``SELECT * FROM 'OUT/logs/*.parquet'``).
"""

from __future__ import annotations

import contextlib
import math
import os
from collections.abc import Iterable
from datetime import datetime
from pathlib import Path
from typing import Any

# pyarrow's jemalloc starts a background thread at import unless told not to; a process with that native
# thread should not fork (the replay no longer does, a library user's code may). Set before pyarrow's first
# import (no effect if something imported it already).
os.environ.setdefault("JE_ARROW_MALLOC_CONF", "background_thread:false")

import pyarrow as pa
import pyarrow.parquet as pq

LOGS_DIR = "logs"
VERSION_KEY = b"magcomp_version"

_STR = pa.string()
_F64 = pa.float64()
_TS = pa.timestamp("us", tz="UTC")

#: every column of a row, in order; a row lacks none (a failure row has nulls)
SCHEMA = pa.schema(
    [
        ("sha256", _STR),
        ("path", _STR),
        ("file_name", _STR),
        ("size_bytes", pa.int64()),
        ("format", _STR),
        ("status", _STR),
        ("error", _STR),
        ("vehicle", _STR),
        ("vehicle_detected", _STR),
        ("identity_source", _STR),
        ("autopilot", _STR),
        ("firmware", _STR),
        ("board", _STR),
        ("board_uid", _STR),
        ("system_id", pa.int32()),
        ("date_utc", _TS),
        ("date_source", _STR),
        ("duration_s", _F64),
        ("flight_s", _F64),
        ("compass", pa.int32()),
        # the physical sensor in that slot (device id; null: the log does not say; diagnosis.identity); a
        # dataset written before this column reads it as null (pyarrow fills a missing column)
        ("compass_sensor", _STR),
        ("applied", pa.bool_()),
        ("why", _STR),
        ("form", _STR),
        ("theta_x_mgauss", _F64),
        ("theta_y_mgauss", _F64),
        ("theta_z_mgauss", _F64),
        ("theta_sigma_x_mgauss", _F64),
        ("theta_sigma_y_mgauss", _F64),
        ("theta_sigma_z_mgauss", _F64),
        ("theta_norm_mgauss", _F64),
        ("theta_norm_sigma_mgauss", _F64),
        ("theta_converged", pa.bool_()),
        ("heading_sigma_deg", _F64),
        ("selfcheck_autopilot_gyro_deg", _F64),
        ("selfcheck_corrected_gyro_deg", _F64),
        ("selfcheck_autopilot_att_deg", _F64),
        ("selfcheck_corrected_att_deg", _F64),
        ("selfcheck_gain_sigma", _F64),
        ("calibration_source", _STR),
        ("calibration_residual_mgauss", _F64),
        ("offset_x_mgauss", _F64),
        ("offset_y_mgauss", _F64),
        ("offset_z_mgauss", _F64),
        ("throttle_min", _F64),
        ("throttle_max", _F64),
        ("throttle2_std", _F64),
        ("yaw_span_deg", _F64),
        ("earth_field_mgauss", _F64),
        ("earth_field_source", _STR),
        ("interference_pct", _F64),
        ("interference_pct_sigma", _F64),
        ("interference_flown_pct", _F64),
        ("onboard_motor_compensation", pa.bool_()),
        ("warnings", _STR),
        ("diagnose_status", _STR),
        ("diagnose_error", _STR),
        ("diagnose_observable", pa.bool_()),
        ("diagnose_why", _STR),
        ("diagnose_theta_from", _STR),
        ("diagnose_theta_x_mgauss", _F64),
        ("diagnose_theta_y_mgauss", _F64),
        ("diagnose_theta_z_mgauss", _F64),
        ("diagnose_theta_ci95_x_mgauss", _F64),
        ("diagnose_theta_ci95_y_mgauss", _F64),
        ("diagnose_theta_ci95_z_mgauss", _F64),
        # the joint 95 % box (a dataset written before these columns reads them as null)
        ("diagnose_theta_ci95_joint_x_mgauss", _F64),
        ("diagnose_theta_ci95_joint_y_mgauss", _F64),
        ("diagnose_theta_ci95_joint_z_mgauss", _F64),
        ("diagnose_theta_identifiable", pa.bool_()),
        ("diagnose_findings", _STR),
        ("diagnose_findings_json", _STR),
        ("diagnose_params_json", _STR),
        ("diagnose_cpu_s", _F64),
        ("replay_cpu_s", _F64),
        ("magcomp_version", _STR),
        ("analysed_at", _TS),
        ("host", _STR),
        ("wall_s", _F64),
        ("cpu_s", _F64),
        ("peak_rss_mb", _F64),
    ]
)


def logs_dir(out: Path) -> Path:
    return out / LOGS_DIR


def part_path(out: Path, sha256: str) -> Path:
    return logs_dir(out) / f"{sha256}.parquet"


def _cell(field: pa.Field, value: Any) -> Any:
    if value is None:
        return None
    if pa.types.is_floating(field.type):
        v = float(value)
        return v if math.isfinite(v) else None
    if pa.types.is_integer(field.type):
        return int(value)
    if pa.types.is_boolean(field.type):
        return bool(value)
    if pa.types.is_timestamp(field.type):
        return value if isinstance(value, datetime) else None
    return str(value)


def rows_table(rows: list[dict[str, Any]]) -> pa.Table:
    """The rows as a table of :data:`SCHEMA` (missing keys: null; NaN: null)."""
    columns = {f.name: [_cell(f, r.get(f.name)) for r in rows] for f in SCHEMA}
    return pa.table(columns, schema=SCHEMA)


def write_part(out: Path, sha256: str, rows: list[dict[str, Any]], version: str) -> Path:
    """One log's rows, atomically: a hidden temporary file, fsync, rename."""
    target = part_path(out, sha256)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.parent / f".{sha256}.{os.getpid()}.tmp"
    table = rows_table(rows).replace_schema_metadata({VERSION_KEY: version.encode()})
    try:
        with open(tmp, "wb") as f:
            pq.write_table(table, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    with contextlib.suppress(OSError):  # the rename itself on disk
        dir_fd = os.open(target.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
    return target


def clean_leftovers(out: Path) -> int:
    """Remove the temporary files a killed run left; how many."""
    n = 0
    for d in (logs_dir(out), out):
        if d.is_dir():
            for p in d.glob(".*.tmp"):
                with contextlib.suppress(OSError):
                    p.unlink()
                    n += 1
    return n


def done(out: Path) -> dict[str, str]:
    """sha256 -> the magcomp version that analysed it, for every finished log (unreadable parts: not done)."""
    d = logs_dir(out)
    found: dict[str, str] = {}
    if not d.is_dir():
        return found
    for p in d.glob("*.parquet"):
        try:
            meta = pq.read_schema(p).metadata or {}
        except (OSError, pa.ArrowException):
            continue  # damaged from outside (a part is never half-written by us): analysed again
        found[p.stem] = meta.get(VERSION_KEY, b"").decode(errors="replace")
    return found


def read_rows(out: Path, shas: Iterable[str] | None = None) -> pa.Table:
    """The whole dataset (or the given logs) as one table of :data:`SCHEMA`."""
    d = logs_dir(out)
    paths = sorted(d.glob("*.parquet")) if d.is_dir() else []
    if shas is not None:
        wanted = set(shas)
        paths = [p for p in paths if p.stem in wanted]
    tables = []
    for p in paths:
        try:
            tables.append(pq.read_table(p, schema=SCHEMA))
        except (OSError, pa.ArrowException):
            continue
    if not tables:
        return SCHEMA.empty_table()
    return pa.concat_tables(tables)


def write_table(path: Path, rows: list[dict[str, Any]]) -> None:
    """Plain rows (types inferred; NaN -> null) as one Parquet file, atomically."""
    clean = [
        {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in r.items()}
        for r in rows
    ]
    table = pa.Table.from_pylist(clean) if clean else pa.table({})
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        pq.write_table(table, tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
