"""Shared fixtures: the repository, the shipped assets, running the real CLI."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.pipeline.lossylink import lossy_link  # noqa: F401 - a fixture, for the tests of every package

REPO = Path(__file__).resolve().parents[1]
ASSETS = REPO / "assets"
VTEST = ASSETS / "media" / "vtest.avi"
BIKES = ASSETS / "media" / "bikes.mp4"


@pytest.fixture(scope="session")
def repo() -> Path:
    return REPO


def cli_env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env.setdefault("GST_DEBUG", "0")
    return env


def run_cli(*args: str, cwd: Path | None = None, timeout: float = 240) -> subprocess.CompletedProcess:
    """Run ``dcuscope ARGS`` as a user would, in a real process."""
    return subprocess.run([sys.executable, "-m", "dcuscope.cli", *map(str, args)], cwd=cwd or REPO, env=cli_env(),
                          capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="session")
def gst_registered():
    import plugins

    plugins.register()


def wait_until_mapped(proc: subprocess.Popen, library: str, timeout: float = 60) -> None:
    """Until ``proc`` has loaded a shared library whose path contains ``library``: a point in its
    start-up that is known to come before its main loop is running."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.poll() is None:
        if library in Path(f"/proc/{proc.pid}/maps").read_text():
            return
        time.sleep(0.005)
    raise AssertionError(f"{library} never loaded")
