"""One page, the whole fleet: two relays on one PostgreSQL and one Redis, four real ``dcuscope run``
nodes split across them, and a page (Chromium) on relay B. The page shows all four live, those
that never connected to B included; relay A killed with SIGKILL, its nodes move to B and the page
keeps all four, live, without a reload.

Real servers: PostgreSQL 15 and redis-server from Debian (tests/pgserver.py, tests/redisserver.py),
relays as processes (``python -m dcuscope.relay``), nodes as ``dcuscope run --probes --relay A,B``.
"""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from tests.conftest import cli_env
from tests.relay.helpers import RelayProcess, get_json, kill_all, wait_for
from tests.relay.test_fleet import node_config
from tests.ui.helpers import REAL_PIPELINES

# Alone: four real pipelines, two relays, PostgreSQL, Redis and Chromium at once load 2 cores past what
# a failover within a minute needs when six other workers run too.
pytestmark = [pytest.mark.skipif(not REAL_PIPELINES, reason="needs the real dcuscope run nodes"), pytest.mark.alone]

NAMES = [f"DCU-{i}" for i in range(1, 5)]
RUN_S = 240
"""Longer than the test can last (its nodes are killed at its end): a node whose run ended stops growing."""


def held(relay: RelayProcess) -> dict[str, str]:
    """Node -> the relay holding it, for the nodes streaming now, as ``relay`` lists the fleet."""
    try:
        return {n["node"]: n["relay"] for n in get_json(f"{relay.url}/api/nodes", timeout=3)
                if n["connected"] and not n["ended"] and not n.get("stale")}
    except OSError:
        return {}


def received(page) -> dict[str, int]:
    """Frames the page received per DCU it shows."""
    return {node: s["received"] for node, s in page.evaluate("window.dcuscope.debug()")["stores"].items()}


def page_holders(page) -> dict[str, str]:
    """Node -> relay, as the page's fleet overview shows them."""
    return {r["node"]: r["relay"] for r in page.evaluate("window.dcuscope.debug()")["overview"]["rows"]}


def agree(page, relay: RelayProcess, want: dict[str, str] | None, timeout: float, what: str) -> None:
    """Wait until the page's overview names ``want`` (default: what ``relay`` lists) as each DCU's relay."""
    last = {}

    def same():
        last.update(page=page_holders(page), relay=want if want is not None else held(relay))
        return last["page"] == last["relay"]

    try:
        wait_for(same, timeout, 0.25, what=what)
    except AssertionError as exc:
        raise AssertionError(f"{exc}: the page {last.get('page')}, the relay {last.get('relay')}") from None


def all_growing(page, timeout: float, what: str) -> dict[str, int]:
    """Wait until every DCU's frame count on the page grew (it is live); returns the counts."""
    before = received(page)
    last = {}

    def grown():
        last.update(now=received(page))
        return last["now"] if set(last["now"]) == set(NAMES) and all(last["now"][n] > before.get(n, 0)
                                                                     for n in NAMES) else None

    try:
        return wait_for(grown, timeout, 0.25, what=what)
    except AssertionError as exc:
        raise AssertionError(f"{exc}: frames on the page {before} then {last.get('now')}") from None


def test_a_page_on_one_relay_shows_the_whole_fleet_and_keeps_it_when_a_relay_dies(tmp_path, pg_url, redis_server,
                                                                                 browser):
    args = ["--redis", redis_server.url]
    a = RelayProcess(pg_url, log=tmp_path / "a.log", args=[*args, "--name", "relay-a"])
    b = RelayProcess(pg_url, log=tmp_path / "b.log", args=[*args, "--name", "relay-b"])
    nodes = {}
    page = None
    try:
        for i, name in enumerate(NAMES):
            order = f"{a.url},{b.url}" if i % 2 == 0 else f"{b.url},{a.url}"  # DCU-1, DCU-3 on A first
            cmd = [sys.executable, "-m", "dcuscope.cli", "run", str(node_config(tmp_path, name)), "--probes",
                   "--relay", order, "--duration", str(RUN_S), "-q"]
            nodes[name] = subprocess.Popen(cmd, cwd=tmp_path, env=cli_env(), stderr=subprocess.PIPE, text=True)
        split = {"DCU-1": "relay-a", "DCU-2": "relay-b", "DCU-3": "relay-a", "DCU-4": "relay-b"}
        wait_for(lambda: held(b) == split, 90, 0.5, what="four nodes streaming, two on each relay")

        page = browser.new_page()
        page.goto(b.url)
        all_growing(page, 30, "the page on B drawing all four DCUs live, A's two included")
        # Some of the DCUs drawn on B's page stream to A only.
        wait_for(lambda: any(held(b).get(n) == "relay-a" for n in NAMES), 20, 0.25, what="DCUs held by A listed on B")
        agree(page, b, None, 10, "the page's overview naming each DCU's relay")
        page.evaluate("window.stillTheSamePage = true")

        a.kill9()
        killed = time.monotonic()
        everyone_on_b = {name: "relay-b" for name in NAMES}
        wait_for(lambda: held(b) == everyone_on_b, 60, 0.5, what="A's nodes resumed on B")
        moved = time.monotonic() - killed
        counts = all_growing(page, 60, "the page drawing all four live again")
        assert page.evaluate("window.stillTheSamePage === true")  # no reload
        agree(page, b, everyone_on_b, 10, "the page's overview naming B as the holder of all four")
        debug = page.evaluate("window.dcuscope.debug()")
        assert sorted(debug["stores"]) == NAMES and debug["overview"]["total"] == 4
        print(f"\nfleet page: A's nodes on B {moved:.1f} s after SIGKILL; frames on the page {counts}")
    except BaseException:
        for name in ("a", "b"):  # what the relays said: the first thing to read when this fails
            log = tmp_path / f"{name}.log"
            print(f"--- relay {name}'s log ---\n" + (log.read_text()[-4000:] if log.exists() else "(none)"))
        raise
    finally:
        if page is not None:
            page.close()
        kill_all(nodes.values())
        a.stop()
        b.stop()
