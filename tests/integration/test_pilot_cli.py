"""What a new user meets on the command line: a failed replay leaves no recording, `run` on a listening link
says how to feed it (and that command works), `--rerun serve` says where it really listens."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from magcomp.adapters.rerun_viz import listening_hosts, serve_notice
from magcomp.cli import main
from magcomp.commands.run import feed_hint
from tests.waiting import finish, start_magcomp, wait_for

REPO = Path(__file__).parents[2]


def test_replay_of_a_missing_log_leaves_no_recording(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    pytest.importorskip("rerun")
    rrd = tmp_path / "x.rrd"
    assert main(["replay", str(tmp_path / "missing.tlog"), "--rerun", f"save={rrd}"]) != 0
    assert "no such file" in capsys.readouterr().err
    assert not rrd.exists()


def test_replay_of_a_log_without_compass_leaves_no_recording(tmp_path: Path) -> None:
    pytest.importorskip("rerun")
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate
    from tests.conftest import split_tlog_records

    full = tmp_path / "f.tlog"
    write_tlog(simulate(SimConfig(scenario="tumble", duration_s=5.0, seed=1)), full)
    heartbeats = [r for r in split_tlog_records(full.read_bytes()) if r[15:18] == b"\0\0\0"]  # HEARTBEAT
    assert heartbeats
    log = tmp_path / "hb.tlog"
    log.write_bytes(b"".join(heartbeats))
    rrd = tmp_path / "y.rrd"
    assert main(["replay", str(log), "--rerun", f"save={rrd}"]) != 0
    assert not rrd.exists()


def test_feed_hint_only_for_listening_links() -> None:
    hint = feed_hint("udpin:0.0.0.0:14550")
    assert hint is not None and "magcomp simulate --link udpout:127.0.0.1:14550" in hint
    assert "--out udp:127.0.0.1:14550" in hint
    tcp = feed_hint("tcpin:0.0.0.0:5760")
    assert tcp is not None and "tcpout:127.0.0.1:5760" in tcp
    assert feed_hint("udpout:10.0.0.2:14550") is None and feed_hint("/dev/ttyACM0:115200") is None


@pytest.mark.slow
def test_run_says_how_to_feed_it_and_that_command_works(tmp_path: Path) -> None:
    from magcomp.service.demo import free_udp_port

    port = free_udp_port()
    summary = tmp_path / "sum.json"
    rrd = tmp_path / "run.rrd"
    proc, out, err = start_magcomp("run", "--master", f"udpin:127.0.0.1:{port}", "--state-dir",
                                   str(tmp_path / "state"), "--json", str(summary), "--rerun",
                                   f"save={rrd}")  # fmt: skip
    try:
        wait_for(lambda: out.has("magcomp simulate --link") or proc.poll() is not None, 60.0, "the hint")
        hint = next(ln for ln in out.lines if "magcomp simulate --link" in ln)
        command = hint.rsplit("`magcomp ", 1)[1].split("`", 1)[0].split()  # the command the user would run
        wait_for(lambda: err.has("listening on udpin:") or proc.poll() is not None, 60.0, "listening")
        assert main([*command, "--scenario", "tumble", "--duration", "8", "--speed", "20"]) == 0
        wait_for(lambda: out.has("compass 0") or err.has("state: compass 0") or proc.poll() is not None,
                 60.0, "data")  # fmt: skip
    finally:
        proc.send_signal(signal.SIGTERM)
        code = finish(proc)
    assert code == 0, err.join()
    assert json.loads(summary.read_text())["published"] > 0
    # run's view: theta, the headings, the bias, and the battery's current and voltage are in the recording
    from rerun.chunk import RrdReader

    rows: dict[str, int] = {}
    for chunk in RrdReader(str(rrd)).stream():
        batch = chunk.to_record_batch()
        if "Scalars:scalars" in batch.schema.names:  # data rows, not the static series styles
            rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + batch.num_rows
    for path in ("/theta/x", "/heading/corrected", "/bias/estimate", "/power/current", "/power/voltage"):
        assert rows.get(path, 0) > 0, (path, rows)


def test_listening_hosts_reads_the_real_bind_address() -> None:
    if listening_hosts(1) is None:
        pytest.skip("no /proc/net on this system")
    for host in ("127.0.0.1", "0.0.0.0"):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.bind((host, 0))
            s.listen()
            assert listening_hosts(s.getsockname()[1]) == {host}


def test_serve_notice_says_where_it_listens() -> None:
    url = "http://127.0.0.1:9090/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A9876%2Fproxy"
    everywhere = serve_notice(url, 9876, 9090, {"0.0.0.0"})
    assert url in everywhere and "every network interface" in everywhere
    local = serve_notice(url, 9876, 9090, {"127.0.0.1"})
    assert "127.0.0.1 only" in local and "ssh -L 9090:127.0.0.1:9090 -L 9876:127.0.0.1:9876" in local
    assert "serve=0.0.0.0" in local


def test_serve_address_is_parsed() -> None:
    from magcomp.adapters.rerun_viz import parse_mode
    from magcomp.errors import MagcompError

    assert parse_mode("serve").target == "127.0.0.1"
    assert parse_mode("serve=0.0.0.0").target == "0.0.0.0"
    with pytest.raises(MagcompError, match="serve=ADDRESS"):
        parse_mode("serve=everywhere")


SERVE = """
import sys
from magcomp.adapters.rerun_viz import open_viz
viz = open_viz(sys.argv[3], live=False, grpc_port=int(sys.argv[1]), web_port=int(sys.argv[2]))
print(viz.notice.replace("\\n", " | "), flush=True)
sys.stdin.read()
"""


def _process_tree(pid: int) -> set[int]:
    """``pid`` and every process below it (read from /proc/*/stat)."""
    parents: dict[int, int] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        parents[int(stat.parent.name)] = int(fields[1])
    tree = {pid}
    grew = True
    while grew:
        below = {p for p, pp in parents.items() if pp in tree} - tree
        tree |= below
        grew = bool(below)
    return tree


def _tcp_listening(pids: set[int]) -> set[tuple[str, int]]:
    """(address, port) of every listening TCP socket (v4 and v6) that a process in ``pids`` holds."""
    import ipaddress

    inodes: set[str] = set()
    for pid in pids:
        for fd in Path(f"/proc/{pid}/fd").glob("*"):
            try:
                target = os.readlink(fd)
            except OSError:
                continue
            if target.startswith("socket:["):
                inodes.add(target[8:-1])
    found = set()
    for name in ("tcp", "tcp6"):
        for line in Path(f"/proc/net/{name}").read_text().splitlines()[1:]:
            parts = line.split()
            if parts[3] != "0A" or parts[9] not in inodes:  # 0A: LISTEN
                continue
            addr_hex, port_hex = parts[1].split(":")
            raw = bytes.fromhex(addr_hex)
            packed = b"".join(raw[i : i + 4][::-1] for i in range(0, len(raw), 4))
            found.add((str(ipaddress.ip_address(packed)), int(port_hex, 16)))
    return found


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/net/tcp").exists(), reason="needs Linux's /proc")
@pytest.mark.parametrize("mode", ["serve", "serve=0.0.0.0"])
def test_every_server_of_rerun_serve_is_on_loopback_unless_told_otherwise(mode: str) -> None:
    """Every listening socket of the process and its children (the recording's gRPC server and the web
    page's server) is on 127.0.0.1 by default, the printed URL names those two ports, and the page loads;
    ``serve=0.0.0.0`` opts in to every interface."""
    pytest.importorskip("rerun")
    import urllib.request
    from urllib.parse import parse_qs, unquote, urlparse

    from magcomp.adapters.rerun_viz import free_port

    gport, wport = free_port(), free_port()
    env = {**os.environ, "PYTHONPATH": str(REPO), "RERUN_ANALYTICS": "0"}
    cmd = [sys.executable, "-c", SERVE, str(gport), str(wport), mode]
    proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env)  # fmt: skip
    try:
        assert proc.stdout is not None
        notice = proc.stdout.readline()
        url = notice.split("Rerun web viewer: ", 1)[1].split(" | ", 1)[0].strip()
        want = {gport, wport}
        ports = lambda: {p for _, p in _tcp_listening(_process_tree(proc.pid))}  # noqa: E731
        wait_for(lambda: want <= ports(), 30.0, "both servers")
        sockets = _tcp_listening(_process_tree(proc.pid))
        with urllib.request.urlopen(url, timeout=10.0) as page:
            html = page.read().decode("utf-8", "replace").lower()
    finally:
        proc.communicate(timeout=60)  # closes stdin: the child ends, its pipes are read and closed
    page_url = urlparse(url)
    data_url = urlparse(unquote(parse_qs(page_url.query)["url"][0]))
    assert (page_url.hostname, page_url.port) == ("127.0.0.1", wport), url
    assert (data_url.scheme, data_url.hostname, data_url.port) == ("rerun+http", "127.0.0.1", gport), url
    assert "re_viewer_bg.wasm" in html
    assert {p for _, p in sockets} == want, sockets  # no other server
    if mode == "serve":
        assert {a for a, _ in sockets} == {"127.0.0.1"}, sockets  # nothing offered to the network
        assert "127.0.0.1 only" in notice and f"ssh -L {wport}:127.0.0.1:{wport} -L {gport}" in notice
    else:
        assert {a for a, _ in sockets} == {"0.0.0.0"}, sockets
        assert "every network interface" in notice
