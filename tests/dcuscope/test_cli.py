"""The command line itself: --version, help, a taken port for every server command."""

from __future__ import annotations

import socket
import subprocess
import sys
import tomllib

import pytest

from tests.conftest import REPO, VTEST, cli_env, run_cli


def test_version_is_the_packages():
    result = run_cli("--version", timeout=60)
    expected = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["version"]
    assert result.returncode == 0 and result.stdout.strip() == f"dcuscope {expected}", result.stdout + result.stderr


def test_run_help_has_no_empty_heading():
    result = run_cli("run", "--help", timeout=60)
    assert result.returncode == 0
    assert result.stdout.count("examples:") == 1 and "examples:\n  dcuscope run configs/" in result.stdout


@pytest.mark.parametrize("command", [["relay", "--db", "{tmp}/r.db"], ["demo", "--db", "{tmp}/d.db"],
                                     ["serve-rtsp", str(VTEST)]], ids=["relay", "demo", "serve-rtsp"])
def test_a_taken_port_exits_2_with_one_line_naming_it(tmp_path, command):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        args = [a.format(tmp=tmp_path) for a in command]
        result = subprocess.run([sys.executable, "-m", "dcuscope.cli", *args, "--port", str(port)], cwd=tmp_path,
                                env=cli_env(), capture_output=True, text=True, timeout=60)
    assert result.returncode == 2, result.stdout + result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"dcuscope: error: --port {port}: cannot listen on "), lines
    assert "starting" not in result.stdout and not (tmp_path / "d.db").exists()
