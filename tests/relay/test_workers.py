"""``relay --workers N``: N relay processes of one host on one port and one PostgreSQL store. Real
relays (``python -m dcuscope.relay``, as bench_relay.py starts them, and ``dcuscope relay``), PostgreSQL 15
(tests/pgserver.py), simulated nodes."""

from __future__ import annotations

import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from dcuscope.relay.workers import worker_argv
from tests.ports import free_port
from tests.relay.helpers import ROOT, _readline, env, finish_node, get_json, load_node, start_node, stored_equals_sent


@pytest.mark.parametrize("argv", [["relay", "--port", "3000", "--workers", "4", "--db", "postgresql://h/db"],
                                  ["--port", "3000", "--workers=4", "--db", "postgresql://h/db"]])
def test_a_worker_runs_the_relay_itself_with_the_options_given_but_workers(argv):
    # From `dcuscope relay ...` and from `python -m dcuscope.relay ...` alike: before, the second made
    # `python -m dcuscope.cli --port ...`, which no worker could run.
    assert worker_argv(argv, 2, 3000) == [sys.executable, "-m", "dcuscope.relay", "--port", "3000", "--db", "postgresql://h/db",
                                          "--reuse-port", "--clock-port", "3002"]


def test_workers_share_one_port_store_what_their_nodes_send_and_stop_together(tmp_path, pg_url):
    port = free_port()
    cmd = [sys.executable, "-m", "dcuscope.relay", "--port", str(port), "--db", pg_url, "--workers", "2"]
    log = open(tmp_path / "relay.log", "wb")
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env(), stdout=subprocess.PIPE, stderr=log)
    try:
        lines = [_readline(proc, 30) for _ in range(2)]
        assert all(re.search(rf"listening on http://127\.0\.0\.1:{port} ", line) for line in lines), \
            (lines, (tmp_path / "relay.log").read_text()[-2000:])
        url = f"http://127.0.0.1:{port}"
        workers = _children(proc.pid)
        assert len(workers) == 2, workers
        # Two processes answer on the one port (the kernel deals each new connection to one of them).
        names = {get_json(f"{url}/api/health")["relay"] for _ in range(24)}
        assert len(names) == 2 and all(re.fullmatch(rf".+:{port}#\d+", n) for n in names), names
        nodes = {name: start_node(url, name, tmp_path / f"{name}.npz", frames=150, fps=200)
                 for name in ("DCU-1", "DCU-2", "DCU-3")}
        for name, node in nodes.items():
            assert finish_node(node, 90)["lost"] == 0
            stored_equals_sent(pg_url, name, load_node(tmp_path / f"{name}.npz")[1])
    finally:
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(30)
        log.close()
    assert code == 0, (tmp_path / "relay.log").read_text()[-2000:]
    assert not [pid for pid in workers if Path(f"/proc/{pid}").exists()]  # none left behind


def _children(pid: int) -> list[int]:
    try:
        return [int(c) for c in open(f"/proc/{pid}/task/{pid}/children").read().split()]
    except OSError:
        return []
