"""`magcomp fleet` on a small simulated fleet: two vehicles with different theta, one whose theta changes
at its third flight, a corrupt file; the Parquet rows, the change found at the right flight, incremental
re-runs, a kill -9 halfway, and the same rows on a local Dask cluster and on a separate scheduler."""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq
import pytest

from magcomp.cli import main
from magcomp.fleet import store
from tests.waiting import LineReader, wait_for

THETA_A = (-61.0, 26.0, -1.0)
THETA_B1 = (40.0, -50.0, 20.0)
THETA_B2 = (140.0, -10.0, 80.0)
#: (folder, file, seed, year, theta)
FLIGHTS = [
    ("vehA", "flight01.tlog", 1, "2026.1", THETA_A),
    ("vehA", "flight02.tlog", 2, "2026.2", THETA_A),
    ("vehA", "flight03.tlog", 3, "2026.3", THETA_A),
    ("vehB", "flight01.tlog", 11, "2026.1", THETA_B1),
    ("vehB", "flight02.tlog", 12, "2026.2", THETA_B1),
    ("vehB", "flight03.tlog", 13, "2026.3", THETA_B2),
    ("vehB", "flight04.tlog", 14, "2026.4", THETA_B2),
]
VEHICLES_TOML = '[vehicles]\nalpha = ["*/vehA/*"]\nbravo = ["*/vehB/*"]\n'
#: columns that differ between two analyses of the same log (when, where, how long)
RUN_COLUMNS = {
    "analysed_at", "host", "wall_s", "cpu_s", "diagnose_cpu_s", "replay_cpu_s", "peak_rss_mb", "path",
}  # fmt: skip


def _foreign_threads() -> list[str]:
    """This process's native threads that do not carry its own name (a library's: pyarrow's allocator,
    Dask's IO loop); a BLAS pool's keep the process's name."""
    own = Path("/proc/self/comm").read_text().strip()
    names = [(t / "comm").read_text().strip() for t in Path("/proc/self/task").iterdir()]
    return [n for n in names if n != own]



def _fleet_args(fleet: Path, out: Path) -> list[str]:
    """`magcomp fleet` over the simulated fleet, in process (no workers), with its vehicle map and config."""
    vehicles, config = str(fleet / "vehicles.toml"), str(fleet / "estimator_only.toml")
    return ["fleet", str(fleet), "--out", str(out), "--workers", "0", "--vehicles", vehicles,
            "--config", config]


@pytest.fixture(autouse=True)
def no_threads_left() -> Iterator[None]:
    """No test here leaves a thread in the test process, Python's or a library's native one (pyarrow's
    allocator, Dask's IO loop)."""
    before = {t.ident for t in threading.enumerate()}
    native = sorted(_foreign_threads())
    yield
    left = [t.name for t in threading.enumerate() if t.ident not in before and t.is_alive()]
    assert left == [], f"threads left running: {left}"
    assert sorted(_foreign_threads()) == native, f"native threads: {native} -> {_foreign_threads()}"


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("fleet")
    for folder, name, seed, year, theta in FLIGHTS:
        (root / folder).mkdir(exist_ok=True)
        rc = main(
            [
                "simulate",
                "--scenario",
                "ordinary",
                "--duration",
                "60",
                "--compasses",
                "1",
                "--seed",
                str(seed),
                "--year",
                year,
                "--set",
                "theta_mgauss=" + ",".join(map(str, theta)),
                "--out",
                str(root / folder / name),
            ]
        )
        assert rc == 0
    (root / "vehB" / "broken.tlog").write_bytes(bytes((i * 7919) % 251 for i in range(40_000)))
    (root / "vehicles.toml").write_text(VEHICLES_TOML)
    # the simulator's autopilot pulls its yaw to the compass at 0.5 /s: against it the self-check refuses
    # corrections that are right (tests/configs.py); these tests are about the fleet's rows, not that check
    (root / "estimator_only.toml").write_text("[output]\nself_check = false\n")
    return root


@pytest.fixture(scope="module")
def analysed(fleet: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The whole fleet, in this process, uninterrupted: the reference the other runs are compared with."""
    out = tmp_path_factory.mktemp("out")
    assert main(_fleet_args(fleet, out)) == 0
    return out


def _rows(out: Path) -> list[dict[str, Any]]:
    return sorted(store.read_rows(out).to_pylist(), key=lambda r: (r["path"], r["compass"] or 0))


def _comparable(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{k: v for k, v in r.items() if k not in RUN_COLUMNS} for r in rows]


def test_every_log_is_a_row_and_the_corrupt_one_a_failure(analysed: Path, fleet: Path) -> None:
    rows = _rows(analysed)
    assert len({r["sha256"] for r in rows}) == len(FLIGHTS) + 1
    broken = [r for r in rows if r["file_name"] == "broken.tlog"]
    assert len(broken) == 1 and broken[0]["status"] == "failed"
    assert broken[0]["error"] and "\n" not in broken[0]["error"] and "Traceback" not in broken[0]["error"]
    ok = [r for r in rows if r["status"] == "ok"]
    assert len(ok) == len(FLIGHTS) and all(r["applied"] for r in ok)
    assert {r["vehicle"] for r in rows} == {"alpha", "bravo"}
    for r in ok:
        assert r["autopilot"] == "ArduPilot" and r["format"] == "tlog"
        assert r["date_source"] == "gps-system-time" and r["date_utc"].year == 2026
        assert 55.0 < r["duration_s"] <= 60.5
        assert 0.0 <= r["throttle_min"] < r["throttle_max"] <= 1.0 and r["yaw_span_deg"] > 90.0
        norm = math.hypot(r["theta_x_mgauss"], r["theta_y_mgauss"], r["theta_z_mgauss"])
        assert r["interference_pct"] == pytest.approx(100.0 * norm / r["earth_field_mgauss"])
        assert r["theta_sigma_x_mgauss"] > 0 and r["heading_sigma_deg"] > 0
    # the two vehicles' theta told apart: each flight's theta nearer its own truth than the other's
    for r in ok:
        truth = (
            THETA_A if r["vehicle"] == "alpha" else (THETA_B1 if r["file_name"] < "flight03" else THETA_B2)
        )
        est = (r["theta_x_mgauss"], r["theta_y_mgauss"], r["theta_z_mgauss"])
        assert math.dist(est, truth) < 30.0, (r["file_name"], r["vehicle"], est)
    # the dataset reads as one table with pyarrow's dataset reader too
    import pyarrow.dataset as ds

    assert ds.dataset(analysed / "logs", format="parquet").to_table().num_rows == len(rows)


def test_rows_carry_diagnose_and_vehicles_its_parameter_files(
    analysed: Path, fleet: Path, tmp_path: Path
) -> None:
    """Each ok row holds what `magcomp diagnose LOG` finds for that compass (theta with its interval, the
    findings), and each vehicle the parameter file diagnose writes for its latest flight with parameters."""
    rows = _rows(analysed)
    ok = [r for r in rows if r["status"] == "ok"]
    assert all(r["diagnose_status"] == "ok" for r in ok)
    # the log's CPU split: its diagnosis and its replay are each a part of it
    for r in ok:
        assert r["diagnose_cpu_s"] > 0.0 and r["replay_cpu_s"] > 0.0
        assert r["diagnose_cpu_s"] + r["replay_cpu_s"] <= r["cpu_s"] + 1e-6
    # the fleet's row equals the CLI's diagnosis of the same log
    r = next(r for r in ok if r["vehicle"] == "bravo" and r["file_name"] == "flight04.tlog")
    j, par = tmp_path / "d.json", tmp_path / "d.param"
    assert main(["diagnose", r["path"], "--json", str(j), "--params-out", str(par)]) == 0
    c = json.loads(j.read_text())["compasses"][0]
    assert c["observable"] and r["diagnose_theta_from"] == "free fit"
    got = [r[f"diagnose_theta_{a}_mgauss"] for a in "xyz"]
    hw = [r[f"diagnose_theta_ci95_{a}_mgauss"] for a in "xyz"]
    assert got == pytest.approx(c["theta"]) and hw == pytest.approx(c["theta_ci95_halfwidth"])
    assert math.dist(got, THETA_B2) < 30.0
    assert json.loads(r["diagnose_findings_json"]) == c["findings"]
    assert r["diagnose_findings"] == "no finding" or c["findings"]
    # bravo's latest flight gives parameters: the fleet's file holds diagnose's values
    whole = json.loads((analysed / "vehicles.json").read_text())
    assert whole["theta_from"] == "diagnose"  # the vehicles follow diagnose's theta where the rows have it
    doc = {v["vehicle"]: v for v in whole["vehicles"]}
    params = doc["bravo"]["params"]
    assert params is not None and params["flight"] == "flight04.tlog" and params["autopilot"] == "ArduPilot"
    from magcomp.adapters.param_files import read_param_file

    mine = read_param_file(analysed / "params" / "bravo.param")
    assert mine == pytest.approx(read_param_file(par))
    assert read_param_file(analysed / "params" / "bravo.params") == pytest.approx(mine)


def test_no_diagnose_leaves_the_diagnose_columns_empty(fleet: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    one = fleet / "vehA" / "flight01.tlog"
    args = ["fleet", str(one), "--out", str(out), "--workers", "0", "--no-diagnose"]
    assert main([*args, "--config", str(fleet / "estimator_only.toml")]) == 0
    rows = _rows(out)
    assert len(rows) == 1 and rows[0]["status"] == "ok" and rows[0]["diagnose_status"] is None
    assert 55.0 < rows[0]["duration_s"] <= 60.5 and rows[0]["throttle_max"] > rows[0]["throttle_min"]
    assert json.loads((out / "vehicles.json").read_text())["theta_from"] == "replay"


def test_the_change_is_found_at_its_flight_and_only_there(analysed: Path) -> None:
    doc = json.loads((analysed / "vehicles.json").read_text())
    by_name = {v["vehicle"]: v for v in doc["vehicles"]}
    assert [v["vehicle"] for v in doc["vehicles"]] == ["bravo", "alpha"]  # the changed one first
    bravo = by_name["bravo"]["compasses"][0]
    assert [(c["file_name"], c["confirmed"], c["at_flight"]) for c in bravo["changes"]] == [
        ("flight03.tlog", True, 2)
    ]
    assert math.dist(bravo["changes"][0]["before_mgauss"], THETA_B1) < 25.0
    assert math.dist(bravo["changes"][0]["after_mgauss"], THETA_B2) < 25.0
    assert by_name["alpha"]["compasses"][0]["changes"] == []
    assert by_name["bravo"]["failed"] == 1 and by_name["alpha"]["failed"] == 0
    flat = pq.read_table(analysed / "vehicles.parquet").to_pylist()
    assert [(r["rank"], r["vehicle"], r["changes_confirmed"], r["last_change_file"]) for r in flat] == [
        (1, "bravo", 1, "flight03.tlog"),
        (2, "alpha", 0, None),
    ]


def test_a_rerun_skips_what_is_done_and_analyses_only_the_new(
    fleet: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    logs = tmp_path / "logs"
    logs.mkdir()
    for name in ("flight01.tlog", "flight02.tlog"):
        shutil.copy(fleet / "vehA" / name, logs / name)
    out = tmp_path / "out"
    assert main(["fleet", str(logs), "--out", str(out), "--workers", "0"]) == 0
    first = {p.name: p.stat().st_mtime_ns for p in (out / "logs").glob("*.parquet")}
    assert len(first) == 2
    capsys.readouterr()
    shutil.copy(fleet / "vehA" / "flight03.tlog", logs / "flight03.tlog")
    shutil.copy(logs / "flight01.tlog", logs / "same-bytes-other-name.tlog")  # the content is the key
    assert main(["fleet", str(logs), "--out", str(out), "--workers", "0"]) == 0
    text = capsys.readouterr().out
    assert "4 logs found, 2 done before (skipped), 1 duplicate file(s); analysing 1" in text
    second = {p.name: p.stat().st_mtime_ns for p in (out / "logs").glob("*.parquet")}
    assert len(second) == 3 and all(second[k] == v for k, v in first.items())
    # another magcomp version's part: kept unless asked
    sha = next(iter(first)).removesuffix(".parquet")
    old = [{**r, "magcomp_version": "0.0.1"} for r in store.read_rows(out, [sha]).to_pylist()]
    store.write_part(out, sha, old, "0.0.1")
    assert main(["fleet", str(logs), "--out", str(out), "--workers", "0"]) == 0
    assert "analysing 0" in capsys.readouterr().out
    assert main(["fleet", str(logs), "--out", str(out), "--workers", "0", "--rerun-outdated"]) == 0
    assert "analysing 1" in capsys.readouterr().out
    assert store.done(out)[sha] != "0.0.1"
    assert main(["fleet", str(logs), "--out", str(out), "--workers", "0", "--rerun-all"]) == 0
    assert "analysing 3" in capsys.readouterr().out
    # a log changed in place (same name): new content, a new key, analysed (the hash cache is not fooled)
    assert (out / "hashes.json").exists()
    with open(logs / "flight02.tlog", "ab") as f:
        f.write(bytes(16))
    assert main(["fleet", str(logs), "--out", str(out), "--workers", "0"]) == 0
    assert (
        "4 logs found, 2 done before (skipped), 1 duplicate file(s); analysing 1" in capsys.readouterr().out
    )


def test_kill_9_halfway_then_resume_gives_the_uninterrupted_table(
    fleet: Path, analysed: Path, tmp_path: Path
) -> None:
    out = tmp_path / "out"
    argv = [
        sys.executable,
        "-m",
        "magcomp",
        *_fleet_args(fleet, out),
    ]
    env = {**os.environ, "CI": "1"}
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    try:
        wait_for(
            lambda: any((out / "logs").glob("*.parquet")) or proc.poll() is not None, 120, "a first part"
        )
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    (out / "logs" / ".deadbeef.123.tmp").write_bytes(b"PAR1 half")  # what a kill during a write leaves
    before = {p.name: p.stat().st_mtime_ns for p in (out / "logs").glob("*.parquet")}
    assert before, "the run was killed before its first part"
    res = subprocess.run(argv, capture_output=True, text=True, env=env, check=True, timeout=300)
    n = len(FLIGHTS) + 1
    assert f"{n} logs found, {len(before)} done before (skipped); analysing {n - len(before)}" in res.stdout
    after = {p.name: p.stat().st_mtime_ns for p in (out / "logs").glob("*.parquet")}
    assert all(after[k] == v for k, v in before.items())  # no finished log analysed twice
    assert not list((out / "logs").glob(".*"))  # the leftover removed
    assert _comparable(_rows(out)) == _comparable(_rows(analysed))


def _fleet_cli(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    """`magcomp fleet` in a process of its own: Dask's client threads (its IO loop, its offload thread)
    outlive the client, and the tests after these ones fork (observer and in-flight processes) only from a
    process without threads."""
    return subprocess.run(
        [sys.executable, "-m", "magcomp", "fleet", *args],
        capture_output=True,
        text=True,
        env={**os.environ, "CI": "1", **(env or {})},
        timeout=600,
    )


def test_local_dask_cluster_gives_the_same_rows(fleet: Path, analysed: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    logs = [str(fleet / "vehB" / n) for n in ("flight01.tlog", "flight02.tlog", "broken.tlog")]
    res = _fleet_cli(
        *logs,
        "--out",
        str(out),
        "--workers",
        "2",
        "--memory-limit",
        "2GiB",
        "--vehicles",
        str(fleet / "vehicles.toml"),
        "--config",
        str(fleet / "estimator_only.toml"),
    )
    assert res.returncode == 0, res.stderr
    assert "analysing 3 on a local Dask cluster" in res.stdout and "on 2 worker(s)" in res.stdout
    mine = _comparable(_rows(out))
    ref = [r for r in _comparable(_rows(analysed)) if r["sha256"] in {m["sha256"] for m in mine}]
    assert len(mine) == 3 and mine == ref


def test_local_workers_start_without_dasks_malloc_trim_threshold() -> None:
    """Dask's nanny starts each worker with MALLOC_TRIM_THRESHOLD_, which makes every large array a fresh
    mmap (diagnose ~40 % more CPU per log, magcomp/fleet/engine.py): the fleet's local workers start with the
    C library's default, as the CLI runs, also after another cluster in the same process (whose nanny leaves
    Dask's value in the process's environment). In a process of its own (Dask's threads outlive the
    client)."""
    code = (
        "import os\n"
        "from distributed import Client, LocalCluster\n"
        "from magcomp.fleet.engine import local_cluster\n"
        "if __name__ == '__main__':\n"
        "    LocalCluster(n_workers=1, threads_per_worker=1, dashboard_address=None).close()\n"
        "    assert os.environ['MALLOC_TRIM_THRESHOLD_'] == '65536'\n"
        "    cluster = local_cluster(1, '1GiB')\n"
        "    with Client(cluster) as client:\n"
        "        got = client.run(lambda: os.environ.get('MALLOC_TRIM_THRESHOLD_', 'unset'))\n"
        "        print(sorted(got.values()))\n"
        "    cluster.close()\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_TRIM_THRESHOLD_"}
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip().splitlines()[-1] == "['unset']"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_separate_scheduler_and_worker_processes_on_loopback(
    fleet: Path, analysed: Path, tmp_path: Path
) -> None:
    port = _free_port()
    addr = f"tcp://127.0.0.1:{port}"
    dask_cli = [str(Path(sys.executable).parent / "dask")]
    procs: list[subprocess.Popen[str]] = []
    try:
        sched = subprocess.Popen(
            [*dask_cli, "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
            stderr=subprocess.PIPE,
            text=True,
        )
        procs.append(sched)
        assert sched.stderr is not None
        sched_lines = LineReader(sched.stderr)
        wait_for(lambda: sched_lines.has("Scheduler at") or sched.poll() is not None, 120, "the scheduler")
        worker = subprocess.Popen(
            [
                *dask_cli,
                "worker",
                addr,
                "--nthreads",
                "1",
                "--nworkers",
                "1",
                "--memory-limit",
                "2GiB",
                "--no-dashboard",
            ],
            stderr=subprocess.PIPE,
            text=True,
        )
        procs.append(worker)
        assert worker.stderr is not None
        worker_lines = LineReader(worker.stderr)
        wait_for(lambda: worker_lines.has("Registered to") or worker.poll() is not None, 120, "the worker")
        out = tmp_path / "out"
        logs = [str(fleet / "vehA" / "flight01.tlog"), str(fleet / "vehB" / "broken.tlog")]
        res = _fleet_cli(
            *logs, "--out", str(out), "--scheduler", addr, "--vehicles", str(fleet / "vehicles.toml"),
            "--config", str(fleet / "estimator_only.toml"),
        )  # fmt: skip
        assert res.returncode == 0, res.stderr
        assert f"analysing 2 on {addr}" in res.stdout
    finally:
        for p in reversed(procs):
            p.send_signal(signal.SIGTERM)
        for p in procs:
            try:
                p.wait(timeout=60)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
    mine = _comparable(_rows(out))
    ref = [r for r in _comparable(_rows(analysed)) if r["sha256"] in {m["sha256"] for m in mine}]
    assert len(mine) == 2 and mine == ref


@pytest.mark.parametrize(
    ("argv", "fragment"),
    [
        (["{tmp}/nowhere"], "no such file or folder"),
        (["{tmp}/empty"], "no logs"),
        (["{tmp}/empty", "--vehicles", "{tmp}/bad.toml"], "--vehicles"),
        (["{tmp}/empty", "--vehicles", "{tmp}/none.toml"], "no such file"),
        (["{tmp}/empty", "--scheduler", "127.0.0.1:8786"], "tcp://HOST:8786"),
        (["{tmp}/empty", "--workers", "-1"], "--workers"),
        (["{tmp}/empty", "--memory-limit", "lots"], "--memory-limit"),
        (["{tmp}/empty", "--memory-limit", "0"], "--memory-limit"),
        (["{tmp}/empty", "--config", "{tmp}/none.toml"], "config"),
        (["report"], "usage"),
        (["report", "{tmp}/empty"], "no fleet results"),
    ],
)
def test_bad_input_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], fragment: str
) -> None:
    (tmp_path / "empty").mkdir()
    (tmp_path / "bad.toml").write_text("[vehicles]\nx = 3\n")
    args = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    rc = main(["fleet", *args, "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc != 0
    assert fragment in err
    assert err.count("\n") == 1 and err.startswith("magcomp fleet: error:")


def test_an_unreachable_scheduler_is_one_line(tmp_path: Path, fleet: Path) -> None:
    addr = f"tcp://127.0.0.1:{_free_port()}"
    res = _fleet_cli(
        str(fleet / "vehA" / "flight01.tlog"),
        "--out",
        str(tmp_path / "o"),
        "--scheduler",
        addr,
        env={"DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT": "2s"},
    )
    assert res.returncode != 0 and "cannot connect" in res.stderr
    assert res.stderr.count("\n") == 1 and res.stderr.startswith("magcomp fleet: error:")


def test_parts_are_written_whole(tmp_path: Path) -> None:
    rows = [{"sha256": "ab", "path": "x", "status": "failed", "error": "bad", "wall_s": math.nan}]
    p = store.write_part(tmp_path, "ab", rows, "9.9")
    t = pq.read_table(p)
    assert t.schema.equals(store.SCHEMA) and t.column("wall_s").to_pylist() == [None]
    assert store.done(tmp_path) == {"ab": "9.9"}
    assert not list((tmp_path / "logs").glob(".*"))


def test_report_is_one_self_contained_page(analysed: Path, tmp_path: Path) -> None:
    import base64
    from html.parser import HTMLParser

    page = tmp_path / "r" / "fleet.html"
    assert main(["fleet", "report", str(analysed), "--html", str(page)]) == 0

    class Page(HTMLParser):
        def __init__(self) -> None:
            super().__init__()
            self.images: list[str] = []
            self.links: list[str] = []
            self.cells: list[str] = []

        def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
            a = dict(attrs)
            if tag == "img":
                self.images.append(a.get("src") or "")
            for key in ("href", "src"):
                if a.get(key) and not str(a[key]).startswith(("#", "data:")):
                    self.links.append(str(a[key]))

        def handle_data(self, data: str) -> None:
            self.cells.append(data)

    p = Page()
    p.feed(page.read_text(encoding="utf-8"))
    assert p.links == []  # opens from disk: nothing fetched
    assert len(p.images) == 2  # alpha and bravo have applied flights
    for src in p.images:
        assert base64.b64decode(src.split(",", 1)[1])[:8] == b"\x89PNG\r\n\x1a\n"
    text = " ".join(p.cells)
    assert "theta changed" in text and "flight03.tlog" in text and "broken.tlog" in text
    assert text.index("bravo") < text.index("alpha")  # the inspect list: the changed vehicle first
    # what to set, from diagnose: bravo's parameters and the file holding them; diagnose's theta per log row
    assert "COMPASS_MOT_X = " in text and "bravo.param" in text
    assert "95 % per axis, free fit" in text  # the row carries per-axis half-widths, not the joint box


@pytest.mark.browser
def test_report_opens_from_disk_in_headless_chromium(analysed: Path, tmp_path: Path) -> None:
    binary = next((b for b in ("chromium", "chromium-browser", "google-chrome") if shutil.which(b)), None)
    if binary is None:
        pytest.skip("Chromium is not installed (apt-get install chromium)")
    page = tmp_path / "fleet.html"
    assert main(["fleet", "report", str(analysed), "--html", str(page)]) == 0
    # a copy with a probe: once loaded, the body carries each image's decoded width (-1: not loaded)
    probe = tmp_path / "probe.html"
    probe.write_text(
        page.read_text(encoding="utf-8").replace(
            "</body>",
            "<script>window.addEventListener('load', () => document.body.setAttribute('data-images', "
            "Array.from(document.images).map(i => i.complete ? i.naturalWidth : -1).join(',')));</script>"
            "</body>",
        ),
        encoding="utf-8",
    )
    with tempfile.TemporaryDirectory(prefix="magcomp-chromium-") as profile:
        res = subprocess.run(
            [
                binary,
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                f"--user-data-dir={profile}",
                "--virtual-time-budget=10000",
                "--dump-dom",
                probe.as_uri(),
            ],
            capture_output=True,
            text=True,
            timeout=120,
        )
    found = re.search(r'data-images="([^"]*)"', res.stdout)
    assert found is not None, res.stderr[-2000:]
    widths = [int(w) for w in found.group(1).split(",")]
    assert len(widths) == 2 and all(w > 100 for w in widths)
    assert "Vehicles to inspect" in res.stdout and "bravo" in res.stdout


def test_an_interrupted_replay_is_not_written_as_done(
    fleet: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from types import SimpleNamespace

    from magcomp.fleet import engine
    from magcomp.service import replay

    def interrupted(*args: Any, **kw: Any) -> Any:  # what replay_log returns after a ^C in its first pass
        return SimpleNamespace(interrupted=True, summary={"counts": {"mag": 10}, "compasses": []})

    monkeypatch.setattr(replay, "replay_log", interrupted)
    out = tmp_path / "out"
    p = engine.plan([fleet / "vehA" / "flight01.tlog"], out)
    with pytest.raises(KeyboardInterrupt):
        engine.run(p.tasks, out, workers=0, progress=False)
    assert store.done(out) == {}


def test_a_second_run_on_the_same_folder_is_refused(fleet: Path, tmp_path: Path) -> None:
    import fcntl

    from magcomp.errors import InputError
    from magcomp.fleet import engine

    out = tmp_path / "out"
    (out / "logs").mkdir(parents=True)
    p = engine.plan([fleet / "vehA" / "flight01.tlog"], out)
    with open(out / ".lock", "a+b") as f:  # what a running fleet holds
        fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(InputError, match="another magcomp fleet"):
            engine.run(p.tasks, out, workers=0, progress=False)
    assert store.done(out) == {}


@pytest.mark.needs_shared
def test_a_measured_log_without_theta_has_no_interference_figure(tmp_path: Path) -> None:
    log = (
        Path(__file__).parents[2].parent
        / "shared"
        / "data"
        / "measured"
        / "ardupilot_loganalyzer_nan_copter311.log"
    )
    if not log.exists():
        pytest.skip("../shared/data/measured is absent")
    out = tmp_path / "out"
    assert main(["fleet", str(log), "--out", str(out), "--workers", "0"]) == 0
    rows = _rows(out)
    assert [r["compass"] for r in rows] == [0, 1]
    for r in rows:
        assert r["status"] == "ok" and r["applied"] is False and "not observable" in r["why"]
        assert r["interference_pct"] is None and r["interference_flown_pct"] is None
        assert r["firmware"] == "ArduCopter V3.1" and r["date_utc"].year == 2014
        assert r["vehicle"] == "ardupilot:PX4v2-002600263432470A31323533"
