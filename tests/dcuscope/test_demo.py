"""make demo's main command, checked as a user would: how it stops, from a checkout. Its two DCUs
reporting every stage through the relay's API is checked from an installed dcuscope
(tests/dcuscope/test_wheel.py), with the same helpers."""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from tests.conftest import cli_env
from tests.ports import free_port

FIVE = ("mux", "infer", "tiler", "convert", "osd")


def get(url: str):
    with urllib.request.urlopen(url, timeout=5) as response:
        return json.loads(response.read())


def start_demo(tmp_path: Path, port: int, *args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "dcuscope.cli", "demo", "--port", str(port),
                             "--db", str(tmp_path / "demo.db"), *args], cwd=tmp_path, env=cli_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def demo_children(port: int) -> list[int]:
    """PIDs of the relay and pipelines a demo on ``port`` started (found by their command lines)."""
    marks = (f"http://127.0.0.1:{port}".encode(), f"--port\0{port}\0".encode())
    pids = []
    for entry in Path("/proc").iterdir():
        try:
            cmdline = (entry / "cmdline").read_bytes()
        except OSError:  # not a process, or gone
            continue
        if b"dcuscope.cli" in cmdline and b"demo\0" not in cmdline and any(m in cmdline for m in marks):
            pids.append(int(entry.name))
    return pids


STATUS = re.compile(r"^demo: (DCU-[12]): +[\d.]+ fps, frame delay +[\d.]+ ms, "
                    r"(bottleneck \w+ \(\d+ % busy\)|no stage saturated \(busiest \w+ \d+ % busy\))$", re.MULTILINE)
"""The status says which stage limits each DCU and how busy it is (or that none is saturated), one
line per DCU: both on one line would run past a terminal's width."""


def statuses(output: str) -> set[str]:
    """The DCUs a status line gave a verdict for."""
    return {m.group(1) for m in STATUS.finditer(output)}


def test_a_demo_with_a_duration_ends_by_itself_and_takes_its_children_with_it(tmp_path):
    port = free_port()
    demo = start_demo(tmp_path, port, "--duration", "5")
    try:
        output, _ = demo.communicate(timeout=90)
        deadline = time.monotonic() + 45
        while time.monotonic() < deadline and demo_children(port):
            time.sleep(0.5)
        assert demo_children(port) == [], "children outlived the demo"
    finally:
        if demo.poll() is None:
            demo.kill()
        for pid in demo_children(port):
            os.kill(pid, signal.SIGKILL)
    assert demo.returncode == 0, output
    assert f"open http://127.0.0.1:{port}/" in output and "demo: stopped" in output and "Traceback" not in output


@pytest.mark.parametrize("how", ["SIGTERM", "SIGKILL"])
def test_a_stopped_or_killed_demo_leaves_no_pipeline_or_relay_running(tmp_path, how):
    """SIGTERM (systemd, docker stop, kill) stops the demo like Ctrl-C; after SIGKILL, which it
    cannot see, its children still end, told by the kernel that their parent died."""
    port = free_port()
    demo = start_demo(tmp_path, port)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and len(demo_children(port)) < 3:
            time.sleep(0.5)
        children = demo_children(port)
        assert len(children) == 3, children  # the relay and two pipelines
        demo.send_signal(getattr(signal, how))
        # Its output ends when the last child does: after SIGKILL the relay dies at once and the
        # pipelines wait for it their close timeout (the demo's 10 s, ~9 s measured; with run's
        # default of 60 s, they went on for 59 s).
        output, _ = demo.communicate(timeout=30)
        deadline = time.monotonic() + 45
        while time.monotonic() < deadline and demo_children(port):
            time.sleep(0.5)
        assert demo_children(port) == [], "children outlived the demo"
    finally:
        if demo.poll() is None:
            demo.kill()
        for pid in demo_children(port):
            os.kill(pid, signal.SIGKILL)
    if how == "SIGTERM":
        assert demo.returncode == 128 + signal.SIGTERM, output
        assert "SIGTERM received, stopping" in output and "demo: stopped" in output and "Traceback" not in output
    else:
        assert demo.returncode == -signal.SIGKILL


def test_a_demo_on_a_taken_port_says_so_and_starts_nothing(tmp_path):
    """Another relay on the port would answer for the demo's own and receive its DCUs' events."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        demo = start_demo(tmp_path, port, "--duration", "5")
        output, _ = demo.communicate(timeout=60)
    assert demo.returncode == 2, output
    assert f"--port {port}: cannot listen on 127.0.0.1:{port}" in output, output
    assert "starting" not in output and "Traceback" not in output, output
    assert demo_children(port) == []
