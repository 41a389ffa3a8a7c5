"""The fleet's Parquet dataset (magcomp/fleet/store.py): a part written before a column existed still
loads, the new column null."""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from magcomp.fleet.store import SCHEMA, logs_dir, read_rows, write_part


def test_a_dataset_without_compass_sensor_still_loads(tmp_path: Path) -> None:
    old_schema = pa.schema([f for f in SCHEMA if f.name != "compass_sensor"])
    assert len(old_schema) == len(SCHEMA) - 1  # the column exists now
    old = pa.Table.from_pylist([{"sha256": "a" * 64, "status": "ok", "compass": 0}], schema=old_schema)
    logs_dir(tmp_path).mkdir(parents=True)
    pq.write_table(old, logs_dir(tmp_path) / f"{'a' * 64}.parquet")
    write_part(
        tmp_path,
        "b" * 64,
        [{"sha256": "b" * 64, "status": "ok", "compass": 1, "compass_sensor": "131594"}],
        "x",
    )
    t = read_rows(tmp_path).to_pylist()
    got = {r["sha256"][0]: r["compass_sensor"] for r in t}
    assert got == {"a": None, "b": "131594"}, got
