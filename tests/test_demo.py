"""make demo's main command, checked as a user would: through the relay's HTTP API."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
import urllib.request

from tests.conftest import cli_env

FIVE = ("mux", "infer", "tiler", "convert", "osd")


def get(url: str):
    with urllib.request.urlopen(url, timeout=5) as response:
        return json.loads(response.read())


def test_demo_runs_two_dcus_that_report_all_five_stages(tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    url = f"http://127.0.0.1:{port}"
    demo = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "demo", "--duration", "60", "--port", str(port),
                             "--db", str(tmp_path / "demo.db")], cwd=tmp_path, env=cli_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        seen: dict[str, dict] = {}
        deadline = time.monotonic() + 55
        while time.monotonic() < deadline and len(seen) < 2:
            time.sleep(3)
            try:
                nodes = get(f"{url}/api/nodes")
            except OSError:
                continue
            for node in nodes:
                stats = get(f"{url}/api/stats?node={node['node']}")
                if all((stats["stages"].get(stage) or {}).get("count", 0) > 0 for stage in FIVE):
                    seen[node["node"]] = stats
        assert set(seen) == {"DCU-1", "DCU-2"}, seen.keys()
        for stats in seen.values():
            assert stats["frame"]["count"] > 0 and stats["frame"]["mean_ms"] > 0
        output, _ = demo.communicate(timeout=90)
    finally:
        if demo.poll() is None:
            demo.kill()
    assert demo.returncode == 0, output
    assert f"open {url}/" in output and "demo: stopped" in output and "Traceback" not in output
