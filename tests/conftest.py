"""Shared fixtures: the repository, the shipped assets, running the real CLI."""

from __future__ import annotations

import atexit
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from tests.pipeline.lossylink import lossy_link  # noqa: F401 - a fixture, for the tests of every package

REPO = Path(__file__).resolve().parents[1]
ASSETS = REPO / "assets"
VTEST = ASSETS / "media" / "vtest.avi"
BIKES = ASSETS / "media" / "bikes.mp4"


def shares_a_module_fixture(item: pytest.Item) -> bool:
    info = getattr(item, "_fixtureinfo", None)
    chains = info.name2fixturedefs.values() if info is not None else ()
    return any(d.scope in ("module", "class") for chain in chains for d in chain)


def pytest_itemcollected(item: pytest.Item) -> None:
    """For parallel workers (``make test``: pytest-xdist, ``--dist loadgroup``): the tests of a
    module that share a module- or class-scoped fixture (a pipeline run, a relay, a browser) go to
    one worker, in order, so that the fixture runs once; every other test goes wherever a worker
    is free. (Marked as each test is collected: xdist reads the marks in its own
    ``pytest_collection_modifyitems``.) Without xdist the marks are inert."""
    if getattr(item.config.option, "loadgroup", False) and shares_a_module_fixture(item):
        item.add_marker(pytest.mark.xdist_group(item.module.__name__))


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Under ``--dist loadgroup`` the groups come first, then the tests marked ``long``: a group
    cannot be split, and a long test started last would hold the whole run up while the other
    workers idle."""
    if not getattr(config.option, "loadgroup", False):
        return
    # stable: the order is kept within each
    items.sort(key=lambda item: (not any(item.iter_markers("xdist_group")), not any(item.iter_markers("long"))))


def pytest_configure(config: pytest.Config) -> None:
    # xdist tells its scheduler a test's group by a suffix to the test's id, which pytest 9 no longer
    # shows: groups would be split, their fixtures run on every worker, tests that run in order broken.
    if config.getoption("dist", "no") == "loadgroup" and int(pytest.__version__.split(".")[0]) >= 9:
        raise pytest.UsageError(f"pytest {pytest.__version__} hides pytest-xdist's test groups (--dist loadgroup): "
                                "install the versions in constraints.txt (make setup)")


# Every node command spools unacknowledged events under $XDG_STATE_HOME/dcuscope/spool and drains
# what earlier runs left there to its own relay: tests must not see each other's runs (nor the
# user's). A folder per worker (session fixtures), per module (module fixtures: autouse ones come
# first in their scope) and per test.
os.environ["XDG_STATE_HOME"] = tempfile.mkdtemp(prefix="dcuscope-state-")
atexit.register(shutil.rmtree, os.environ["XDG_STATE_HOME"], True)


@pytest.fixture(autouse=True, scope="module")
def module_spool(tmp_path_factory):
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("XDG_STATE_HOME", str(tmp_path_factory.mktemp("module-state")))
        yield


@pytest.fixture(autouse=True)
def own_spool(module_spool, tmp_path_factory, monkeypatch) -> None:
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path_factory.mktemp("state")))


@pytest.fixture(scope="session")
def repo() -> Path:
    return REPO


def cli_env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env.setdefault("GST_DEBUG", "0")
    return env


def run_cli(*args: str, cwd: Path | None = None, timeout: float = 240,
            env: dict | None = None) -> subprocess.CompletedProcess:
    """Run ``dcuscope ARGS`` as a user would, in a real process (``env``: variables to add)."""
    return subprocess.run([sys.executable, "-m", "dcuscope.cli", *map(str, args)], cwd=cwd or REPO,
                          env={**cli_env(), **(env or {})}, capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="session")
def real_traces(tmp_path_factory) -> dict:
    """Two real traces (tests/realtraces.py), made once per worker."""
    from tests import realtraces

    return realtraces.make(tmp_path_factory.mktemp("traces"), cli_env())


@pytest.fixture(scope="session")
def gst_registered():
    from dcuscope import plugins

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


@pytest.fixture(scope="session")
def postgres():
    """This worker's PostgreSQL server (tests/pgserver.py), started at first use."""
    from tests.pgserver import PostgresServer

    server = PostgresServer().start()
    yield server
    server.close()


@pytest.fixture
def pg_url(postgres) -> str:
    """The URL of an empty database of its own on this worker's PostgreSQL server."""
    return postgres.new_database()


@pytest.fixture
def redis_server():
    """A Redis server of the test's own (tests/redisserver.py), on loopback, stopped after."""
    from tests.redisserver import RedisServer

    server = RedisServer().start()
    yield server
    server.close()
