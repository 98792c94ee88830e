"""The command line itself: --version, help, a taken port for every server command."""

from __future__ import annotations

import socket
import subprocess
import sys
import tomllib

import pytest

from dcuscope.pipeline.config import load_config
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


def test_shipped_configurations_are_listed_run_by_name_and_copied_out(tmp_path):
    listed = run_cli("configs", cwd=tmp_path, timeout=60)
    assert listed.returncode == 0, listed.stderr
    names = {line.split()[0] for line in listed.stdout.splitlines() if line and not line.startswith("(")}
    assert names == {p.stem for p in (REPO / "configs").glob("*.yaml")}
    assert "vtest  " in listed.stdout and "One camera: the OpenCV pedestrian clip" in listed.stdout

    # By name, from a folder that holds no configs/: the shipped file, its clip found beside it.
    ran = run_cli("run", "vtest", "--num-frames", "3", cwd=tmp_path, timeout=120)
    assert ran.returncode == 0, ran.stderr
    assert any(line.startswith("infer: ") and " objects in " in line for line in ran.stderr.splitlines()), ran.stderr
    unknown = run_cli("run", "nosuch", cwd=tmp_path, timeout=60)
    assert unknown.returncode == 2 and unknown.stderr.startswith("dcuscope: error: nosuch: no such configuration file")
    assert "vtest" in unknown.stderr

    copied = run_cli("configs", "--copy", tmp_path / "mine", cwd=tmp_path, timeout=60)
    assert copied.returncode == 0, copied.stderr
    assert sorted(p.name for p in (tmp_path / "mine").iterdir()) == sorted(p.name for p in (REPO / "configs").glob("*.yaml"))
    (tmp_path / "elsewhere").mkdir()
    moved = (tmp_path / "elsewhere" / "one.yaml")
    moved.write_text((tmp_path / "mine" / "vtest.yaml").read_text())  # its clip named by absolute path: loads anywhere
    assert load_config(moved).sources[0].location == (REPO / "assets" / "media" / "vtest.avi").as_uri()
    again = run_cli("configs", "--copy", tmp_path / "mine", cwd=tmp_path, timeout=60)
    assert again.returncode == 0 and "vtest.yaml: exists, kept" in again.stdout
