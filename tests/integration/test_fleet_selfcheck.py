"""The fleet's rows carry the self-check of the real-flights issue: on the measured log171 the corrected
compasses' headings agree better with the gyro than the autopilot's own, and the row says by how much."""

from __future__ import annotations

from pathlib import Path

import pytest

from magcomp.cli import main
from magcomp.fleet import store

MEASURED = Path(__file__).parents[2].parent / "shared" / "data" / "measured"
LOG171 = MEASURED / "dronekit_log171_copter33_quad.bin"

pytestmark = pytest.mark.needs_shared


def test_fleet_rows_carry_the_self_check(tmp_path: Path) -> None:
    if not LOG171.exists():
        pytest.skip(f"{LOG171.name} not found (../shared/data/measured is absent in this clone)")
    out = tmp_path / "out"
    assert main(["fleet", str(LOG171), "--out", str(out), "--workers", "0"]) == 0
    rows = {r["compass"]: r for r in store.read_rows(out).to_pylist()}
    for idx in (1, 2):
        r = rows[idx]
        assert r["applied"]
        assert r["selfcheck_corrected_gyro_deg"] < 0.5 * r["selfcheck_autopilot_gyro_deg"]
        assert r["selfcheck_gain_sigma"] > 2.0
