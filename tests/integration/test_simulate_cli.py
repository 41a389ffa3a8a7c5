"""`magcomp simulate` on the command line: files written, bad arguments as one-line errors."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from magcomp.cli import main


def test_simulate_writes_tlog_and_truth(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run.tlog"
    rc = main(
        [
            "simulate",
            "--scenario",
            "flight_multirotor",
            "--duration",
            "8",
            "--seed",
            "4",
            "--effect",
            "per_motor=0.5",
            "--effect",
            "current_lag=0.2",
            "--compasses",
            "3",
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    assert out.stat().st_size > 10_000
    truth = json.loads((tmp_path / "run.truth.json").read_text())
    assert truth["vehicle"] == "multirotor" and truth["scenario"] == "flight"
    assert truth["effects"] == {"per_motor": 0.5, "current_lag": 0.2}
    assert len(truth["compasses"]) == 3
    assert (tmp_path / "run.truth.npz").exists()
    assert "wrote" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("argv", "fragment"),
    [
        (["--scenario", "loop"], "unknown scenario"),
        (["--effect", "warp=1"], "unknown effect"),
        (["--effect", "time_skew=5"], "time_skew"),
        (["--effect", "per_motor=1"], "multirotor"),
        (["--year", "2031"], "2031"),
        (["--compasses", "0"], "n_compasses"),
    ],
)
def test_bad_arguments_give_one_line_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], fragment: str
) -> None:
    rc = main(["simulate", *argv, "--duration", "2", "--out", str(tmp_path / "x.tlog")])
    err = capsys.readouterr().err
    assert rc != 0
    assert fragment in err
    assert err.count("\n") == 1 and err.startswith("magcomp simulate: error:")


def test_bad_link_url_is_an_error(capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["simulate", "--scenario", "step", "--duration", "2", "--link", "serial:/dev/null"])
    assert rc != 0
    assert "link" in capsys.readouterr().err
